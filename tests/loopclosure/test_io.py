"""Loop-closure files: no pickle, atomic, validated; the rtabmap-style folder reader."""

from __future__ import annotations

import json
import zipfile

import cv2
import numpy as np
import pytest

from semloc_core.io.loopclosure import (
    LoopClosureFileError,
    load_engine_state,
    load_features,
    load_topomap,
    load_vocabulary,
    read_loop_samples,
    save_engine_state,
    save_features,
    save_topomap,
    save_vocabulary,
)
from semloc_core.loopclosure.bow import Vocabulary
from semloc_core.loopclosure.features import FeatureSequence
from semloc_core.loopclosure.topomap import build_topological_map


def test_engine_state_file_holds_no_pickle(tmp_path):
    path = tmp_path / "state.npz"
    arrays = {"a": np.arange(5), "b": np.ones((2, 3), np.float32)}
    save_engine_state(path, arrays, {"format": "x", "frames": 3})
    got, meta = load_engine_state(path)
    assert meta == {"format": "x", "frames": 3} and np.array_equal(got["a"], arrays["a"])
    with np.load(path, allow_pickle=False) as archive:  # readable without pickle
        assert set(archive.files) == {"a", "b", "__meta__"}
    assert not (tmp_path / "state.npz.tmp").exists()
    with pytest.raises(ValueError, match="pickle"):
        save_engine_state(tmp_path / "bad.npz", {"o": np.array([{}], dtype=object)}, {})


def test_corrupt_files_raise_one_error_type(tmp_path):
    path = tmp_path / "broken.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(LoopClosureFileError):
        load_engine_state(path)
    with zipfile.ZipFile(tmp_path / "empty.npz", "w"):
        pass
    with pytest.raises(LoopClosureFileError):
        load_vocabulary(tmp_path / "empty.npz")


def test_vocabulary_and_feature_cache_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    vocabulary = Vocabulary(rng.random((8, 128)) * 50, rng.random(8))
    save_vocabulary(tmp_path / "v.npz", vocabulary)
    again = load_vocabulary(tmp_path / "v.npz")
    assert np.array_equal(again.centers, vocabulary.centers) and np.array_equal(again.idf, vocabulary.idf)
    sequences = [FeatureSequence.from_unsorted(rng.uniform(-3, 3, k), rng.integers(0, 255, (k, 128)).astype(np.uint8))
                 for k in (0, 5, 17)]
    save_features(tmp_path / "f.npz", sequences, {"camera": "pinhole"})
    loaded, meta = load_features(tmp_path / "f.npz")
    assert meta["camera"] == "pinhole" and [len(s) for s in loaded] == [0, 5, 17]
    for a, b in zip(sequences, loaded):
        assert np.array_equal(a.bearings, b.bearings) and np.array_equal(a.descriptors, b.descriptors)


def test_topomap_files(tmp_path):
    topomap = build_topological_map(20, [(1, 15), (2, 16)], 1)
    save_topomap(tmp_path / "map.json", topomap)
    save_topomap(tmp_path / "map.graphml", topomap)
    assert np.array_equal(load_topomap(tmp_path / "map.json").frame_node, topomap.frame_node)
    assert json.loads((tmp_path / "map.json").read_text())["format"] == "semloc.topomap"
    assert (tmp_path / "map.graphml").read_text().startswith("<?xml")
    with pytest.raises(ValueError):
        save_topomap(tmp_path / "map.txt", topomap)


def test_read_loop_samples_layout(tmp_path):
    (tmp_path / "images").mkdir()
    for k in range(1, 12):  # 1..11: numeric, not lexicographic, order
        cv2.imwrite(str(tmp_path / "images" / f"{k}.jpg"), np.full((8, 8, 3), k, np.uint8))
    gt = np.zeros((11, 11), np.uint8)
    gt[10, 2] = 255  # row = later frame, column = earlier
    cv2.imwrite(str(tmp_path / "samples_GT.bmp"), gt)
    images, truth = read_loop_samples(tmp_path)
    assert [p.name for p in images][:3] == ["1.jpg", "2.jpg", "3.jpg"] and images[-1].name == "11.jpg"
    assert truth.shape == (11, 11) and truth[2, 10] and truth.sum() == 1
    cv2.imwrite(str(tmp_path / "samples_GT.bmp"), np.zeros((5, 5), np.uint8))
    with pytest.raises(LoopClosureFileError, match="11x11"):
        read_loop_samples(tmp_path)
