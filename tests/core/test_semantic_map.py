import json

import numpy as np
import pytest

from semloc_core.io.semantic_map import MapFormatError, SemanticMap, load_semantic_map, save_semantic_map


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_roundtrip(tmp_path, suffix):
    semantic_map = SemanticMap.from_objects(
        [
            {"class": "bowl", "position": [0.1, 0.2, 0.75], "size": [0.15, 0.15, 0.06]},
            {"class": "cap", "position": [0.4, -0.3]},
            {"class": "bowl", "position": [-0.2, 0.0, 0.74], "score": 0.5},
        ],
        bounds=[[-1, -1], [1, 1]],
        free_space=[[[-1, -1], [1, -1], [1, 1], [-1, 1]]],
    )
    path = tmp_path / f"map{suffix}"
    save_semantic_map(semantic_map, path)
    loaded = load_semantic_map(path)
    assert loaded.class_names == ("bowl", "cap")
    assert loaded.class_index.tolist() == [0, 1, 0]
    np.testing.assert_allclose(loaded.positions, semantic_map.positions)
    assert loaded.has_height.tolist() == [True, False, True]
    assert loaded.objects_of("bowl").tolist() == [0, 2]
    assert loaded.objects_of("clock").size == 0
    assert len(loaded.free_space) == 1


@pytest.mark.parametrize(
    "document, message",
    [
        ({"objects": [{"class": "bowl", "position": [0.0]}]}, "position"),
        ({"objects": [{"class": "bowl", "position": [0.0, float("nan")]}]}, "finite"),
        ({"objects": [{"class": "", "position": [0.0, 1.0]}]}, "class"),
        ({"objects": [{"class": "bowl", "position": [0, 1], "colour": "red"}]}, "colour"),
        ({"objects": [], "version": 9}, "version"),
        ({"objects": [], "format": "other"}, "format"),
        ({"objects": []}, "bounds"),
        ({"objects": [], "bounds": {"min": [1, 1], "max": [0, 0]}}, "below"),
        ([1, 2], "mapping"),
    ],
)
def test_rejects_bad_documents(tmp_path, document, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(document))
    with pytest.raises(MapFormatError, match=message):
        load_semantic_map(path)


def test_unreadable_and_unparseable(tmp_path):
    with pytest.raises(MapFormatError, match="cannot read"):
        load_semantic_map(tmp_path / "missing.json")
    path = tmp_path / "broken.yaml"
    path.write_text("objects: [unclosed")
    with pytest.raises(MapFormatError, match="not valid"):
        load_semantic_map(path)
