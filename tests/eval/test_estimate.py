"""`semloc eval localization DATASET --set estimate=FILE.tum`: a trajectory computed elsewhere, scored with the
filter runs' figures against the data set's ground truth on the frames whose stamps it has."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from semloc_core.experiments.localization import LocalizationSpec, evaluate_estimate
from semloc_core.geometry import pose2d_to_transform
from semloc_core.io.dataset import open_dataset
from semloc_core.io.trajectory import read_tum, write_planar_tum, write_tum


@pytest.fixture(scope="module")
def dataset(sim_dataset):
    return Path(sim_dataset("tabletop", frames=24, seed=0))


def test_the_body_ground_truth_file_is_the_planar_pose(dataset):
    data = open_dataset(dataset)
    stamps, poses = read_tum(dataset / "groundtruth_body.tum")
    assert np.array_equal(np.round(stamps * 1e9).astype(np.int64), data.stamps_ns)
    assert np.allclose(poses, [pose2d_to_transform(*p) for p in data.poses2d], atol=1e-8)
    camera_heights = read_tum(dataset / "groundtruth.txt")[1][:, 2, 3]
    assert np.all(poses[:, 2, 3] == 0) and np.all(camera_heights > 1.0)  # the camera's file is another frame


def test_an_estimate_is_scored_on_its_own_frames(dataset, tmp_path):
    data = open_dataset(dataset)
    frames = np.arange(0, len(data), 2)
    offsets = np.where(frames < 12, 0.3, 0.05)  # 0.3 m east, then 0.05 m
    estimate = data.poses2d[frames] + np.stack([offsets, np.zeros_like(offsets), np.zeros_like(offsets)], axis=1)
    stamps = np.concatenate([data.stamps_ns[frames], [data.stamps_ns[-1] + 10**9]])  # and one stamp past the end
    write_planar_tum(tmp_path / "est.tum", stamps, np.vstack([estimate, estimate[-1:]]))
    spec = LocalizationSpec(dataset=str(dataset), estimate=str(tmp_path / "est.tum"))
    report = evaluate_estimate(spec, data).report
    assert report["frame_indices"] == frames.tolist() and report["unmatched_stamps"] == 1
    metrics = report["runs"]["estimate"]["metrics"]
    assert metrics["rmse_m"] == pytest.approx(math.sqrt(np.mean(offsets ** 2)), abs=1e-9)
    # under the table-top threshold (0.10 m) from its 7th frame to the end
    assert metrics["time_to_converge_frames"] == 6
    assert metrics["rmse_after_convergence_m"] == pytest.approx(0.05, abs=1e-9)
    assert max(metrics["heading_errors_deg"]) == pytest.approx(0, abs=1e-6)


def test_an_estimate_without_one_frame_of_the_dataset_is_refused(dataset, tmp_path):
    write_tum(tmp_path / "far.tum", np.array([1e6]), np.eye(4)[None])
    with pytest.raises(ValueError, match="no stamp"):
        evaluate_estimate(LocalizationSpec(dataset=str(dataset), estimate=str(tmp_path / "far.tum")),
                          open_dataset(dataset))


def test_a_live_runs_file_cut_short_is_scored_up_to_the_cut(dataset, tmp_path):
    """The power cut while the saver writes trajectory.tum: the file ends anywhere in a line (its unflushed tail
    lost). The estimate is scored on every whole line before the cut, and one message says the file was cut and
    where; a last line without its line end may have lost digits and still parse: it is dropped too."""
    from services.saving import TumStream

    data = open_dataset(dataset)
    path = tmp_path / "trajectory.tum"
    stream = TumStream(path)
    for stamp, pose in zip(data.stamps_ns, data.poses2d):
        stream.add(int(stamp), *pose)
    stream.close()
    whole = path.read_bytes()
    line_ends = [i + 1 for i, byte in enumerate(whole) if byte == ord("\n")][1:]  # after the header
    for cut in range(line_ends[-3] - 1, len(whole) + 1, 7):
        path.write_bytes(whole[:cut])
        said = []
        report = evaluate_estimate(LocalizationSpec(dataset=str(dataset), estimate=str(path)), data,
                                   log=said.append).report
        expected = sum(end <= cut for end in line_ends)
        assert report["frames"] == expected and report["frame_indices"] == list(range(expected)), cut
        cuts = [line for line in said if "was cut short" in line]
        assert len(cuts) == (0 if cut in line_ends else 1), (cut, said)
        if cuts:
            assert cuts[0].startswith(f"{path} was cut short: its last line ({expected + 2}) has no line end")
