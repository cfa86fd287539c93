"""The wire contract: round trips, zero-copy decoding, strict validation, keys, registration, JSON Schema."""

from __future__ import annotations

import struct
import time

import cv2
import msgpack
import numpy as np
import pytest

from schemas import (
    Ack,
    Array,
    CameraModel,
    EquirectangularSpec,
    Frame,
    FrameError,
    Header,
    Image,
    Odometry,
    PinholeSpec,
    Pose2D,
    Pose3D,
    Status,
    camera_image,
    decode,
    encode,
    export,
    frame_types,
    keys,
)
from schemas.detection import CameraHeatmapLevels, HeatmapLevels
from schemas.mapping import ObjectMap, ObjectMapV1
from schemas.status import InputStats, LogTail

HEADER = Header(robot="r1", stream="test", seq=7, stamp_ns=1_700_000_000_123_456_789, frame_id="cam0")
RNG = np.random.default_rng(0)


def _rotation_z(angle: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    return T


def _frames() -> dict[str, Frame]:
    K = np.array([[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]])
    return {
        "image_bgr": Image.from_pixels(HEADER, RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)),
        "image_mono": Image.from_pixels(HEADER, RNG.integers(0, 256, (48, 64), dtype=np.uint8)),
        "image_rig": Image(header=HEADER, images=[
            camera_image(RNG.integers(0, 256, (20, 30, 3), dtype=np.uint8), camera=0, T_body_cam=_rotation_z(0.3)),
            camera_image(RNG.integers(0, 256, (20, 30, 3), dtype=np.uint8), camera=1, encoding="rgb8"),
        ]),
        "camera_model_rig": CameraModel(header=HEADER, name="rig", cameras=[
            PinholeSpec(width=640, height=480, K=K, dist=np.array([0.1, -0.05, 0.001, 0.002, 0.01]),
                        T_body_cam=_rotation_z(1.0)),
            EquirectangularSpec(width=1024, height=512, T_body_cam=np.eye(4), lat_top=1.2, lat_bottom=-1.0),
        ]),
        "odometry": Odometry(header=HEADER, v=0.5, omega=-0.1, dt=0.1, covariance=np.diag([0.01, 0.001, 0.002])),
        "pose2d": Pose2D(header=HEADER, x=1.0, y=-2.0, theta=3.0, covariance=np.eye(3) * 0.1),
        "pose3d": Pose3D.from_matrix(HEADER, _rotation_z(2.5) @ np.diag([1.0, 1.0, 1.0, 1.0]), child_frame_id="cam0",
                                     covariance=np.eye(6)),
        "status": Status(header=HEADER, worker="w", kind="sink", state="running", pid=12, started_ns=5, uptime_s=1.5,
                         received=3, latency_p50_ms=0.5, inputs={"a": InputStats(key="k", policy="latest", dropped=2)}),
        "ack": Ack(header=HEADER, ok=False, message="no map yet"),
        "log_tail": LogTail(header=HEADER, launcher="ops-1", graph="ops"),
        "heatmap_levels": HeatmapLevels(header=HEADER, classes=("bowl", "mug"), detector="linear",
                                        level_scales=(1.2, 0.85, 0.6), maps=[CameraHeatmapLevels(
                                            image_width=64, image_height=48, scale=1 / 255,
                                            scores=RNG.integers(0, 256, (2, 3, 12, 16), dtype=np.uint8))]),
        "object_map": ObjectMap(header=HEADER, **OBJECT_COLUMNS, existence=np.array([0.9, 1.0])),
        "object_map_v1": ObjectMapV1(header=HEADER, **OBJECT_COLUMNS),
        "past_poses": _past_poses_frame(),
        "topomap_update_poses": _topomap_update(),
    }


def _topomap_update(**changes):
    """Frame 2 placed, frame 1's pose withdrawn (NaN row), after frame 3 of a map of 4 frames and 2 places."""
    from schemas.loopclosure import TopoMapUpdate

    return TopoMapUpdate(**{"header": HEADER, "frames": 4, "nodes": 2, "assigned": np.array([[3, 1]], np.int64),
                            "new_nodes": np.zeros((0, 2), np.int64), "edges_added": np.zeros((0, 2), np.int64),
                            "edges_removed": np.zeros((0, 2), np.int64), "posed_frames": np.array([1, 2], np.int64),
                            "frame_poses": np.array([[np.nan] * 3, [0.5, -0.2, 1.0]]), **changes})


def _past_poses_frame(**changes):
    from schemas.localization import PastPoses

    return PastPoses(**{"header": HEADER, "anchor_stamp_ns": 300, "stamps_ns": np.array([200, 100], np.int64),
                        "poses": np.array([[0.1, 0.2, 0.3], [0.0, 0.1, 0.2]]),
                        "covariances": np.stack([np.eye(3) * 1e-3] * 2), **changes})


