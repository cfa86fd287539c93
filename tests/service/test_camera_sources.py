"""Camera worker sources (in process): folder, video, ROS 1/2 bags, MCAP (ROS 2 and semloc recordings), data set."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from schemas import decode, keys
from services.camera_sources import DatasetSource, SourceError, classify, open_source, ros_image_to_bgr
from tests.service.conftest import make_image_folder, wait_until

RNG = np.random.default_rng(3)


def _frames(count: int, shape=(24, 32, 3)) -> list[np.ndarray]:
    return [RNG.integers(0, 256, shape, dtype=np.uint8) for _ in range(count)]


def test_folder_is_naturally_sorted_with_timestamps(tmp_path):
    files = make_image_folder(tmp_path, 12)
    (tmp_path / "timestamps.txt").write_text("# seconds file\n" + "".join(
        f"{100 + 0.5 * i:.3f} {f.name}\n" for i, f in reversed(list(enumerate(files)))))
    source = open_source(str(tmp_path))
    assert classify(str(tmp_path)) == "folder"
    captures = list(source)
    assert len(captures) == 12
    for index, (capture, file) in enumerate(zip(captures, files)):
        np.testing.assert_array_equal(capture.images[0], cv2.imread(str(file)))
        assert capture.stamp_ns == int(round((100 + 0.5 * index) * 1e9))


def test_folder_timestamp_errors(tmp_path):
    make_image_folder(tmp_path, 3)
    (tmp_path / "timestamps.txt").write_text("1.0\n0.5\n2.0\n")
    with pytest.raises(SourceError, match="increasing"):
        open_source(str(tmp_path))
    (tmp_path / "timestamps.txt").write_text("1.0\n")
    with pytest.raises(SourceError, match="1 timestamps for 3 images"):
        open_source(str(tmp_path))


def test_video_file(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    frames = [np.full((24, 32, 3), 20 * i, np.uint8) for i in range(10)]
    for frame in frames:
        writer.write(frame)
    writer.release()
    source = open_source(str(path))
    captures = list(source)
    source.close()
    assert len(captures) == 10 and source.fps == pytest.approx(10.0)
    for index, capture in enumerate(captures):
        assert abs(float(capture.images[0].mean()) - 20 * index) < 3
    assert [c.stamp_ns for c in captures] == [int(round(i * 1e8)) for i in range(10)]


def _noise_video(path) -> bytearray:
    """60 frames of noise (its own seed: the damage below must hit the same frames whichever tests ran first) as an
    mp4v video at 10 fps; its bytes."""
    rng = np.random.default_rng(0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (64, 48))
    for _ in range(60):
        writer.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    writer.release()
    return bytearray(path.read_bytes())


def test_a_damaged_stretch_of_a_video_is_skipped_and_counted(tmp_path):
    """OpenCV's read() fails on each frame of a damaged stretch, then decodes the frames after it: the source skips
    and counts them and goes on (it once stopped at the first, a third of the way in, as if the video had ended)."""
    path = tmp_path / "clip.mp4"
    data = _noise_video(path)
    middle = len(data) // 2
    data[middle : middle + 2000] = bytes(2000)
    path.write_bytes(bytes(data))
    source = open_source(str(path))
    skips = []
    source.on_skip = lambda why, detail: skips.append((why, detail))
    stamps = [capture.stamp_ns for capture in source]
    source.close()
    skipped = source.skipped["undecodable video frames"]
    assert 0 < skipped < 10 and len(stamps) == 60 - skipped, (len(stamps), source.skipped)
    assert stamps[-1] == int(round(59 * 1e8)) and np.all(np.diff(stamps) > 0)  # the container's clock, to the end
    assert set(stamps) <= {int(round(i * 1e8)) for i in range(60)}
    assert len(skips) == skipped and skips[0][1].endswith("cannot be decoded: skipped")


def test_a_video_shorter_than_its_container_says_is_reported(tmp_path):
    path = tmp_path / "clip.mp4"
    data = _noise_video(path)
    start, end = data.find(b"mdat") + 4, data.find(b"moov") - 4  # the frames' data; the index after it
    cut = (start + end) // 2
    data[cut:end] = bytes(end - cut)  # the second half of the frames is gone, the index still counts them
    path.write_bytes(bytes(data))
    source = open_source(str(path))
    skips = []
    source.on_skip = lambda why, detail: skips.append(detail)
    count = sum(1 for _ in source)
    source.close()
    assert 0 < count < 45 and source.skipped == {"video ended early": 1}
    assert skips == [f"{path}: ended after {count} frames of the 60 its container declares"]


def _ros_image(typestore, pixels: np.ndarray, stamp_ns: int, encoding: str, ros1: bool):
    Image = typestore.types["sensor_msgs/msg/Image"]
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    header_fields = {"stamp": Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), "frame_id": "cam"}
    if ros1:
        header_fields["seq"] = 0
    data = pixels[..., ::-1] if encoding == "rgb8" else pixels
    return Image(header=Header(**header_fields), height=pixels.shape[0], width=pixels.shape[1], encoding=encoding,
                 is_bigendian=0, step=pixels.shape[1] * (3 if pixels.ndim == 3 else 1),
                 data=np.ascontiguousarray(data).reshape(-1))


@pytest.mark.parametrize("flavour", ["ros2", "ros1"])
def test_ros_bags(tmp_path, flavour):
    from rosbags.typesys import Stores, get_typestore

    frames = _frames(4)
    stamps = [1_000_000_000 + i * 50_000_000 for i in range(4)]
    if flavour == "ros2":
        from rosbags.rosbag2 import Writer

        typestore = get_typestore(Stores.ROS2_HUMBLE)
        path = tmp_path / "bag2"
        with Writer(path, version=9) as writer:
            connection = writer.add_connection("/cam/image", "sensor_msgs/msg/Image", typestore=typestore)
            for pixels, stamp in zip(frames, stamps):
                msg = _ros_image(typestore, pixels, stamp, "rgb8", ros1=False)
                writer.write(connection, stamp, typestore.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    else:
        from rosbags.rosbag1 import Writer

        typestore = get_typestore(Stores.ROS1_NOETIC)
        path = tmp_path / "session.bag"
        with Writer(path) as writer:
            connection = writer.add_connection("/cam/image", "sensor_msgs/msg/Image", typestore=typestore)
            for pixels, stamp in zip(frames, stamps):
                msg = _ros_image(typestore, pixels, stamp, "bgr8", ros1=True)
                writer.write(connection, stamp, typestore.serialize_ros1(msg, "sensor_msgs/msg/Image"))
    assert classify(str(path)) == "bag"
    source = open_source(str(path), topic="/cam/image")
    captures = list(source)
    source.close()
    assert [c.stamp_ns for c in captures] == stamps
    for capture, pixels in zip(captures, frames):
        np.testing.assert_array_equal(capture.images[0], pixels)


def test_mcap_with_ros2_images(tmp_path):
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    frames = _frames(3, shape=(8, 10))
    path = tmp_path / "ros.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2")  # as `ros2 bag record` writes it: profile ros2, ros2msg definitions
        definition, _ = typestore.generate_msgdef("sensor_msgs/msg/Image", ros_version=2)
        schema = writer.register_schema("sensor_msgs/msg/Image", "ros2msg", definition.encode())
        channel = writer.register_channel("/mono", "cdr", schema)
        for index, pixels in enumerate(frames):
            msg = _ros_image(typestore, pixels, 5 + index, "mono8", ros1=False)
            writer.add_message(channel, log_time=index, data=typestore.serialize_cdr(msg, "sensor_msgs/msg/Image"),
                               publish_time=index)
        writer.finish()
    captures = list(open_source(str(path), grayscale=True))
    assert [c.stamp_ns for c in captures] == [5, 6, 7]
    for capture, pixels in zip(captures, frames):
        np.testing.assert_array_equal(capture.images[0], pixels)


def test_mcap_semloc_recording_plays_as_a_camera(tmp_path):
    from mcap.writer import Writer

    from schemas import Header, Image, camera_image, encode

    frames = _frames(3)
    path = tmp_path / "semloc.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        channel = writer.register_channel("semloc/r1/camera/front/image", "semloc",
                                          writer.register_schema("semloc.Image", "jsonschema", b"{}"))
        for index, pixels in enumerate(frames):
            frame = Image(header=Header(robot="r1", seq=index, stamp_ns=1000 + index),
                          images=[camera_image(pixels, T_body_cam=np.eye(4))])
            writer.add_message(channel, log_time=index, data=encode(frame), publish_time=index)
        writer.finish()
    captures = list(open_source(str(path)))
    assert [c.stamp_ns for c in captures] == [1000, 1001, 1002]
    np.testing.assert_array_equal(captures[2].images[0], frames[2])
    np.testing.assert_array_equal(captures[0].T_body_cam[0], np.eye(4))


@pytest.mark.parametrize("encoding", ["mono16", "bgra8", "rgba8"])
def test_ros_image_encodings(encoding):
    class Msg:
        height, width, is_bigendian = 2, 3, 0

    msg = Msg()
    msg.encoding = encoding
    if encoding == "mono16":
        grey = np.array([[0, 256, 512], [65535, 1024, 2048]], dtype="<u2")
        msg.step, msg.data = 6, grey.view(np.uint8).reshape(-1)
        np.testing.assert_array_equal(ros_image_to_bgr("sensor_msgs/msg/Image", msg, grayscale=True), grey >> 8)
    else:
        pixels = RNG.integers(0, 256, (2, 3, 4), dtype=np.uint8)
        msg.step, msg.data = 12, pixels.reshape(-1)
        expected = pixels[..., :3] if encoding == "bgra8" else pixels[..., 2::-1]
        np.testing.assert_array_equal(ros_image_to_bgr("sensor_msgs/msg/Image", msg), expected)


def test_dataset_source_gives_ground_truth_and_odometry():
    from semloc_core.camera import PinholeCamera
    from semloc_core.geometry import pose2d_to_transform
    from semloc_core.io import dataset as dataset_module

    frames = _frames(3)
    poses = np.stack([pose2d_to_transform(0.5 * i, 0.0, 0.1 * i) for i in range(3)])
    odometry = dataset_module.Odometry(np.array([0, 5.0, 5.0]), np.array([0, 0.1, 0.1]), np.array([0, 1.0, 1.0]),
                                       np.array([0, 0.1, 0.1]))
    dataset = dataset_module.Dataset("tiny", 3, camera=PinholeCamera.from_fov(32, 24, 60.0),
                                     stamps_ns=np.array([10, 20, 30]), T_world_body=poses,
                                     T_body_cam=np.stack([np.eye(4)] * 3), odometry=odometry,
                                     image_source=lambda i: frames[i])
    captures = list(DatasetSource(dataset))
    assert [c.stamp_ns for c in captures] == [10, 20, 30]
    np.testing.assert_array_equal(captures[1].images[0], frames[1])
    np.testing.assert_allclose(captures[2].T_world_body, poses[2])
    assert captures[0].odometry is None and captures[1].odometry == (5.0, 0.1, 1.0, 0.1)
    np.testing.assert_array_equal(captures[1].T_body_cam[0], np.eye(4))


def test_unknown_sources_are_reported(tmp_path):
    with pytest.raises(SourceError, match="not found"):
        open_source(str(tmp_path / "nothing.avi"))
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(SourceError, match="cannot tell"):
        classify(str(tmp_path / "notes.txt"))
    with pytest.raises(SourceError, match="no images"):
        open_source(str(tmp_path), source_type="folder")


@pytest.mark.service
def test_a_looping_camera_keeps_its_source_clock_increasing_at_a_set_rate(procs, hub, session, sim_dataset):
    """A data set played at ``rate`` and looped: each lap's stamps are the first lap's moved on by one lap (images
    and odometry alike), never back in time. (They once started over at a set rate: a looping camera's stamps went
    back each lap, and the loop-closure worker's key-frame gate, measuring time since its last key-frame, closed.)"""
    dataset = sim_dataset("tabletop", frames=6, seed=0)
    stamps: dict[str, list[int]] = {"image": [], "odometry": []}
    for name, key in (("image", keys.camera_image("r1", "front")), ("odometry", keys.odometry("r1"))):
        session.declare_subscriber(key, lambda sample, name=name: stamps[name].append(
            decode(sample.payload.to_bytes()).header.stamp_ns))
    procs.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--set", f"source={dataset}", "--set",
                 "rate=30", "--set", "loop=true", "--set", "wait_for_subscriber_s=20", name="camera")
    wait_until(lambda: len(stamps["image"]) >= 15 and len(stamps["odometry"]) >= 15, 60,
               message=lambda: f"three laps of images and odometry\n{procs.log('camera')[-2000:]}")
    images = np.array(stamps["image"][:15], dtype=np.int64)
    assert np.all(np.diff(images) > 0), images
    lap = images[6] - images[0]
    assert lap > images[5] - images[0]  # one lap on, and a frame period more
    np.testing.assert_array_equal(images[6:12] - images[:6], np.full(6, lap))
    odometry = np.array(stamps["odometry"][:12], dtype=np.int64)  # an image's odometry carries its stamp
    assert np.all(np.diff(odometry) > 0) and set(odometry) <= set(stamps["image"]), (odometry, images)


