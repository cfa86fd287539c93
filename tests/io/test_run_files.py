"""The files of a run (services/saving.py): TUM written a pose at a time, the maps' files from their frames, read
back with standard readers (plyfile, networkx, numpy) and with semloc's own."""

from __future__ import annotations

import json
import math

import networkx
import numpy as np
import plyfile
import pytest

from schemas import FrameError, Header, decode, encode
from schemas.loopclosure import TopoMap
from schemas.mapping import VoxelMap
from semloc_core.geometry import pose2d_to_transform
from semloc_core.io.semantic_map import load_semantic_map
from semloc_core.io.trajectory import TUM_HEADER, read_tum, tum_line
from semloc_core.io.voxel_map import load_voxel_map
from semloc_core.mapping import VoxelGrid
from semloc_core.mapping.volume import hot_voxels
from services.saving import TumStream, write_maps
from tests.service.conftest import file_size_limit

CLASSES = ("bowl", "mug")


def test_tum_lines_keep_nanosecond_stamps_exactly():
    line = tum_line(1_733_360_000_123_456_789, np.eye(4))
    assert line.split()[0] == "1733360000.123456789"
    assert tum_line(5, np.eye(4)).split()[0] == "0.000000005"
    with pytest.raises(ValueError):
        tum_line(0, np.full((4, 4), np.nan))


def test_tum_stream_one_line_per_stamp_in_time_order(tmp_path):
    stream = TumStream(tmp_path / "t.tum")
    stream.add(10**9, 1.0, 2.0, 0.5)
    stream.add(2 * 10**9, 1.5, 2.0, 0.5)
    stream.add(2 * 10**9, 3.0, -1.0, -math.pi / 2)  # a newer estimate of the same stamp replaces its line
    stream.add(10**9, 9.0, 9.0, 0.0)  # older than the last line: skipped
    stream.add(3 * 10**9, 3.0, -1.5, 3.0)
    assert (stream.lines, stream.skipped) == (3, 1)
    # flushed as it goes: readable while still open
    stamps, poses = read_tum(tmp_path / "t.tum")
    stream.close()
    assert stamps.tolist() == [1.0, 2.0, 3.0]
    expected = [pose2d_to_transform(1.0, 2.0, 0.5), pose2d_to_transform(3.0, -1.0, -math.pi / 2),
                pose2d_to_transform(3.0, -1.5, 3.0)]
    assert np.allclose(poses, expected, atol=1e-8)
    assert np.all(poses[:, 2, 3] == 0)  # planar body pose: z = 0, yaw only


def test_a_restarted_writer_continues_the_file(tmp_path):
    stream = TumStream(tmp_path / "t.tum")
    for second in (1, 2, 3):
        stream.add(second * 10**9 + 5, float(second), 0.0, 0.0)
    stream.close()
    with open(tmp_path / "t.tum", "ab") as crashed:  # killed in the middle of a line
        crashed.write(b"4.000000000 4.0 0.0")
    resumed = TumStream(tmp_path / "t.tum", resume=True)
    assert (resumed.lines, resumed.last_stamp_ns, resumed.cut_short) == (3, 3 * 10**9 + 5, 19)
    resumed.add(2 * 10**9, 9.0, 9.0, 0.0)  # older than the file's last line: skipped
    resumed.add(3 * 10**9 + 5, 3.5, 0.0, 0.0)  # the last stamp again: its line replaced
    resumed.add(4 * 10**9, 4.0, 0.0, 0.0)
    resumed.close()
    stamps, poses = read_tum(tmp_path / "t.tum")
    assert stamps.tolist() == [1.000000005, 2.000000005, 3.000000005, 4.0]
    assert poses[:, 0, 3].tolist() == [1.0, 2.0, 3.5, 4.0]
    TumStream(tmp_path / "t.tum").close()  # a new run starts afresh
    assert (tmp_path / "t.tum").read_text() == TUM_HEADER + "\n"