OBJECT_COLUMNS = dict(class_names=("bowl", "mug"), class_index=np.array([1, 0], np.int32),
                      positions=np.array([[0.1, 0.2, 0.8], [0.5, -0.3, 0.0]]), has_height=np.array([True, False]),
                      sizes=np.array([[0.1, 0.1, 0.12], [0.0, 0.0, 0.0]]), scores=np.array([1.2, 0.7]),
                      bounds=np.array([[-1.0, -1.0], [1.0, 1.0]]), frames=12)


@pytest.mark.parametrize("existence, message", [([0.9], "existence has 1 rows for 2 objects"),
                                                ([0.0, 1.0], r"existence must lie in \(0, 1\]"),
                                                ([0.5, 1.5], r"existence must lie in \(0, 1\]")])
def test_object_map_existence_is_checked(existence, message):
    with pytest.raises(ValueError, match=message):
        ObjectMap(header=HEADER, **OBJECT_COLUMNS, existence=np.array(existence))


@pytest.mark.parametrize("name", list(_frames()))
def test_round_trip_is_exact(name):
    frame = _frames()[name]
    data = encode(frame)
    back = decode(data)
    assert type(back) is type(frame)
    assert back.header == frame.header
    assert encode(back) == data  # re-encoding a decoded frame gives the same bytes
    for field in type(frame).model_fields:
        a, b = getattr(frame, field), getattr(back, field)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)


def test_arrays_decode_without_copy_into_read_only_views():
    pixels = RNG.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    data = encode(Image.from_pixels(HEADER, pixels))
    frame = decode(data)
    array = frame.images[0].data
    assert not array.flags.writeable
    assert np.shares_memory(array, np.frombuffer(data, dtype=np.uint8))
    np.testing.assert_array_equal(array, pixels)
    # Every array sits at an 8-byte aligned offset of the payload.
    assert (array.__array_interface__["data"][0] - np.frombuffer(data, np.uint8).__array_interface__["data"][0]) % 8 == 0


def test_jpeg_image_decodes_to_the_original_pixels_within_jpeg_error():
    gradient = np.tile(np.linspace(0, 255, 64, dtype=np.uint8), (48, 1))
    pixels = np.stack([gradient, gradient[::-1], np.full_like(gradient, 90)], axis=-1)
    frame = decode(encode(Image.from_pixels(HEADER, pixels, jpeg_quality=95)))
    assert frame.images[0].compression == "jpeg"
    assert np.abs(frame.bgr().astype(int) - pixels).mean() < 3.0


def test_rgb8_pixels_are_returned_as_bgr():
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB order
    image = decode(encode(Image.from_pixels(HEADER, rgb, encoding="rgb8")))
    assert image.bgr()[0, 0].tolist() == [0, 0, 200]


def test_pose3d_matrix_round_trip():
    T = _rotation_z(-2.0)
    T[:3, 3] = [1, 2, 3]
    pose = decode(encode(Pose3D.from_matrix(HEADER, T)))
    np.testing.assert_allclose(pose.matrix(), T, atol=1e-12)


def _tamper(frame: Frame, edit) -> bytes:
    """Re-pack a frame's msgpack header after ``edit(body)``, keeping the data section."""
    data = encode(frame)
    (length,) = struct.unpack_from("<I", data)
    body = msgpack.unpackb(data[4 : 4 + length])
    edit(body)
    header = msgpack.packb(body)
    lead = 4 + len(header)
    pad = (-lead) % 8
    old_start = 4 + length + (-(4 + length)) % 8
    return struct.pack("<I", len(header)) + header + bytes(pad) + data[old_start:]


def _image_array(body):
    return body["images"][0]["data"]