def test_a_folder_of_unreadable_images_is_a_bad_source(tmp_path):
    for index in range(3):
        (tmp_path / f"{index}.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    with pytest.raises(SourceError, match="none of the 3 images in .* can be read"):
        list(open_source(str(tmp_path)))


@pytest.mark.service
def test_the_camera_skips_unreadable_and_odd_sized_frames_counts_them_and_goes_on(procs, hub, session, tmp_path):
    """A folder with an unreadable image and frames of another size in the middle: the camera publishes every other
    frame, in order, and its status says what it skipped and why (degraded while it does). (An unreadable image
    once stopped the camera with exit code 2; frames of another size went on the wire with the first frame's model.)"""
    from schemas import Status
    from services.bus import query

    files = make_image_folder(tmp_path / "images", 12, shape=(24, 32, 3))
    files[4].write_bytes(b"\x89PNG\r\n\x1a\n damaged")
    for index in (7, 8):
        cv2.imwrite(str(files[index]), np.zeros((12, 16, 3), np.uint8))
    camera = tmp_path / "camera.yaml"
    camera.write_text("image_width: 32\nimage_height: 24\n"
                      "camera_matrix: {rows: 3, cols: 3, data: [30, 0, 15.5, 0, 30, 11.5, 0, 0, 1]}\n")
    received = []
    session.declare_subscriber(keys.camera_image("r1", "front"), lambda sample: received.append(
        int(decode(sample.payload.to_bytes()).images[0].pixels()[0, 0, 0])))
    procs.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--set", f"source={tmp_path / 'images'}",
                 "--set", f"calibration={camera}", "--set", "rate=20", "--set", "exit_at_end=false",
                 "--set", "wait_for_subscriber_s=20", "--set", "status_period_s=0.2", name="camera")
    expected = [0, 1, 2, 3, 5, 6, 9, 10, 11]  # the marker pixel of each frame published (make_image_folder's)

    def finished():
        frames = query(session, keys.robot_statuses("r1"), reply_type=Status, timeout=2.0, every_reply=True)
        status = next((f for f in frames if f.worker == "camera"), None)
        return status is not None and status.details.get("frames_published") == len(expected) and status

    status = wait_until(finished, 60, interval=0.2, message=lambda: f"the source played\n{procs.log('camera')[-3000:]}")
    assert received == expected
    assert status.state == "degraded" and "unreadable images: 1 frame(s) skipped" in status.state_reason
    assert "frames not 32x24 like the camera model: 2 frame(s) skipped" in status.state_reason
    assert status.details["frames_skipped"] == 3
    log = procs.log("camera")
    assert f"cannot read image {files[4]}: skipped" in log and "frame 8 is 16x12, the camera model 32x24" in log
    assert "source finished after 9 frames; skipped: 1 unreadable images, 2 frames not 32x24 like the camera model" \
        in log