def a_voxel_map(seed: int = 0) -> VoxelMap:
    grid = VoxelGrid(np.array([-0.5, -0.4, 0.7]), 0.05, (20, 16, 6))
    rng = np.random.default_rng(seed)
    volumes = rng.random((len(CLASSES), *grid.volume_shape), dtype=np.float32)
    header = Header(robot="r1", stream="mapper/save", stamp_ns=42, frame_id="world")
    return VoxelMap(header=header, class_names=CLASSES, class_index=np.array([0, 1], np.int32),
                    positions=np.array([[0.1, 0.2, 0.8], [-0.2, 0.1, 0.75]]), has_height=np.array([True, True]),
                    sizes=np.array([[0.1, 0.1, 0.05], [0.08, 0.08, 0.1]]), scores=np.array([0.9, 0.7]),
                    existence=np.array([0.95, 0.8]), bounds=np.array([[-0.5, -0.4], [0.5, 0.4]]), frames=17,
                    origin=grid.origin, voxel_size=grid.voxel_size, score_volumes=volumes,
                    views=np.full(grid.volume_shape, 3.0, np.float32))


def a_topomap() -> TopoMap:
    header = Header(robot="r1", stream="loopclosure/topomap", stamp_ns=9)
    return TopoMap(header=header, keyframes=np.array([0, 3, 5]), keyframe_stamps_ns=np.array([100, 400, 600]),
                   frame_node=np.array([0, 0, 1, 1, 2, 2, 0]), edges=np.array([[0, 1], [1, 2], [0, 2]]),
                   transitions=np.array([1, 1, 1]),
                   keyframe_poses=np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.3], [np.nan, np.nan, np.nan]]))


def test_the_maps_files_parse_with_standard_readers(tmp_path):
    frame = decode(encode(a_voxel_map()), expected=VoxelMap)  # as it arrives from the mapper
    written = write_maps(tmp_path, frame, a_topomap(), hot_fraction=0.9)
    assert sorted(p.name for p in written) == sorted(["objects.json", "voxels.npz", "voxels.ply", "topomap.json",
                                                      "topomap.graphml"])
    objects = load_semantic_map(tmp_path / "objects.json")  # the localizer's reader
    assert objects.class_names == CLASSES and np.allclose(objects.positions, frame.positions)
    assert np.allclose(objects.existence, [0.95, 0.8])
    voxels = load_voxel_map(tmp_path / "voxels.npz")
    assert np.array_equal(voxels["scores"], frame.score_volumes) and int(voxels["frames"]) == 17
    assert dict(np.load(tmp_path / "voxels.npz", allow_pickle=False))["class_names"].tolist() == list(CLASSES)
    cloud = plyfile.PlyData.read(str(tmp_path / "voxels.ply"))["vertex"]
    expected = hot_voxels(frame.score_volumes, VoxelGrid(frame.origin, frame.voxel_size, (20, 16, 6)), 0.9)
    assert cloud.count == len(expected["score"]) > 0
    assert np.allclose(np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1), expected["points"], atol=1e-6)
    assert np.array_equal(cloud["score"], expected["score"])
    # every point's score is at least 0.9 of its class's best
    best = frame.score_volumes.reshape(len(CLASSES), -1).max(axis=1)
    assert np.all(cloud["score"] >= 0.9 * best[cloud["class_index"].astype(int)] - 1e-6)
    graph = networkx.read_graphml(tmp_path / "topomap.graphml")
    assert sorted(graph.nodes) == ["n0", "n1", "n2"] and graph.number_of_edges() == 3
    assert (graph.nodes["n1"]["x"], graph.nodes["n1"]["y"], graph.nodes["n1"]["theta"]) == (1.0, 0.5, 0.3)
    assert graph.nodes["n1"]["stamp_ns"] == 400 and "x" not in graph.nodes["n2"]  # unknown pose: no position
    document = json.loads((tmp_path / "topomap.json").read_text())
    assert [node["pose"] for node in document["nodes"]] == [[0.0, 0.0, 0.0], [1.0, 0.5, 0.3], None]
    assert [node["frames"] for node in document["nodes"]] == [[0, 1, 6], [2, 3], [4, 5]]