BAD_PAYLOADS = {
    "empty": lambda: b"",
    "random bytes": lambda: bytes(RNG.integers(0, 256, 300, dtype=np.uint8)),
    "header length past end": lambda: struct.pack("<I", 10_000) + b"\x80",
    "truncated": lambda: encode(_frames()["image_bgr"])[:-100],
    "not a map": lambda: struct.pack("<I", 1) + msgpack.packb(1),
    "unknown schema": lambda: _tamper(_frames()["ack"], lambda b: b.update(schema="semloc.Nope")),
    "unknown version": lambda: _tamper(_frames()["ack"], lambda b: b.update(version=99)),
    # Same byte count, but float32 where the field wants uint8.
    "wrong dtype": lambda: _tamper(_frames()["image_bgr"], lambda b: _image_array(b).update(dtype="float32",
                                                                                              shape=[48, 16, 3])),
    "dtype not on the wire": lambda: _tamper(_frames()["image_bgr"], lambda b: _image_array(b).update(dtype="object")),
    "shape/bytes mismatch": lambda: _tamper(_frames()["image_bgr"], lambda b: _image_array(b).update(shape=[48, 64, 4])),
    "100 MB declared": lambda: _tamper(_frames()["image_bgr"], lambda b: _image_array(b).update(
        shape=[10_000, 10_000], nbytes=100_000_000)),
    "negative offset": lambda: _tamper(_frames()["image_bgr"], lambda b: _image_array(b).update(offset=-8)),
    "NaN pose": lambda: _tamper(_frames()["pose2d"], lambda b: b.update(x=float("nan"))),
    "NaN covariance": lambda: encode_raw_odometry_with_nan(),
    "missing field": lambda: _tamper(_frames()["odometry"], lambda b: b.pop("v")),
    "extra field": lambda: _tamper(_frames()["odometry"], lambda b: b.update(surprise=1)),
    "bad robot name": lambda: _tamper(_frames()["ack"], lambda b: b["header"].update(robot="a/b")),
    # semloc logs -f asks the launcher a LogTail names on the key its name makes
    "bad launcher name": lambda: _tamper(_frames()["log_tail"], lambda b: b.update(launcher="x/**")),
    "negative seq": lambda: _tamper(_frames()["ack"], lambda b: b["header"].update(seq=-1)),
    "non-unit quaternion": lambda: bad_quaternion(),
    "camera pose not rigid": lambda: scaled_camera_pose(),
    "image shape vs size": lambda: _tamper(_frames()["image_bgr"], lambda b: b["images"][0].update(width=65)),
}


def encode_raw_odometry_with_nan() -> bytes:
    frame = _frames()["odometry"]
    data = bytearray(encode(frame))
    covariance = np.frombuffer(data, dtype="<f8", count=9, offset=len(data) - 72)
    assert covariance[0] == 0.01
    struct.pack_into("<d", data, len(data) - 72, float("nan"))
    return bytes(data)


def bad_quaternion() -> bytes:
    data = bytearray(encode(_frames()["pose3d"]))
    orientation = _frames()["pose3d"].orientation
    index = bytes(data).find(orientation.tobytes())
    struct.pack_into("<d", data, index, 0.9)
    return bytes(data)


def scaled_camera_pose() -> bytes:
    """The equirectangular member's T_body_cam (the identity) with a scale of 2 on x: finite but not a rotation."""
    data = bytearray(encode(_frames()["camera_model_rig"]))
    index = bytes(data).find(np.eye(4).tobytes())
    assert index > 0
    struct.pack_into("<d", data, index, 2.0)
    return bytes(data)


@pytest.mark.parametrize("case", list(BAD_PAYLOADS))
def test_bad_payloads_raise_frame_error(case):
    with pytest.raises(FrameError):
        decode(BAD_PAYLOADS[case]())


@pytest.mark.parametrize("case, reason", [("empty", "decode"), ("random bytes", "decode"), ("not a map", "decode"),
                                          ("unknown schema", "schema"), ("unknown version", "schema"),
                                          ("wrong dtype", "invalid"), ("dtype not on the wire", "array"),
                                          ("100 MB declared", "array"), ("missing field", "invalid"),
                                          ("NaN pose", "nonfinite"), ("NaN covariance", "nonfinite")])
def test_rejections_name_their_reason(case, reason):
    with pytest.raises(FrameError) as caught:
        decode(BAD_PAYLOADS[case]())
    assert caught.value.reason == reason


def test_a_reason_is_a_short_code():
    assert FrameError("x", reason="range").reason == "range"
    with pytest.raises(ValueError, match="reason"):
        FrameError("x", reason="Not A Code")


def test_expected_type_is_enforced():
    with pytest.raises(FrameError, match="expected semloc.Image"):
        decode(encode(_frames()["ack"]), expected=Image)


def test_per_type_size_limit():
    big = Image.from_pixels(HEADER, np.zeros((4000, 4000, 3), np.uint8))
    assert len(encode(big)) < Image.max_bytes
    assert Ack.max_bytes < 100_000
    with pytest.raises(FrameError, match="exceeds its limit"):
        decode(_tamper(_frames()["ack"], lambda b: b.update(message="x" * 70_000)))


def test_building_invalid_frames_fails_at_the_boundary():
    with pytest.raises(ValueError):
        Image.from_pixels(HEADER, np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError):
        Odometry(header=HEADER, v=float("inf"), omega=0, dt=0.1)
    with pytest.raises(ValueError):
        PinholeSpec(width=10, height=10, K=np.eye(3), dist=np.zeros(3), T_body_cam=np.eye(4))
    with pytest.raises(ValueError):
        Pose2D(header=HEADER, x=0, y=0, theta=0, covariance=np.array([[1, 2, 0], [0, 1, 0], [0, 0, 1.0]]))
    levels = CameraHeatmapLevels(image_width=64, image_height=48, scores=np.zeros((2, 3, 12, 16), np.float32))
    with pytest.raises(ValueError, match="3 levels for 2 classes x 2 level scales"):
        HeatmapLevels(header=HEADER, classes=("bowl", "mug"), level_scales=(1.0, 0.5), maps=[levels])
    with pytest.raises(ValueError):
        HeatmapLevels(header=HEADER, classes=("bowl", "mug"), level_scales=(1.0, 0.5, 0.0), maps=[levels])
    with pytest.raises(ValueError):
        CameraHeatmapLevels(image_width=64, image_height=48, scores=np.zeros((2, 12, 16), np.float32))


