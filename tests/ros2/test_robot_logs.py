"""Robot logs read whole: a ROS 2 bag (sqlite3, MCAP storage, the bare .mcap file) of a simulated run gives back the
data set it was written from - images, stamps, camera model, per-image camera mount, odometry between images and
ground truth - through the camera worker's source."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.io.dataset import open_dataset
from services.camera_sources import SourceError, classify, open_source
from services.ros2 import messages as ros
from services.ros2.logs import LogTopics
from tests.ros2.robot_log import EPOCH_NS, write_ros2_bag


@pytest.fixture(scope="module")
def dataset_dir(sim_dataset):
    return sim_dataset("tabletop", frames=24, seed=0)


@pytest.mark.parametrize("storage, bare_file", [("sqlite3", False), ("mcap", False), ("mcap", True)])
def test_a_ros2_bag_gives_back_the_run(tmp_path, dataset_dir, storage, bare_file):
    dataset = open_dataset(dataset_dir)
    bag = write_ros2_bag(dataset_dir, tmp_path / "bag", storage=storage)
    path = next(bag.glob("*.mcap")) if bare_file else bag
    assert classify(str(path)) == ("mcap" if bare_file else "bag")
    source = open_source(str(path))
    assert "ground truth /ground_truth/odom" in source.description
    np.testing.assert_array_equal(source.camera.K, dataset.camera.K)
    np.testing.assert_allclose(source.camera.T_body_cam, dataset.T_body_cam[0], atol=1e-12)
    captures = list(source)
    source.close()
    assert [c.stamp_ns - EPOCH_NS for c in captures] == dataset.stamps_ns.tolist()
    expected_odometry = dataset.odometry.as_array()
    for index, capture in enumerate(captures):
        np.testing.assert_array_equal(capture.images[0], dataset.image(index))
        np.testing.assert_allclose(capture.T_world_body, dataset.T_world_body[index], atol=1e-12)
        np.testing.assert_allclose(capture.T_body_cam[0], dataset.T_body_cam[index], atol=1e-12)
        if index == 0:
            assert capture.odometry is None
        else:
            np.testing.assert_allclose(capture.odometry, expected_odometry[index], atol=1e-9)


def test_odometry_from_tf_and_topics_chosen_by_name(tmp_path, dataset_dir):
    bag = write_ros2_bag(dataset_dir, tmp_path / "bag")
    by_tf = list(open_source(str(bag), log=LogTopics(odometry="tf", ground_truth="none")))
    by_topic = list(open_source(str(bag)))
    assert by_tf[5].T_world_body is None
    np.testing.assert_allclose([c.odometry for c in by_tf[1:]], [c.odometry for c in by_topic[1:]], atol=1e-12)
    with pytest.raises(SourceError, match="no odometry topic /wheel"):
        open_source(str(bag), log=LogTopics(odometry="/wheel"))
    with pytest.raises(SourceError, match="no image topic /nothing"):
        open_source(str(bag), topic="/nothing")


def test_ros1_camera_info_fields():
    """ROS 1 bags keep their definitions' upper-case names (D, K)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    K = np.array([[400.0, 0, 160], [0, 410.0, 120], [0, 0, 1]])
    header = types["std_msgs/msg/Header"](seq=0, stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                          frame_id="cam")
    info = types["sensor_msgs/msg/CameraInfo"](
        header=header, height=240, width=320, distortion_model="plumb_bob", D=np.array([0.1, 0, 0, 0, 0]),
        K=K.reshape(-1), R=np.eye(3).reshape(-1), P=np.zeros(12), binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    data = store.serialize_ros1(info, "sensor_msgs/msg/CameraInfo")
    camera = ros.camera_from_info(store.deserialize_ros1(data, "sensor_msgs/msg/CameraInfo"), np.eye(4))
    np.testing.assert_array_equal(camera.K, K)
    np.testing.assert_array_equal(camera.dist, [0.1, 0, 0, 0, 0])


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_cut_short_gives_its_images_up_to_the_cut(tmp_path, dataset_dir, storage):
    """`ros2 bag record` killed, or the power cut: the folder has no metadata.yaml (written last) and its storage file
    lost its tail. The folder, and the file alone, play every image whole before the cut (the log's own images,
    stamps and ground truth, in order), and say once where it stopped; the folder without metadata.yaml but whole
    plays all; a file cut before its first topic is refused, naming it."""
    from services.cut_files import CUT_SHORT

    dataset = open_dataset(dataset_dir)
    bag = write_ros2_bag(dataset_dir, tmp_path / "bag", storage=storage)
    (bag / "metadata.yaml").unlink()
    [file] = bag.iterdir()
    data = file.read_bytes()
    rgb = [np.ascontiguousarray(dataset.image(i)[..., ::-1]).tobytes() for i in range(len(dataset))]
    # MCAP (uncompressed) keeps each image's pixels in one piece; sqlite3 spreads them over overflow pages
    image_ends = [data.find(pixels) + len(pixels) for pixels in rgb]
    assert classify(str(bag)) == "bag"

    def played(path):
        source = open_source(str(path))
        captures = list(source)
        source.close()
        for index, capture in enumerate(captures):
            np.testing.assert_array_equal(capture.images[0], dataset.image(index))
            np.testing.assert_allclose(capture.T_world_body, dataset.T_world_body[index], atol=1e-12)
        assert [c.stamp_ns - EPOCH_NS for c in captures] == dataset.stamps_ns[:len(captures)].tolist()
        return len(captures), source.skipped

    assert played(bag) == (len(dataset), {CUT_SHORT: 1})  # whole, but the recorder did not finish
    for fraction in (0.15, 0.5, 0.85):
        cut = int(len(data) * fraction)
        file.write_bytes(data[:cut])
        for path in (bag, file):
            count, skipped = played(path)
            assert skipped == {CUT_SHORT: 1}
            if storage == "mcap":  # exactly the images whole before the cut
                assert count == sum(end <= cut for end in image_ends), fraction
            else:  # the rows before the first page lost: no more images than fit before the cut, at most 2 fewer
                assert int(fraction * len(dataset)) - 2 <= count <= cut // len(rgb[0]), (fraction, count)
    file.write_bytes(data[:100])
    with pytest.raises(SourceError, match=f"cannot open robot log {bag}"):
        open_source(str(bag))


@pytest.mark.parametrize("storage, bare_file", [("sqlite3", False), ("mcap", False), ("mcap", True)])
def test_export_of_a_robot_log_says_it_is_one(tmp_path, dataset_dir, storage, bare_file, capsys):
    """`semloc export` takes a semloc recording (the workers' results); given a robot log (its folder was once 'no
    such recording') it exits 2 with one line naming the log and what to do instead, and writes nothing."""
    from services.cli import main

    bag = write_ros2_bag(dataset_dir, tmp_path / "bag", storage=storage)
    path = next(bag.glob("*.mcap")) if bare_file else bag
    assert main(["export", str(path), "-o", str(tmp_path / "out")]) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line == f"semloc export: {path} is a robot log, not a semloc recording: play it into a graph (semloc " \
                   "replay) while semloc record writes one, and export that"
    assert not (tmp_path / "out").exists()