def test_the_same_maps_give_the_same_bytes(tmp_path):
    write_maps(tmp_path / "a", a_voxel_map(), a_topomap())
    write_maps(tmp_path / "b", a_voxel_map(), a_topomap())
    for path in (tmp_path / "a").iterdir():
        assert path.read_bytes() == (tmp_path / "b" / path.name).read_bytes(), path.name
    write_maps(tmp_path / "c", a_voxel_map(seed=1), None)
    assert (tmp_path / "c" / "voxels.npz").read_bytes() != (tmp_path / "a" / "voxels.npz").read_bytes()


@pytest.mark.parametrize("row, reason", [([np.nan, 1.0, 0.0], "nonfinite"), ([np.inf, 0.0, 0.0], "nonfinite"),
                                         ([2e7, 0.0, 0.0], "range")])
def test_key_frame_poses_are_known_or_nan_throughout(row, reason):
    frame = a_topomap()
    poses = np.array(frame.keyframe_poses)
    poses[0] = row
    with pytest.raises(FrameError) as error:  # as a worker receives it
        decode(encode(TopoMap.model_construct(**{**dict(frame), "keyframe_poses": poses})))
    assert error.value.reason == reason


def test_voxel_volumes_must_match_the_classes():
    frame = a_voxel_map()
    with pytest.raises(FrameError, match="score_volumes"):
        decode(encode(VoxelMap.model_construct(**{**dict(frame), "score_volumes": frame.score_volumes[:1]})))


def test_a_full_disk_never_leaves_a_partial_file(tmp_path):
    """Writes the disk refuses (here a file size limit) leave every earlier file whole and no temporary file; the
    trajectory's lines wait and are written, in order, once the disk takes them again."""
    stream = TumStream(tmp_path / "t.tum")
    stream.add(10**9, 1.0, 0.0, 0.0)
    write_maps(tmp_path, a_voxel_map(), a_topomap())
    earlier = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with file_size_limit((tmp_path / "t.tum").stat().st_size + 10):  # room for part of a line, for no map
        for second in (2, 3, 4):
            with pytest.raises(OSError) as refused:
                stream.add(second * 10**9, float(second), 0.0, 0.0)
        with pytest.raises(OSError) as refused_map:
            write_maps(tmp_path, a_voxel_map(seed=1), a_topomap())
        assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == earlier
    assert refused.value.filename == str(tmp_path / "t.tum") and refused.value.strerror == "File too large"
    assert refused_map.value.filename == str(tmp_path / "voxels.npz")
    assert stream.pending == 3
    stream.add(5 * 10**9, 5.0, 0.0, 0.0)
    stream.close()
    stamps, poses = read_tum(tmp_path / "t.tum")
    assert stamps.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0] and poses[:, 0, 3].tolist() == [1.0, 2.0, 3.0, 4.0, 5.0]


def test_a_file_cut_within_its_header_is_resumed_with_a_header(tmp_path):
    """The power cut before the header's line end reached the disk: the resumed file starts afresh, header first."""
    path = tmp_path / "t.tum"
    stream = TumStream(path)
    stream.add(10**9, 1.0, 0.0, 0.0)
    stream.close()
    for cut in (0, 1, len(TUM_HEADER)):
        path.write_bytes(path.read_bytes()[:cut])
        resumed = TumStream(path, resume=True)
        resumed.add(2 * 10**9, 2.0, 0.0, 0.0)
        resumed.close()
        assert path.read_text().splitlines()[0] == TUM_HEADER
        assert read_tum(path)[0].tolist() == [2.0]