def test_a_new_frame_type_is_one_class():
    class Probe(Frame, schema="test.Probe", version=3, max_bytes=4096):
        label: str
        values: Array("float32", ndim=1, finite=True)

    assert frame_types()[("test.Probe", 3)] is Probe
    frame = decode(encode(Probe(header=HEADER, label="x", values=np.arange(4, dtype=np.float32))))
    assert isinstance(frame, Probe) and frame.values.tolist() == [0, 1, 2, 3]
    assert export.frame_json_schema(Probe)["properties"]["schema"] == {"const": "test.Probe"}
    with pytest.raises(ValueError, match="already registered"):
        type("Other", (Frame,), {"__annotations__": {}}, schema="test.Probe", version=3)
    with pytest.raises(TypeError, match="reserved"):
        type("Clash", (Frame,), {"__annotations__": {"version": int}}, schema="test.Clash", version=1)
    assert ("test.Clash", 1) not in frame_types()


def test_json_schema_files_match_the_models():
    """Fails when a frame model changed without `semloc schema` being re-run (or a file is stale/missing)."""
    assert export.differences() == [], "run `semloc schema` and commit schemas/jsonschema/"
    files = export.export_all()
    for name in ("semloc.Image.v1.json", "semloc.CameraModel.v1.json", "semloc.Odometry.v1.json",
                 "semloc.Pose2D.v1.json", "semloc.Pose3D.v1.json", "semloc.Status.v1.json"):
        assert name in files


def test_json_schema_describes_the_wire_header():
    import json

    schema = json.loads(export.export_all()["semloc.Image.v1.json"])
    assert schema["properties"]["schema"] == {"const": "semloc.Image"}
    assert {"schema", "version", "header", "images"} <= set(schema["required"])
    header = schema["$defs"]["Header"]["properties"]
    assert {"robot", "stream", "seq", "stamp_ns", "frame_id"} == set(header)


def test_keys():
    assert keys.camera_image("r1", "front") == "semloc/r1/camera/front/image"
    assert keys.status("r1", "camera") == "semloc/r1/camera/status"
    assert keys.worker_of(keys.alive("r2", "mapper")) == ("r2", "mapper")
    assert keys.mapper_map("r1") == "semloc/r1/mapper/map"
    assert keys.detector_heatmap_levels("r1") == "semloc/r1/detector/heatmap_levels"
    assert keys.localizer_set_initial_pose("r1") == "semloc/r1/localizer/set_initial_pose"
    # The wildcards cover the keys they are for, and only that robot's.
    from services.recording import _key_match as key_matches
    assert key_matches(keys.robot_statuses("r1"), keys.status("r1", "mapper"))
    assert not key_matches(keys.robot_statuses("r1"), keys.status("r2", "mapper"))
    assert key_matches(keys.loopclosure_all("r1"), keys.loopclosure_events("r1"))
    assert not key_matches(keys.loopclosure_all("r1"), keys.localizer_pose("r1"))
    assert key_matches(keys.robot_all("r1"), keys.camera_image("r1")) and not key_matches(keys.robot_all("r1"),
                                                                                          keys.odometry("r2"))
    for bad in ("", "a/b", "r*", "x y"):
        with pytest.raises(ValueError):
            keys.odometry(bad)


@pytest.mark.parametrize("key, robot", [
    ("semloc/r1/odom", "r1"), ("semloc/r-2.a/camera/front/image", "r-2.a"), ("semloc/*/odom", None),
    ("semloc/**", None), ("semloc/$*/odom", None), ("rt/camera/image_raw", None), ("semloc", None),
])
def test_the_robot_a_key_names(key, robot):
    assert keys.robot_of(key) == robot


def test_encode_into_a_reused_buffer_gives_the_same_bytes():
    frames = _frames()
    buffer = bytearray(b"stale" * 1000)
    for name in ("image_bgr", "ack", "image_rig", "odometry"):
        assert encode(frames[name], into=buffer) is buffer
        assert bytes(buffer) == encode(frames[name])


# ---------------------------------------------------------------------------------------------------- physical ranges
def _forged(cls, **fields) -> bytes:
    """The wire bytes of a frame nobody validated (a peer's, an attacker's)."""
    return encode(cls.model_construct(**fields))


def _odometry(**fields) -> bytes:
    return _forged(Odometry, **{"header": HEADER, "v": 0.5, "v_lateral": 0.0, "omega": 0.1, "dt": 0.1,
                                "covariance": None, **fields})


def _heatlines(scores, classes=("bowl",), scale=1.0) -> bytes:
    from schemas.detection import Heatlines

    return _forged(Heatlines, header=HEADER, classes=classes, scores=np.asarray(scores, np.float32), scale=scale,
                   observed=np.ones(np.asarray(scores).shape[1], bool), hard=False)


def _object_map(**changes) -> bytes:
    return _forged(ObjectMap, **{"header": HEADER, **OBJECT_COLUMNS, "existence": np.array([0.9, 1.0]),
                                 "free_space": [], **changes})


def _features(descriptors, **fields) -> bytes:
    from schemas.loopclosure import LoopFeatures

    return _forged(LoopFeatures, header=HEADER, bearings=np.linspace(-1.0, 1.0, len(descriptors)),
                   descriptors=descriptors, **fields)


def _camera_pose(translation) -> bytes:
    T = np.eye(4)
    T[:3, 3] = translation
    image = camera_image(np.zeros((4, 4, 3), np.uint8))
    return _forged(Image, header=HEADER, images=[image.model_copy(update={"T_body_cam": T})])


def _sift_like(count: int) -> np.ndarray:
    from semloc_core.loopclosure.features import normalize_descriptors

    return normalize_descriptors(RNG.random((count, 128)) ** 4)


RANGES = {
    "1e300 speed": (lambda: _odometry(v=1e300, dt=3600.0), "range"),
    "speed beyond MAX_SPEED": (lambda: _odometry(v=101.0), "range"),
    "turn rate beyond MAX_TURN_RATE": (lambda: _odometry(omega=-51.0), "range"),
    "dt 0": (lambda: _odometry(dt=0.0), "range"),
    "dt beyond an hour": (lambda: _odometry(dt=3601.0), "range"),
    "infinite speed": (lambda: _odometry(v=float("inf")), "nonfinite"),
    "covariance of 1e300": (lambda: _odometry(covariance=np.full((3, 3), 1e300)), "range"),
    "pose 1e300 away": (lambda: _forged(Pose2D, header=HEADER, x=1e300, y=0.0, theta=0.0, child_frame_id="body",
                                        covariance=None), "range"),
    "3D pose 1e8 away": (lambda: _forged(Pose3D, header=HEADER, position=np.array([0.0, 1e8, 0.0]),
                                         orientation=np.array([0.0, 0.0, 0.0, 1.0]), child_frame_id="body",
                                         covariance=None), "range"),
    "score above 1": (lambda: _heatlines(np.full((1, 8), 1.5)), "range"),
    "negative score": (lambda: _heatlines(np.full((1, 8), -0.1)), "range"),
    "uint8 scores scaled past 1": (lambda: _forged(
        HeatmapLevels, header=HEADER, classes=("bowl",), detector="", level_scales=(1.0,), maps=[
            CameraHeatmapLevels.model_construct(camera=0, image_width=64, image_height=48, scale=1.0, T_body_cam=None,
                                                scores=np.full((1, 1, 2, 2), 7, np.uint8))]), "range"),
    "NaN score": (lambda: _heatlines(np.full((1, 8), np.nan)), "nonfinite"),
    "1,025 classes": (lambda: _heatlines(np.zeros((1025, 4)), classes=tuple(f"c{i}" for i in range(1025))), "size"),
    "object 1e300 away": (lambda: _object_map(positions=np.full((2, 3), 1e300)), "range"),
    "negative object size": (lambda: _object_map(sizes=-np.ones((2, 3))), "range"),
    "existence 0": (lambda: _object_map(existence=np.zeros(2)), "range"),
    "descriptors not SIFT": (lambda: _features(RNG.integers(0, 256, (5, 128), dtype=np.uint8)), "range"),
    "feature pixel 1e9 px away": (lambda: _features(_sift_like(2), points=np.array([[1e9, 0.0], [1.0, 1.0]],
                                                                                     np.float32)), "range"),
    "feature of rig member 40": (lambda: _features(_sift_like(2), camera_index=np.array([0, 40], np.int16)), "range"),
    "camera 1 km from the body": (lambda: _camera_pose([1000.0, 0.0, 0.0]), "range"),
}


@pytest.mark.parametrize("case", list(RANGES))
def test_physical_ranges_are_checked_on_decode(case):
    make, reason = RANGES[case]
    with pytest.raises(FrameError) as caught:
        decode(make())
    assert caught.value.reason == reason, caught.value


def _past_poses(**changes) -> bytes:
    from schemas.localization import PastPoses

    return _forged(PastPoses, **{**dict(_past_poses_frame()), **changes})


@pytest.mark.parametrize("changes, reason", [
    ({"poses": np.array([[0.1, np.nan, 0.3], [0.0, 0.1, 0.2]])}, "nonfinite"),
    ({"poses": np.array([[1e300, 0.2, 0.3], [0.0, 0.1, 0.2]])}, "range"),
    ({"covariances": np.full((2, 3, 3), 1e300)}, "range"),
    ({"poses": np.zeros((3, 3))}, "invalid"),  # sizes: 2 stamps, 3 poses
    ({"covariances": np.stack([np.eye(3)])}, "invalid"),
    ({"stamps_ns": np.array([100, 200], np.int64)}, "invalid"),  # not newest first
    ({"stamps_ns": np.array([400, 100], np.int64)}, "invalid"),  # after the anchor
    ({"covariances": np.stack([np.eye(3), -np.eye(3)])}, "invalid"),
    ({"stamps_ns": np.arange(100_001, 0, -1, dtype=np.int64), "anchor_stamp_ns": 200_000}, "size"),
])
def test_past_poses_are_checked_on_decode(changes, reason):
    with pytest.raises(FrameError) as caught:
        decode(_past_poses(**changes))
    assert caught.value.reason == reason, caught.value


NOT_PSD = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # symmetric, diagonal >= 0, eigenvalue -1


def _pose_estimate(**changes) -> bytes:
    from schemas.localization import PoseEstimate

    covariance = np.diag([1e-4, 1e-4, 1e-3])
    return _forged(PoseEstimate, **{"header": HEADER, "x": 0.5, "y": -0.2, "theta": 1.0, "covariance": covariance,
                                    "child_frame_id": "body", "status": "converged", "state": "localized",
                                    "particles": 500, "effective_sample_size": 400.0, "clusters": 1,
                                    "cluster_weight": 1.0, "recovery_ratio": 1.0, "injected": 0,
                                    "mean": np.array([0.5, -0.2, 1.0]), "mean_covariance": covariance,
                                    "converged_std": np.array([0.1, 0.2]), "motion_std": np.array([0.01, 0.02]),
                                    "sample": None, "sample_weights": None, **changes})


def _loop_closure(**changes) -> bytes:
    from schemas.loopclosure import LoopClosure

    return _forged(LoopClosure, **{"header": HEADER, "frame": 9, "status": "loop_found", "loops": np.array([2, 3]),
                                   "loop_stamps_ns": np.array([200, 300], np.int64),
                                   "beliefs": np.array([2.0, 3.0], np.float32), "node": 1, "revised": [],
                                   "expected_precision": None, "decision_threshold": None,
                                   "loop_poses": np.array([[0.1, 0.2, 0.3], [np.nan] * 3]), **changes})


@pytest.mark.parametrize("make, reason", [
    (lambda: _pose_estimate(covariance=NOT_PSD), "invalid"),
    (lambda: _pose_estimate(mean_covariance=NOT_PSD), "invalid"),
    (lambda: _pose_estimate(covariance=np.diag([1.0, -1e-3, 1.0])), "invalid"),
    (lambda: _pose_estimate(converged_std=np.array([0.0, 0.2])), "invalid"),
    (lambda: _pose_estimate(state="evil"), "invalid"),
    (lambda: _pose_estimate(status="localizing", state="localized"), "invalid"),
    (lambda: _pose_estimate(status="localizing", state="uncertain"), "invalid"),
    (lambda: _pose_estimate(x=1e300), "range"),
    (lambda: _pose_estimate(theta=float("nan")), "nonfinite"),
    (lambda: _pose_estimate(mean=np.array([0.0, np.inf, 0.0])), "nonfinite"),
    (lambda: _past_poses(covariances=np.stack([np.eye(3), NOT_PSD])), "invalid"),
    (lambda: _loop_closure(loop_stamps_ns=np.array([-5, 300], np.int64)), "range"),
    (lambda: _loop_closure(loops=np.array([3, 3])), "invalid"),
    (lambda: _loop_closure(loops=np.array([2, 9])), "invalid"),  # not an earlier frame
    (lambda: _loop_closure(loop_poses=np.zeros((3, 3))), "invalid"),
    (lambda: _loop_closure(loop_poses=np.array([[0.1, np.nan, 0.3], [np.nan] * 3])), "nonfinite"),
    (lambda: _loop_closure(loop_poses=np.array([[1e300, 0.2, 0.3], [np.nan] * 3])), "range"),
    (lambda: _loop_closure(beliefs=np.array([np.nan, 3.0], np.float32)), "nonfinite"),
], ids=["covariance not PSD", "mean covariance not PSD", "negative variance", "converged spread 0", "state evil",
        "localized while localizing", "uncertain while localizing", "x 1e300", "theta NaN", "mean inf",
        "past covariance not PSD", "negative loop stamp", "a loop twice",
        "a loop not earlier", "poses of 3 loops for 2", "a pose partly NaN", "a pose 1e300 away", "NaN belief"])
def test_hybrid_frames_are_checked_on_decode(make, reason):
    """PoseEstimate, PastPoses and LoopClosure carry the localizer's and the places' poses between workers: physical
    nonsense in them is refused on decode, with its reason."""
    with pytest.raises(FrameError) as caught:
        decode(make())
    assert caught.value.reason == reason, caught.value


@pytest.mark.parametrize("status, state", [("localizing", "lost"), ("localizing", None), ("converged", "lost"),
                                           ("converged", "uncertain"), ("lost", "localized"), ("lost", None)])
def test_a_pose_estimates_state_may_differ_from_its_status_where_the_two_can(status, state):
    """The filter's status and the monitor's state weigh different things and may disagree (a converged filter
    judged lost, one recovering that the monitor finds localized): only an initialising filter fixes the state."""
    assert decode(_pose_estimate(status=status, state=state)).state == state


@pytest.mark.parametrize("changes, reason", [
    ({"frame_poses": np.array([[np.nan, 0.0, 0.0], [0.5, -0.2, 1.0]])}, "nonfinite"),  # a row partly NaN
    ({"frame_poses": np.array([[np.nan] * 3, [1e300, -0.2, 1.0]])}, "range"),
    ({"posed_frames": np.array([1, 4], np.int64)}, "invalid"),  # frame 4 of a map of 4
    ({"posed_frames": np.array([1], np.int64)}, "invalid"),  # 1 frame, 2 poses
    ({"posed_frames": None}, "invalid"),  # poses without their frames
])
def test_topomap_update_poses_are_checked_on_decode(changes, reason):
    from schemas.loopclosure import TopoMapUpdate

    with pytest.raises(FrameError) as caught:
        decode(_forged(TopoMapUpdate, **{**dict(_topomap_update()), **changes}))
    assert caught.value.reason == reason, caught.value


def test_values_at_the_edges_of_their_ranges_decode():
    from schemas import limits

    for payload in (_odometry(v=limits.MAX_SPEED, omega=-limits.MAX_TURN_RATE, dt=limits.MAX_ODOMETRY_DT),
                    _heatlines(np.array([[0.0, 1.0, 0.5, 1.0]])), _features(_sift_like(50)), _camera_pose([0, 0, 99.0]),
                    _object_map(positions=np.full((2, 3), -limits.MAX_COORDINATE))):
        decode(payload)


@pytest.mark.parametrize("extension, flags", [(".png", []), (".jpg", []),
                                              (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])])
def test_a_compressed_image_header_gives_its_size_without_decoding(extension, flags):
    from schemas.camera import compressed_size

    pixels = RNG.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    data = cv2.imencode(extension, pixels, flags)[1].reshape(-1)
    compression = "png" if extension == ".png" else "jpeg"
    assert compressed_size(data, compression) == (53, 37)
    frame = decode(_forged(Image, header=HEADER, images=[camera_image(pixels).model_copy(update={
        "compression": compression, "data": data})]))
    assert frame.images[0].pixels().shape == (37, 53, 3)


def test_a_decompression_bomb_is_rejected_before_it_is_decoded():
    """A 12000x12000 PNG (430 KB of zeros, 432 MB decoded) declared 640x480; a PNG declared JPEG; garbage."""
    bomb = cv2.imencode(".png", np.zeros((12000, 12000, 3), np.uint8))[1].reshape(-1)
    small = cv2.imencode(".png", np.zeros((480, 640, 3), np.uint8))[1].reshape(-1)
    for data, compression in ((bomb, "png"), (small, "jpeg"), (RNG.integers(0, 256, 900, dtype=np.uint8), "png"),
                              (small[:20], "png")):
        payload = _forged(Image, header=HEADER, images=[camera_image(np.zeros((480, 640, 3), np.uint8)).model_copy(
            update={"compression": compression, "data": data})])
        with pytest.raises(FrameError) as caught:
            decode(payload)
        assert caught.value.reason == "image_header"


def test_json_schema_carries_the_ranges():
    import json

    from schemas import limits

    files = export.export_all()
    odometry = json.loads(files["semloc.Odometry.v1.json"])["properties"]
    assert (odometry["v"]["minimum"], odometry["v"]["maximum"]) == (-limits.MAX_SPEED, limits.MAX_SPEED)
    assert odometry["dt"]["exclusiveMinimum"] == 0 and odometry["dt"]["maximum"] == limits.MAX_ODOMETRY_DT
    positions = json.loads(files["semloc.ObjectMap.v2.json"])["properties"]["positions"]
    assert positions["x-semloc-element-maximum"] == limits.MAX_COORDINATE and positions["x-semloc-finite"]


def test_a_status_without_the_rate_fields_still_decodes_as_v1():
    """Status's rate fields (rate_hz, handler_ms, busy_fraction) came later within v1: an older worker's frame,
    without them, decodes with None; a new one carries them."""
    stats = InputStats(key="semloc/r1/camera/front/image", policy="latest", processed=10, rate_hz=9.5, handler_ms=40.0)
    status = Status(header=Header(robot="r1", stream="semloc/r1/detector/status", seq=0, stamp_ns=1), worker="detector",
                    kind="detector", state="running", pid=1, started_ns=1, uptime_s=2.0, inputs={"image": stats},
                    busy_fraction=0.4)
    again = decode(encode(status), expected=Status)
    assert again.busy_fraction == 0.4 and again.inputs["image"].rate_hz == 9.5
    payload = encode(status)
    (size,) = struct.unpack_from("<I", payload)
    body = msgpack.unpackb(payload[4 : 4 + size], raw=False)
    del body["busy_fraction"]
    for name in ("rate_hz", "handler_ms"):
        del body["inputs"]["image"][name]
    header = msgpack.packb(body, use_bin_type=True)
    older = decode(struct.pack("<I", len(header)) + header, expected=Status)
    assert older.busy_fraction is None and older.inputs["image"].rate_hz is None and older.inputs["image"].processed == 10
    body["busy_fraction"] = 1.5  # a share of time: checked at the boundary
    header = msgpack.packb(body, use_bin_type=True)
    with pytest.raises(FrameError):
        decode(struct.pack("<I", len(header)) + header, expected=Status)


def test_revisions_beyond_one_frames_limit_go_with_the_next():
    """A new decision threshold may revise more earlier frames than a LoopClosure may carry: the earliest go first,
    the rest with the next frames, a newer revision of a frame replacing the older; every one fits the schema."""
    from schemas.loopclosure import MAX_REVISIONS, LoopClosure, Revision
    from services.frames import take_revisions

    due: dict = {}
    first = {f: np.array([0]) for f in range(1, MAX_REVISIONS + 6)}
    sent = take_revisions(due, first, MAX_REVISIONS)
    assert sorted(sent) == list(range(1, MAX_REVISIONS + 1)) and sorted(due) == list(range(MAX_REVISIONS + 1,
                                                                                            MAX_REVISIONS + 6))
    LoopClosure(header=Header(robot="r1"), frame=MAX_REVISIONS + 6, status="no_candidate", loops=np.zeros(0, np.int64),
                loop_stamps_ns=np.zeros(0, np.int64), beliefs=np.zeros(0, np.float32), node=-1,
                revised=[Revision(frame=f, loops=l) for f, l in sorted(sent.items())])
    newer = {MAX_REVISIONS + 2: np.array([1, 2])}
    sent = take_revisions(due, newer, MAX_REVISIONS)
    assert sorted(sent) == list(range(MAX_REVISIONS + 1, MAX_REVISIONS + 6)) and not due
    assert sent[MAX_REVISIONS + 2].tolist() == [1, 2]
    with pytest.raises(ValueError):
        LoopClosure(header=Header(robot="r1"), frame=MAX_REVISIONS + 7, status="no_candidate",
                    loops=np.zeros(0, np.int64), loop_stamps_ns=np.zeros(0, np.int64),
                    beliefs=np.zeros(0, np.float32), node=-1,
                    revised=[Revision(frame=f, loops=np.array([0])) for f in range(1, MAX_REVISIONS + 2)])


def _peer_frame(stamp_s: float, seq: int = 0, robot: str = "r1"):
    return Odometry(header=Header(robot=robot, seq=seq, stamp_ns=int(stamp_s * 1e9)), v=0.1, v_lateral=0.0,
                    omega=0.0, dt=0.1)


@pytest.mark.parametrize("earlier, later, reason", [
    ((10.0, 1), (10.0, 1), "order"),  # delivered twice
    ((10.0, 1), (9.5, 2), "order"),  # stale: stamped before the last one taken
    ((10.0, 1), (10.0, 2), None),  # the same stamp as another frame of the stream (a new initial pose)
    ((10.0, 1), (3.0, 2), None),  # a new run of the stream (a replay of an earlier recording): taken
    ((10.0, 1), (10.5, 2), None),
])
def test_an_ordered_peer_stream_refuses_repeats_and_stale_frames_but_not_a_new_run(earlier, later, reason):
    from services.frames import FrameError, PeerStream
    stream = PeerStream()
    stream.check(_peer_frame(*earlier))
    if reason is None:
        stream.check(_peer_frame(*later))
        stream.check(_peer_frame(later[0] + 0.1, later[1] + 1))  # and the stream goes on from there
    else:
        with pytest.raises(FrameError) as refused:
            stream.check(_peer_frame(*later))
        assert refused.value.reason == reason


def test_a_frame_stamped_ahead_cannot_silence_an_ordered_peer_stream():
    """One frame stamped at this machine's clock, into a stream stamped by a recording's (hours earlier), must not
    hold back the recording's later frames."""
    from services.frames import PeerStream
    stream = PeerStream()
    now = time.time()
    stream.check(_peer_frame(now))
    for k in range(3):
        stream.check(_peer_frame(1_000.0 + 0.1 * k, k))
