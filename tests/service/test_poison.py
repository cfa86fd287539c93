"""Acceptance (issue 28): every input of every worker takes >= 1,000 hostile payloads - wire garbage, schema-valid
physical nonsense (1e300 speeds, 3600 s gaps, absurd poses, unknown and 512 invented classes, a 12000x12000 PNG
declared 640x480) and other robots' frames - and rejects each one with the reason the test expects, counted exactly
in the worker's status. Then the attacked worker processes a clean sequence from the simulator, and its output equals
that of a worker that never saw the barrage: the same poses (within 1 cm), the same map objects, the same loops, the
same heatmaps.

Real worker processes over zenoh on loopback. Each test runs an attacked worker (robot ``hit``) beside a reference
one (robot ``ref``; the stateless detector is its own reference: its output before the barrage).
"""

from __future__ import annotations

import collections
import json
import math
import struct
import time

import cv2
import numpy as np
import pytest
import yaml
import zenoh

from schemas import Ack, Header, Image, Odometry, Pose2D, Pose3D, Status, decode, encode, keys
from schemas.camera import CameraImage
from schemas.detection import CameraHeatmapLevels, CameraHeatmaps, HeatmapLevels, Heatlines, Heatmaps
from schemas.localization import PastPoses, PoseEstimate
from schemas.loopclosure import LoopClosure, LoopFeatures, Revision
from schemas.mapping import ObjectMap
from semloc_core.camera import PinholeCamera
from semloc_core.io.semantic_map import save_semantic_map
from semloc_core.localization import field_of_view_mask, synthetic_scores_heatlines, visible_objects
from semloc_core.loopclosure import FeatureParams, extract_features
from semloc_core.mapping.scale_depth import level_depths
from semloc_core.mapping.synthetic import SyntheticObject, render_heatmaps, render_level_heatmaps
from services.bus import query
from semloc_core.io.camera_model import save_camera
from semloc_core.io.dataset import increment_to_twist, relative_increments
from services.frames import heatlines_frame, objectmap_frame
from tests.service.conftest import Received, repack, wait_until

pytestmark = pytest.mark.service

COUNT = 1000  # hostile payloads per input, at least
SMALL = PinholeCamera.from_fov(160, 120, 60.0)  # the camera of the clean sequences that are images or heatmaps
SECOND = 1_000_000_000
NOT_PSD = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # symmetric, diagonal >= 0, eigenvalue -1


# ---------------------------------------------------------------------------------------------------- payloads
def forge(cls, **fields):
    """A frame built as an attacker would: no validation on this side (``model_construct``)."""
    return cls.model_construct(**fields)


def garbage(example, rng) -> list:
    """Wire-level garbage made from a valid frame of the input's type: (maker, reason) pairs."""
    raw = encode(example)
    (length,) = struct.unpack_from("<I", raw)
    data_start = 4 + length + (-(4 + length)) % 8
    makers = [
        # never empty: an empty payload is a request-less query's valid request
        (lambda: bytes(rng.integers(0, 256, int(rng.integers(1, 2000)), dtype=np.uint8)), "decode"),
        (lambda: raw[: int(rng.integers(1, 4 + length))], "decode"),
        (lambda: repack(example, lambda b: b.update(schema=f"semloc.Evil{int(rng.integers(1e6))}")), "schema"),
        (lambda: repack(example, lambda b: b.update(version=int(rng.integers(3, 1000)))), "schema"),
        (lambda: encode(Ack(header=example.header, ok=True)), "schema"),
        (lambda: repack(example, lambda b: b.update(evil=1)), "invalid"),
        (lambda: repack(example, lambda b: b.update(header="evil")), "invalid"),
    ]
    if len(raw) > data_start:  # cut inside the arrays' bytes
        makers.append((lambda: raw[: int(rng.integers(data_start, len(raw)))], "array"))
    return makers


def barrage(makers, count: int = COUNT) -> tuple[list[bytes], collections.Counter]:
    """``count`` (or a few more: every kind as often) payloads cycling over ``makers``, and the expected reasons."""
    rounds = -(-count // len(makers))
    payloads, reasons = [], collections.Counter()
    for _ in range(rounds):
        for make, reason in makers:
            payloads.append(make())
            reasons[reason] += 1
    return payloads, reasons


def nan_at(array: np.ndarray, rng) -> np.ndarray:
    out = np.array(array, dtype=array.dtype)
    out.reshape(-1)[int(rng.integers(out.size))] = np.nan
    return out


def png(width: int, height: int) -> np.ndarray:
    """The PNG bytes of a black image of this size (a 12000x12000 one is ~430 KB)."""
    return cv2.imencode(".png", np.zeros((height, width, 3), np.uint8))[1].reshape(-1)


# ---------------------------------------------------------------------------------------------------- workers
class Fleet:
    """Worker processes of one test on the test's hub: start, status, wait."""

    def __init__(self, procs, session, hub):
        self.procs, self.session, self.hub = procs, session, hub

    def start(self, kind: str, robot: str, *args: str):
        return self.procs.semloc("worker", kind, "--connect", self.hub, "--robot", robot, "--log-level", "WARNING",
                                 "--set", "status_period_s=0.5", *args, name=f"{kind}-{robot}")

    def status(self, robot: str, worker: str) -> Status | None:
        replies = query(self.session, keys.status(robot, worker), reply_type=Status, timeout=1.0)
        return replies[0] if replies else None

    def running(self, robot: str, worker: str, process) -> Status:
        def up():
            assert process.poll() is None, self.procs.log(f"{worker}-{robot}")
            status = self.status(robot, worker)
            return status if status is not None and status.state == "running" else None
        return wait_until(up, 90, message=lambda: f"{worker}-{robot} running\n{self.procs.log(f'{worker}-{robot}')}")

    def publisher(self, key: str):
        publisher = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, 30, message=f"a subscriber on {key}")
        return publisher

    def flood(self, robot: str, worker: str, key: str, name: str, payloads, reasons) -> None:
        """Publish the payloads on ``key`` and check that input ``name`` rejected each with its expected reason."""
        publisher = self.publisher(key)
        before = self.counts(robot, worker, name)
        for payload in payloads:
            publisher.put(payload)
        self.expect_rejected(robot, worker, name, before, len(payloads), reasons)
        publisher.undeclare()

    def ask(self, robot: str, worker: str, key: str, name: str, payloads, reasons, batch: int = 50) -> None:
        """Send each payload as a query on ``key`` (``None``: an empty one): every reply is an error, and the query
        counts each rejection under its expected reason."""
        replies = []
        before = self.counts(robot, worker, name)
        for start in range(0, len(payloads), batch):  # a batch well below the worker's query queue
            pending = [self.session.get(key, timeout=30.0, **({} if p is None else {"payload": p}))
                       for p in payloads[start : start + batch]]
            for handler in pending:
                replies.append([reply.ok is None for reply in handler])
        assert all(answer == [True] for answer in replies), collections.Counter(map(str, replies))
        self.expect_rejected(robot, worker, name, before, len(payloads), reasons)

    def counts(self, robot: str, worker: str, name: str) -> collections.Counter:
        """Input ``name``'s counters now (received, rejected, processed, errors and each reason)."""
        entry = self.status(robot, worker).inputs[name]
        return collections.Counter({"received": entry.received, "rejected": entry.rejected,
                                    "processed": entry.processed, "errors": entry.errors,
                                    **{f"reason {k}": v for k, v in entry.rejected_reasons.items()}})

    def expect_rejected(self, robot: str, worker: str, name: str, before, count: int, reasons) -> None:
        """Since ``before``: ``count`` payloads received on input ``name``, each rejected with its reason."""
        seen = []

        def counted():
            now = self.counts(robot, worker, name)
            now.subtract(before)
            seen.append(now)
            return now if now["received"] >= count else None

        change = wait_until(counted, 120, message=lambda: f"{count} payloads on {name} counted, last {seen[-1]}")
        assert [change[k] for k in ("received", "rejected", "processed", "errors")] == [count, count, 0, 0], change
        assert {k.removeprefix("reason "): v for k, v in change.items() if k.startswith("reason ") and v} == dict(
            reasons), change


@pytest.fixture
def fleet(procs, session, hub):
    return Fleet(procs, session, hub)


# ---------------------------------------------------------------------------------------------------- localizer
def _heatlines(scenario, k: int, robot: str) -> Heatlines:
    semantic_map = scenario.semantic_map
    fov = 2 * math.atan(0.5 * scenario.camera.width / scenario.camera.K[0, 0])
    observed = field_of_view_mask(360, 0.0, fov)
    views = visible_objects(scenario.poses2d[k], semantic_map, observed, semantic_map.class_names)
    header = Header(robot=robot, seq=k, stamp_ns=int(scenario.stamps_ns[k]), frame_id="body")
    return heatlines_frame(header, synthetic_scores_heatlines(views, observed))


def _heatlines_payloads(example: Heatlines, rng):
    h, classes = example.header, example.classes
    scores, observed = np.asarray(example.scores), np.asarray(example.observed)
    invented = tuple(f"invented{i}" for i in range(512))
    makers = garbage(example, rng) + [
        (lambda: encode(forge(Heatlines, header=h, classes=classes, scores=nan_at(scores, rng), scale=1.0,
                              observed=observed, hard=False)), "nonfinite"),
        (lambda: encode(forge(Heatlines, header=h, classes=classes, scores=scores + 1.0, scale=1.0,
                              observed=observed, hard=False)), "range"),
        (lambda: encode(forge(Heatlines, header=h, classes=classes, scores=-scores - 0.5, scale=1.0,
                              observed=observed, hard=False)), "range"),
        (lambda: encode(forge(Heatlines, header=h, classes=("evil",), scores=scores[:1], scale=1.0,
                              observed=observed, hard=False)), "classes"),
        (lambda: encode(forge(Heatlines, header=h, classes=invented, scores=np.zeros((512, 4), np.float32),
                              scale=1.0, observed=np.ones(4, bool), hard=False)), "classes"),
        (lambda: encode(forge(Heatlines, header=h, classes=classes[:-1] + ("evil",), scores=scores, scale=1.0,
                              observed=observed, hard=False)), "classes"),
        (lambda: encode(forge(Heatlines, header=h, classes=classes, scores=scores[:-1], scale=1.0,
                              observed=observed, hard=False)), "invalid"),
        (lambda: encode(forge(Heatlines, header=h, classes=tuple(f"c{i}" for i in range(1025)),
                              scores=np.zeros((1025, 4), np.float32), scale=1.0, observed=np.ones(4, bool),
                              hard=False)), "size"),
    ] + _peer_payloads(_under(example), h)
    return barrage(makers)


def _odometry_payloads(header, rng, extra=()):
    """Odometry the wire refuses, and ``extra`` (maker, reason) pairs: a consumer's own limits."""
    example = Odometry(header=header, v=0.3, omega=0.1, dt=0.2)
    makers = garbage(example, rng) + [
        (_odometry(header, v=1e300, dt=3600.0), "range"),  # the issue's: kills localization for good without checks
        (_odometry(header, v=-1e300), "range"), (_odometry(header, omega=1e300), "range"),
        (_odometry(header, dt=0.0), "range"), (_odometry(header, dt=-1.0), "range"),
        (_odometry(header, dt=1e6), "range"), (_odometry(header, v=math.inf), "nonfinite"),
        (_odometry(header, omega=math.nan), "nonfinite"),
        (_odometry(header, covariance=np.full((3, 3), np.nan)), "nonfinite"),
        (_odometry(header, covariance=np.full((3, 3), 1e300)), "range"),
        (_odometry(header, covariance=np.triu(np.ones((3, 3)))), "invalid"),
        (_odometry(header, covariance=NOT_PSD), "invalid"),
    ]
    return barrage(makers + list(extra))


def _odometry(header, **fields):
    return lambda: encode(forge(Odometry, **{"header": header, "v": 0.3, "v_lateral": 0.0, "omega": 0.1, "dt": 0.2,
                                             "covariance": None, **fields}))


def _odometry_limits(header) -> list:
    """Odometry the wire takes and a consumer's configured limits (max_speed...: services.frames) refuse."""
    return [(_odometry(header, v=50.0), "range"), (_odometry(header, v_lateral=20.0), "range"),
            (_odometry(header, omega=20.0), "range"), (_odometry(header, dt=3600.0), "range")]


def _other_robots(make, header: Header) -> list:
    """(maker, reason) pairs: ``make(header)``, the bytes of a frame the input takes, under the headers of other
    robots (the twin's, another's): refused whatever else they carry (``robot``: the runtime checks every input)."""
    return [(lambda robot=robot: make(header.model_copy(update={"robot": robot})), "robot") for robot in ("ref", "r2")]


def _under(example):
    """``make(header)`` of :func:`_other_robots`: ``example`` under another header."""
    return lambda header: encode(example.model_copy(update={"header": header}))


def _ahead(make, header: Header) -> list:
    """(maker, reason) pairs: ``make(header)``, the bytes of a frame an input ordering by stamps takes, stamped past
    any clock (``services.frames.check_clock``)."""
    return [(lambda: make(header.model_copy(update={"stamp_ns": 2 ** 62})), "range"),
            (lambda: make(header.model_copy(update={"stamp_ns": time.time_ns() + 2 * 86400 * SECOND})), "range")]


def _peer_payloads(make, header: Header, last: Header | None = None) -> list:
    """(maker, reason) pairs of a peer's stream (``services.frames.PeerStream``): ``make(header)`` the frame's bytes
    under another header. Other robots'; stamped past any clock; with ``last`` (the header of the last frame the
    input took, of an ordered stream), that frame again and one stamped before it."""
    makers = _other_robots(make, header) + _ahead(make, header)
    if last is not None:
        makers += [(lambda: make(last), "order"),
                   (lambda: make(last.model_copy(update={"stamp_ns": last.stamp_ns - 1, "seq": last.seq + 1})),
                    "order")]
    return makers


def _map_payloads(example: ObjectMap, rng):
    fields = {name: getattr(example, name) for name in type(example).model_fields}

    def object_map(**changes):
        return lambda: encode(forge(ObjectMap, **{**fields, **changes}))
    positions, n = np.asarray(example.positions), len(example)
    names = example.class_names
    makers = garbage(example, rng) + [
        (object_map(positions=positions + 1e300), "range"), (object_map(positions=nan_at(positions, rng)), "nonfinite"),
        (object_map(sizes=-np.ones((n, 3))), "range"), (object_map(existence=np.zeros(n)), "range"),
        (object_map(existence=np.full(n, 2.0)), "range"), (object_map(bounds=np.array([[-1e300, -1.0], [1.0, 1.0]])),
                                                           "range"),
        (object_map(scores=np.full(n, np.inf)), "nonfinite"),
        (object_map(class_names=names[:-1] + ("evil",)), "classes"),
        (object_map(class_names=tuple(f"invented{i}" for i in range(512))), "classes"),
        (object_map(class_index=np.full(n, len(names), np.int32)), "invalid"),
        (object_map(bounds=np.array([[1.0, 1.0], [-1.0, -1.0]])), "invalid"),
        (object_map(scores=np.ones(n + 1)), "invalid"),
    ] + _other_robots(_under(example), example.header)
    return barrage(makers)


def _initial_pose_payloads(header, rng):
    def pose(**fields):
        return lambda: encode(forge(Pose2D, **{"header": header, "x": 0.0, "y": 0.0, "theta": 0.0,
                                               "child_frame_id": "body", "covariance": None, **fields}))
    example = Pose2D(header=header, x=0.0, y=0.0, theta=0.0)
    makers = garbage(example, rng) + [
        (pose(x=1e300), "range"), (pose(y=-1e300), "range"), (pose(theta=1e300), "range"),
        (pose(x=1e6), "range"),  # inside the wire's range, outside the map
        (pose(covariance=np.diag([1e10, 1e10, 0.1])), "range"), (pose(covariance=np.full((3, 3), 1e300)), "range"),
        (pose(x=math.nan), "nonfinite"), (pose(covariance=np.full((3, 3), np.nan)), "nonfinite"),
        (pose(covariance=NOT_PSD), "invalid"), (pose(covariance=np.triu(np.ones((3, 3)))), "invalid"),
        (lambda: None, "schema"),  # no request at all
    ] + _other_robots(_under(example), header)  # the set_initial_pose of another robot's operator
    return barrage(makers)


def _decision(header: Header, **fields) -> bytes:
    """A loop-closure decision built unchecked: frame 30 recognises frames 2 and 5, seen at (1, 0, 0) and (1.2, 0, 0)
    (``fields`` change it)."""
    return encode(forge(LoopClosure, **{
        "header": header, "frame": 30, "status": "loop_found", "loops": np.array([2, 5]),
        "loop_stamps_ns": np.array([2, 5], np.int64) * SECOND, "beliefs": np.array([4.0, 4.0], np.float32), "node": 1,
        "revised": [], "expected_precision": None, "decision_threshold": None,
        "loop_poses": np.array([[1.0, 0.0, 0.0], [1.2, 0.0, 0.0]]), **fields}))


def _decision_payloads(header: Header, last: Header, center, bounds, rng):
    """Decisions the localizer's loops input refuses, their places (shifted to the map's ``center``) inside the map
    but for the defect each carries (``last``: the header of the decision it took last)."""
    poses = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]]) + [center[0], center[1], 0.0]

    def decision(**fields):
        return lambda: _decision(header, **{"loop_poses": poses, **fields})
    many = 100_001
    makers = garbage(decode(decision()()), rng) + [
        (decision(loop_poses=poses + [bounds[1][0] - center[0] + 1.0, 0.0, 0.0]), "range"),  # outside the map
        (decision(loop_poses=poses + [0.0, bounds[0][1] - center[1] - 1.0, 0.0]), "range"),
        (decision(loop_poses=poses + 1e300), "range"),
        (decision(loop_poses=np.array([poses[0], [np.nan, 0.0, 0.0]])), "nonfinite"),
        (decision(loop_poses=np.array([poses[0], [np.inf] * 3])), "nonfinite"),
        (decision(loop_poses=np.concatenate([poses, poses[:1]])), "invalid"),
        (decision(beliefs=np.array([np.nan, 4.0], np.float32)), "nonfinite"),
        (decision(beliefs=np.full(3, 4.0, np.float32)), "invalid"),
        (decision(loops=np.array([2, 30])), "invalid"), (decision(loops=np.array([-1, 5])), "invalid"),
        (decision(loops=np.array([5, 5])), "invalid"),
        (decision(loop_stamps_ns=np.array([-SECOND, 5 * SECOND], np.int64)), "range"),
        (decision(status="no_candidate"), "invalid"), (decision(status="evil"), "invalid"),
        (decision(node=-2), "range"), (decision(expected_precision=2.0), "range"),
        (decision(decision_threshold=math.inf), "nonfinite"),
        (decision(revised=[forge(Revision, frame=4, loops=np.array([7]))]), "invalid"),
        (decision(frame=9_000_000, loops=np.arange(many), loop_stamps_ns=np.arange(many),
                  beliefs=np.ones(many, np.float32), loop_poses=np.tile(poses[:1], (many, 1))), "size"),
    ] + _peer_payloads(lambda h: _decision(h, loop_poses=poses), header, last)
    return barrage(makers)


def _no_request_payloads(example, rng):
    """A query that takes no request: any payload, garbage or a valid frame, is rejected."""
    makers = [(make, "schema") for make, _ in garbage(example, rng)] + [(lambda: encode(example), "schema")]
    return barrage(makers)


def test_localizer_rejects_every_hostile_payload_and_tracks_as_if_never_attacked(tmp_path, fleet, session,
                                                                                sim_scenario):
    scenario = sim_scenario("tabletop", frames=40, seed=0, fps=5.0)
    classes = list(scenario.semantic_map.class_names)
    map_path = tmp_path / "map.json"
    save_semantic_map(scenario.semantic_map, map_path)
    x, y, theta = (float(v) for v in scenario.poses2d[0])
    config = tmp_path / "localizer.yaml"
    config.write_text(yaml.safe_dump({
        "map": str(map_path), "map_from_mapper": True, "classes": classes, "model": "B", "motion": "omni",
        "seed": 3, "initial_pose": [x, y, theta], "initial_covariance": [0.01, 0.01, 0.01], "sample_size": 0,
        "ground_truth": False, "odom_alpha1": 0.05, "odom_alpha2": 0.01, "odom_alpha3": 0.05, "odom_alpha4": 0.01,
        # heatlines always wait for their odometry: a wall-clock release on a loaded machine would make the two
        # runs differ for a reason that is not the barrage
        "odometry_wait_s": 60.0,
        "filter": {"max_particles": 1500, "min_particles": 300, "kld_bin_xy": 0.05, "kld_bin_theta": math.radians(5),
                   "cluster_cell": 0.05, "converged_xy_std": 0.1, "converged_theta_std": math.radians(10),
                   "recovery_alpha_slow": 0.0}}))
    workers = {robot: fleet.start("localizer", robot, "--config", str(config)) for robot in ("ref", "hit")}
    for robot, process in workers.items():
        fleet.running(robot, "localizer", process)

    rng = np.random.default_rng(28)
    header = Header(robot="hit", stamp_ns=int(scenario.stamps_ns[1]))
    fleet.flood("hit", "localizer", keys.detector_heatlines("hit"), "heatlines",
                *_heatlines_payloads(_heatlines(scenario, 1, "hit"), rng))
    fleet.flood("hit", "localizer", keys.odometry("hit"), "odom",
                *_odometry_payloads(header, rng, _odometry_limits(header) + _peer_payloads(
                    lambda h: encode(Odometry(header=h, v=0.3, omega=0.1, dt=0.2)), header)))
    fleet.flood("hit", "localizer", keys.mapper_objects("hit"), "map",
                *_map_payloads(objectmap_frame(Header(robot="hit", frame_id="world"), scenario.semantic_map), rng))
    fleet.ask("hit", "localizer", keys.localizer_set_initial_pose("hit"), "query:set_initial_pose",
              *_initial_pose_payloads(header, rng))
    # The loop-closure worker's first decision (no loops) to both, then recognised places of every wrong kind (the
    # localizer starts lost: one taken would draw particles around its poses)
    first = {robot: Header(robot=robot, stamp_ns=int(scenario.stamps_ns[1]) // 2) for robot in ("ref", "hit")}
    for robot in ("ref", "hit"):
        fleet.publisher(keys.loopclosure_events(robot)).put(_decision(
            first[robot], frame=0, status="too_few_frames", loops=np.zeros(0, np.int64),
            loop_stamps_ns=np.zeros(0, np.int64), beliefs=np.zeros(0, np.float32), node=0, loop_poses=None))
    wait_until(lambda: all(fleet.status(r, "localizer").inputs["loops"].processed == 1 for r in ("ref", "hit")), 30,
               message="the first decision")
    bounds = scenario.semantic_map.bounds
    fleet.flood("hit", "localizer", keys.loopclosure_events("hit"), "loops", *_decision_payloads(
        header, first["hit"], np.mean(bounds, axis=0), bounds, rng))
    reply = Pose2D(header=header, x=x, y=y, theta=theta)
    fleet.ask("hit", "localizer", keys.localizer_relocalize("hit"), "query:relocalize",
              *_no_request_payloads(reply, rng))
    fleet.ask("hit", "localizer", keys.localizer_pose("hit"), "query:pose", *_no_request_payloads(reply, rng))

    # The clean sequence, to both: odometry then heatlines per frame, each frame's estimates awaited.
    estimates = Received(session, {robot: keys.localizer_pose(robot) for robot in ("ref", "hit")})
    publishers = {(robot, kind): fleet.publisher(key(robot)) for robot in ("ref", "hit")
                  for kind, key in (("odom", keys.odometry), ("heatlines", keys.detector_heatlines))}
    odometry = scenario.odometry.as_array()
    frames = range(1, len(scenario))
    for k in frames:
        stamp = int(scenario.stamps_ns[k])
        v, v_lateral, omega, dt = (float(value) for value in odometry[k])
        for robot in ("ref", "hit"):
            publishers[robot, "odom"].put(encode(Odometry(header=Header(robot=robot, stamp_ns=stamp), v=v,
                                                          v_lateral=v_lateral, omega=omega, dt=dt)))
        if k == frames[0]:  # a localizer that has never seen odometry does not wait for it: the first must be in
            wait_until(lambda: all((s := fleet.status(r, "localizer")) and s.inputs["odom"].processed == 1
                                   for r in ("ref", "hit")), 30, message="the first odometry")
        for robot in ("ref", "hit"):
            publishers[robot, "heatlines"].put(encode(_heatlines(scenario, k, robot)))
        wait_until(lambda: all(any(e.header.stamp_ns == stamp for e in estimates[r]) for r in ("ref", "hit")), 30,
                   message=lambda: f"the estimates of frame {k}\n{fleet.procs.log('localizer-hit')[-3000:]}")
    estimates.close()
    ref, hit = ({e.header.stamp_ns: e for e in estimates[robot]} for robot in ("ref", "hit"))
    assert sorted(ref) == sorted(hit) == [int(scenario.stamps_ns[k]) for k in frames]

    def apart(k: int, stamp: int) -> str:
        return (f"frame {k}: reference {ref[stamp].x:.4f} {ref[stamp].y:.4f} {ref[stamp].theta:.4f}, attacked "
                f"{hit[stamp].x:.4f} {hit[stamp].y:.4f} {hit[stamp].theta:.4f}\n"
                f"{fleet.procs.log('localizer-hit')[-2000:]}\n{fleet.procs.log('localizer-ref')[-2000:]}")

    for k, stamp in enumerate(sorted(ref), start=1):
        assert np.hypot(ref[stamp].x - hit[stamp].x, ref[stamp].y - hit[stamp].y) < 0.01, apart(k, stamp)
        assert abs(math.remainder(ref[stamp].theta - hit[stamp].theta, 2 * math.pi)) < 0.01, apart(k, stamp)
        assert ref[stamp].status == hit[stamp].status
    final = hit[int(scenario.stamps_ns[-1])]
    assert np.hypot(final.x - scenario.poses2d[-1][0], final.y - scenario.poses2d[-1][1]) < 0.2  # it tracks
    status = fleet.status("hit", "localizer")
    assert status.state == "running" and status.errors == 0
    assert status.inputs["heatlines"].processed == len(frames) and status.inputs["odom"].processed == len(frames)
    assert status.inputs["loops"].processed == 1


# ---------------------------------------------------------------------------------------------------- mapper
SCALES = (1.2, 0.85, 0.6, 0.42, 0.3, 0.21)
DEPTH_PER_SCALE = 0.0085


def _objects(scenario) -> list[SyntheticObject]:
    m = scenario.semantic_map
    return [SyntheticObject(int(c), np.array(p), np.array(s)) for c, p, s in zip(m.class_index, m.positions, m.sizes)]


def _heat(scenario, k: int, robot: str, levels: bool, grid: tuple[int, int] = (120, 160)):
    """Frame k's heatmaps (or levels) of the SMALL camera, on a ``grid`` of cells (rows, cols) over its image."""
    classes = scenario.semantic_map.class_names
    header = Header(robot=robot, seq=k, stamp_ns=int(scenario.stamps_ns[k]), frame_id="cam0")
    T = scenario.T_world_cam[k]
    size = {"height": grid[0], "width": grid[1]}
    if levels:
        depths = level_depths([DEPTH_PER_SCALE] * len(classes), SCALES, SMALL.K[0, 0])
        scores = render_level_heatmaps(SMALL, T, _objects(scenario), len(classes), depths, **size)
        return HeatmapLevels(header=header, classes=classes, level_scales=SCALES, maps=[CameraHeatmapLevels(
            image_width=SMALL.width, image_height=SMALL.height, scores=np.round(scores * 255).astype(np.uint8),
            scale=1 / 255)])
    scores = render_heatmaps(SMALL, T, _objects(scenario), len(classes), **size)
    return Heatmaps(header=header, classes=classes, maps=[CameraHeatmaps(
        image_width=SMALL.width, image_height=SMALL.height, scores=np.round(scores * 255).astype(np.uint8),
        scale=1 / 255)])


def _heat_payloads(example, rng):
    levels = isinstance(example, HeatmapLevels)
    cls, entry_cls = (HeatmapLevels, CameraHeatmapLevels) if levels else (Heatmaps, CameraHeatmaps)
    h, classes, entry = example.header, example.classes, example.maps[0]
    scores = np.asarray(entry.scores)
    extra = {"level_scales": example.level_scales} if levels else {}

    def frame(names=classes, values=None, scale=1 / 255, width=160, height=120, camera=0, T=None, entries=1,
              **more):
        maps = [forge(entry_cls, camera=camera + i, image_width=width, image_height=height,
                      scores=scores if values is None else values, scale=scale, T_body_cam=T) for i in range(entries)]
        return lambda: encode(forge(cls, header=h, classes=names, detector="", maps=maps, **{**extra, **more}))
    small = scores[:, ..., :4, :4]
    invented = np.zeros((512,) + small.shape[1:], np.uint8)
    far = np.eye(4)
    far[:3, 3] = 1e4
    makers = garbage(example, rng) + [
        (frame(names=("evil",) + classes[1:]), "classes"),
        (frame(names=tuple(f"invented{i}" for i in range(512)), values=invented), "classes"),
        (frame(names=classes[:-1], values=scores[:-1]), "classes"),
        (frame(values=scores.astype(np.float32) / 255 + 1.5, scale=1.0), "range"),
        (frame(values=np.full_like(scores, 200), scale=1.0), "range"),
        (frame(values=nan_at(scores.astype(np.float32), rng), scale=1.0), "nonfinite"),
        (frame(T=far), "range"),
        (frame(width=320, height=240), "calibration"),
        (frame(camera=3), "calibration"),
        (frame(entries=2), "calibration"),
        (frame(values=scores[:-1]), "invalid"),
    ] + _peer_payloads(_under(example), h)
    if levels:
        makers += [(frame(level_scales=(1.0, 0.5), values=scores[:, :2]), "calibration"),
                   (frame(level_scales=(100.0,) + SCALES[1:]), "range")]
    return barrage(makers)


def _pose_payloads(header, rng):
    example = Pose3D.from_matrix(header, np.eye(4))

    def pose3d(position=(0.0, 0.0, 1.0), orientation=(0.0, 0.0, 0.0, 1.0)):
        return lambda: encode(forge(Pose3D, header=header, position=np.array(position, float),
                                    orientation=np.array(orientation, float), child_frame_id="body", covariance=None))

    def pose2d(**fields):
        return lambda: encode(forge(Pose2D, **{"header": header, "x": 0.0, "y": 0.0, "theta": 0.0,
                                               "child_frame_id": "body", "covariance": None, **fields}))
    makers = garbage(example, rng) + [
        (pose3d(position=(1e300, 0.0, 0.0)), "range"), (pose3d(position=(0.0, 1e5, 0.0)), "range"),
        (pose3d(position=(np.nan, 0.0, 0.0)), "nonfinite"), (pose3d(orientation=(0.0, 0.0, 0.0, 2.0)), "invalid"),
        (pose2d(x=math.inf), "nonfinite"), (pose2d(theta=1e300), "range"), (pose2d(y=5e3), "range"),
    ] + _peer_payloads(_under(example), header) + _peer_payloads(_under(Pose2D(header=header, x=0.0, y=0.0,
                                                                                theta=0.0)), header)
    return barrage(makers)


@pytest.mark.parametrize("levels", [False, True], ids=["heatmaps", "heatmap_levels"])
def test_mapper_rejects_every_hostile_payload_and_maps_as_if_never_attacked(tmp_path, fleet, session, sim_scenario,
                                                                           levels):
    scenario = sim_scenario("tabletop", frames=24, seed=0, fps=2.0)
    classes = list(scenario.semantic_map.class_names)
    calibration = save_camera(SMALL, tmp_path / "camera.yaml")
    args = ["--set", f"calibration={calibration}", "--set", f"classes={json.dumps(classes)}", "--set",
            "pose_frame=camera", "--set", "grid_min=[-1.3,-1.3,0.7]", "--set", "grid_max=[1.3,1.3,1.15]", "--set",
            "voxel_size=0.04", "--set", "extraction.min_views=3", "--set", "publish_period_s=0.5"]
    if levels:
        scale_depth = tmp_path / "scale_depth.json"
        scale_depth.write_text(json.dumps({"detector": {"scale_depth": {
            "scales": list(SCALES), "classes": {name: {"depth_per_scale": DEPTH_PER_SCALE} for name in classes}}}}))
        args += ["--set", f"scale_depth_file={scale_depth}"]
    workers = {robot: fleet.start("mapper", robot, *args) for robot in ("ref", "hit")}
    for robot, process in workers.items():
        fleet.running(robot, "mapper", process)

    rng = np.random.default_rng(5)
    heat_key = keys.detector_heatmap_levels if levels else keys.detector_heatmaps
    header = Header(robot="hit", stamp_ns=int(scenario.stamps_ns[0]), frame_id="world")
    fleet.flood("hit", "mapper", heat_key("hit"), "heatmaps",
                *_heat_payloads(_heat(scenario, 0, "hit", levels, grid=(12, 16)), rng))
    fleet.flood("hit", "mapper", keys.groundtruth_pose("hit"), "pose", *_pose_payloads(header, rng))
    fleet.ask("hit", "mapper", keys.mapper_map("hit"), "query:map", *_no_request_payloads(
        Pose2D(header=header, x=0.0, y=0.0, theta=0.0), rng))

    publishers = {(robot, kind): fleet.publisher(key(robot)) for robot in ("ref", "hit")
                  for kind, key in (("pose", keys.groundtruth_pose), ("heat", heat_key))}
    for k in range(len(scenario)):
        stamp = int(scenario.stamps_ns[k])
        for robot in ("ref", "hit"):
            publishers[robot, "heat"].put(encode(_heat(scenario, k, robot, levels)))
            publishers[robot, "pose"].put(encode(Pose3D.from_matrix(
                Header(robot=robot, stamp_ns=stamp, frame_id="world"), scenario.T_world_cam[k])))
        if k % 8 == 7:  # a lossless queue (16 heatmaps) refuses what comes faster than it is handled: pace
            for robot in ("ref", "hit"):
                wait_until(lambda r=robot: fleet.status(r, "mapper").inputs["heatmaps"].processed >= k + 1, 60,
                           message=f"{robot} took frame {k}")

    def final_map(robot):
        replies = query(session, keys.mapper_map(robot), reply_type=ObjectMap, timeout=10.0)
        return replies[0] if replies and replies[0].frames == len(scenario) else None

    maps = {robot: wait_until(lambda r=robot: final_map(r), 60, message=f"{robot}'s map of every frame")
            for robot in ("ref", "hit")}
    ref, hit = maps["ref"], maps["hit"]
    assert len(hit) >= 3 and hit.class_names == ref.class_names == tuple(classes)
    np.testing.assert_array_equal(hit.class_index, ref.class_index)
    np.testing.assert_allclose(hit.positions, ref.positions, atol=1e-9)
    np.testing.assert_allclose(hit.scores, ref.scores, rtol=1e-9)
    status = fleet.status("hit", "mapper")
    assert status.state == "running" and status.errors == 0
    assert status.inputs["heatmaps"].processed == len(scenario)


# ---------------------------------------------------------------------------------------------------- images
def _calibration(tmp_path):
    return save_camera(SMALL, tmp_path / "camera.yaml")


def _image_payloads(example: Image, rng, extra=()):
    """Images the wire, the size limit and the camera model refuse, and ``extra`` (maker, reason) pairs."""
    h = example.header
    pixels = np.asarray(example.images[0].data)
    jpeg = cv2.imencode(".jpg", pixels)[1].reshape(-1)
    bomb = png(12000, 12000)  # ~430 KB: 432 MB once decoded

    def image(width=160, height=120, compression="none", data=None, camera=0, T=None, count=1, encoding="bgr8"):
        images = [forge(CameraImage, camera=camera + i, width=width, height=height, encoding=encoding,
                        compression=compression, data=pixels if data is None else data, T_body_cam=T)
                  for i in range(count)]
        return lambda: encode(forge(Image, header=h, images=images))
    far, skew, broken = np.eye(4), np.eye(4), np.eye(4)
    far[:3, 3] = 1e3
    skew[0, 1] = 0.5
    broken[0, 3] = np.nan
    makers = garbage(example, rng) + [
        (image(width=640, height=480, compression="png", data=bomb), "image_header"),  # the bomb
        (image(compression="png", data=bomb), "image_header"),
        (image(width=320, height=240, compression="jpeg", data=jpeg), "image_header"),
        (image(compression="jpeg", data=png(160, 120)), "image_header"),
        (image(compression="png", data=rng.integers(0, 256, 5000, dtype=np.uint8)), "image_header"),
        (image(compression="png", data=png(160, 120)[:20]), "image_header"),
        (image(width=5000, height=5000, compression="png", data=png(5000, 5000)), "size"),  # over max_image_pixels
        (image(width=320, height=240, data=np.zeros((240, 320, 3), np.uint8)), "calibration"),
        (image(count=2), "calibration"),
        (image(camera=4), "calibration"),
        (image(T=far), "range"),
        (image(T=broken), "nonfinite"),
        (image(T=skew), "invalid"),
        (image(data=pixels[:, :-1]), "invalid"),
        (image(encoding="mono8"), "invalid"),
    ] + _other_robots(_under(example), h)
    return barrage(makers + list(extra))


def test_detector_rejects_every_hostile_image_and_answers_as_before(tmp_path, fleet, session, sim_scenario):
    scenario = sim_scenario("tabletop", frames=24, seed=0, fps=2.0, camera=SMALL)
    library = tmp_path / "library"
    for name, views in scenario.exemplars().items():
        (library / name).mkdir(parents=True)
        cv2.imwrite(str(library / name / "0.png"), views[0])
    detector_file = tmp_path / "detector.yaml"
    detector_file.write_text(yaml.safe_dump({"kind": "templates", "templates": "library", "scales": [1.0, 0.6],
                                             "mask": "none"}))
    process = fleet.start("detector", "hit", "--set", f"detector_file={detector_file}", "--set",
                          f"calibration={_calibration(tmp_path)}")
    fleet.running("hit", "detector", process)
    heatmaps = Received(session, {"hit": keys.detector_heatmaps("hit")})
    heatlines = Received(session, {"hit": keys.detector_heatlines("hit")})
    images = fleet.publisher(keys.camera_image("hit"))
    frames = [0, 6, 12, 18]

    def clean_pass(seq0: int) -> None:
        for offset, k in enumerate(frames):
            images.put(encode(Image.from_pixels(Header(robot="hit", seq=seq0 + offset, stamp_ns=seq0 + offset),
                                                scenario.image(k))))
            wait_until(lambda: len(heatlines["hit"]) >= seq0 + offset + 1, 60, message=f"the heatlines of {k}")

    clean_pass(0)  # the reference: this detector before the barrage
    fleet.flood("hit", "detector", keys.camera_image("hit"), "image", *_image_payloads(
        Image.from_pixels(Header(robot="hit", seq=99, stamp_ns=99), scenario.image(0)), np.random.default_rng(9)))
    clean_pass(len(frames))
    heatmaps.close()
    heatlines.close()
    maps, lines = heatmaps["hit"], heatlines["hit"]
    assert len(maps) == len(lines) == 2 * len(frames)
    for before, after in zip(maps[: len(frames)], maps[len(frames) :]):
        np.testing.assert_array_equal(before.maps[0].scores, after.maps[0].scores)
    for before, after in zip(lines[: len(frames)], lines[len(frames) :]):
        np.testing.assert_array_equal(before.scores, after.scores)
        np.testing.assert_array_equal(before.observed, after.observed)
    assert max(float(np.max(m.maps[0].values())) for m in maps) > 0.0  # it answers
    status = fleet.status("hit", "detector")
    assert status.state == "running" and status.errors == 0 and status.inputs["image"].processed == 2 * len(frames)


# ---------------------------------------------------------------------------------------------------- loop closure
def _features_payloads(example: LoopFeatures, rng):
    h = example.header
    bearings, descriptors = np.asarray(example.bearings), np.asarray(example.descriptors)
    n = len(bearings)

    def features(b=None, d=None):
        return lambda: encode(forge(LoopFeatures, header=h, bearings=bearings if b is None else b,
                                    descriptors=descriptors if d is None else d))
    makers = garbage(example, rng) + [
        (features(d=rng.integers(0, 256, (n, 128), dtype=np.uint8)), "range"),  # not SIFT: norms ~1,600, not 512
        (features(d=np.zeros((n, 128), np.uint8)), "range"),
        (features(b=bearings + 4.0), "range"),
        (features(b=nan_at(bearings, rng)), "nonfinite"),
        (features(b=bearings[::-1].copy()), "invalid"),
        (features(d=descriptors[:-1]), "invalid"),
        (features(d=descriptors[:, :64].copy()), "invalid"),
    ] + _peer_payloads(_under(example), h)
    return barrage(makers)


def _estimate(header: Header, pose, state: str = "localized", **fields) -> bytes:
    """The localizer's estimate at ``pose`` (x, y, theta), built unchecked: the clean stream's and the payloads'."""
    covariance = np.diag([1e-4, 1e-4, 1e-3])
    status = "converged" if state != "lost" else "localizing"
    return encode(forge(PoseEstimate, **{
        "header": header, "x": float(pose[0]), "y": float(pose[1]), "theta": float(pose[2]),
        "covariance": covariance, "child_frame_id": "body", "status": status, "state": state, "particles": 1000,
        "effective_sample_size": 500.0, "clusters": 1, "cluster_weight": 1.0, "recovery_ratio": 1.0, "injected": 0,
        "mean": np.asarray(pose, float), "mean_covariance": covariance, "converged_std": np.array([0.1, 0.17]),
        "motion_std": np.array([0.02, 0.02]), "sample": None, "sample_weights": None, **fields}))


def _estimate_payloads(header: Header, last: Header, rng):
    """Estimates the loop-closure worker's pose input refuses (``last``: the header of the one it took last)."""
    pose = np.array([0.2, -0.1, 0.5])

    def estimate(**fields):
        return lambda: _estimate(header, pose, **fields)
    makers = garbage(decode(_estimate(header, pose)), rng) + [
        (estimate(covariance=NOT_PSD), "invalid"), (estimate(mean_covariance=NOT_PSD), "invalid"),
        (estimate(covariance=np.diag([1e-4, -1e-4, 1e-3])), "invalid"),
        (estimate(covariance=np.full((3, 3), np.nan)), "nonfinite"),
        (estimate(x=1e300), "range"), (estimate(y=-2e7), "range"), (estimate(theta=math.inf), "nonfinite"),
        (estimate(theta=1e300), "range"), (estimate(mean=np.array([0.0, np.nan, 0.0])), "nonfinite"),
        (estimate(mean=np.array([1e8, 0.0, 0.0])), "range"), (estimate(state="evil"), "invalid"),
        (estimate(status="evil"), "invalid"), (estimate(converged_std=np.zeros(2)), "invalid"),
        (estimate(converged_std=np.array([np.nan, 0.1])), "nonfinite"), (estimate(motion_std=-np.ones(2)), "range"),
        (estimate(particles=0), "range"), (estimate(cluster_weight=2.0), "range"),
        (estimate(sample=np.zeros((3, 3), np.float32), sample_weights=np.ones(2, np.float32) / 2), "invalid"),
        (estimate(sample=np.zeros((100_001, 3), np.float32), sample_weights=np.zeros(100_001, np.float32)), "size"),
    ] + _peer_payloads(lambda h: _estimate(h, pose), header, last)
    return barrage(makers)


def _past_poses_payloads(header: Header, rng):
    """Backward passes the loop-closure worker's past_poses input refuses."""
    anchor = header.stamp_ns
    stamps, poses, covariances = np.array([anchor - 1, anchor - 2], np.int64), np.zeros((2, 3)), np.stack([np.eye(3)] * 2)

    def past(h=header, **fields):
        return lambda: encode(forge(PastPoses, **{"header": h, "anchor_stamp_ns": anchor, "stamps_ns": stamps,
                                                  "poses": poses, "covariances": covariances, **fields}))
    many = 100_001
    makers = garbage(decode(past()()), rng) + [
        (past(stamps_ns=stamps[::-1].copy()), "invalid"), (past(stamps_ns=stamps + 2), "invalid"),
        (past(stamps_ns=np.array([anchor - 1, anchor - 1], np.int64)), "invalid"),
        (past(poses=nan_at(poses, rng)), "nonfinite"), (past(poses=poses + 1e300), "range"),
        (past(poses=poses[:1]), "invalid"), (past(covariances=np.stack([np.eye(3), NOT_PSD])), "invalid"),
        (past(covariances=-covariances), "invalid"),
        (past(stamps_ns=np.arange(anchor - 1, anchor - 1 - many, -1, dtype=np.int64), poses=np.zeros((many, 3)),
              covariances=np.zeros((many, 3, 3))), "size"),
    ] + _peer_payloads(lambda h: past(h)(), header)
    return barrage(makers)


def _odometry_of(poses: np.ndarray, stamps_ns: np.ndarray, robot: str) -> list[Odometry]:
    """Odometry exactly between consecutive planar poses (the first from rest), one second each."""
    twists = increment_to_twist(relative_increments(poses))
    return [Odometry(header=Header(robot=robot, stamp_ns=int(stamp)), v=float(v), v_lateral=float(v_lateral),
                     omega=float(omega), dt=1.0) for stamp, (v, v_lateral, omega) in zip(stamps_ns, twists)]


def _frame_poses(updates) -> dict[int, tuple]:
    """Every frame's pose (NaN: none) as a TopoMapUpdate stream, replayed in order, gives them."""
    poses: dict[int, tuple] = {}
    for update in sorted(updates, key=lambda u: u.header.seq):
        if update.posed_frames is not None:
            poses.update(zip(update.posed_frames.tolist(), map(tuple, update.frame_poses.tolist())))
    return poses


def test_loop_closure_rejects_every_hostile_payload_and_closes_the_same_loops(tmp_path, fleet, session,
                                                                             sim_scenario):
    """Images and features, then the hybrid map's inputs (issue 34): the localizer's estimates and backward passes
    and the odometry. Both workers then see the same clean walk twice with the localizer's estimates of it: the same
    decisions, and the frames record the same poses, those of the ground truth."""
    scenario = sim_scenario("tabletop", frames=24, seed=0, fps=2.0, camera=SMALL)
    calibration = _calibration(tmp_path)
    # every image a key-frame (a decision each, compared one by one), with the odometry subscribed: the places carry
    # poses along it
    args = [a for setting in (f"calibration={calibration}", "engine.window=5", "engine.bootstrap_frames=12",
                              "engine.vocabulary_words=48", "engine.candidates=5", "engine.band=8",
                              "engine.temporal_radius=1", "image_policy=lossless", "rerun_every=0",
                              "keyframes.min_change=1e-9", "keyframes.min_distance=1e-9", "keyframes.min_turn=1e-9")
            for a in ("--set", setting)]
    workers = {robot: fleet.start("loopclosure", robot, *args) for robot in ("ref", "hit")}
    for robot, process in workers.items():
        fleet.running(robot, "loopclosure", process)

    rng = np.random.default_rng(7)
    pixels = scenario.image(0)
    header = Header(robot="hit", seq=99, stamp_ns=99)
    features = extract_features(pixels, SMALL, FeatureParams(max_features=500))
    assert len(features) >= 10
    fleet.flood("hit", "loopclosure", keys.camera_image("hit"), "image",
                *_image_payloads(Image.from_pixels(header, pixels), rng, _ahead(
                    _under(Image.from_pixels(header, pixels)), header)))  # the key-frame gate goes by stamps
    fleet.flood("hit", "loopclosure", keys.loopclosure_features("hit"), "features", *_features_payloads(
        LoopFeatures(header=header, bearings=features.bearings, descriptors=features.descriptors), rng))
    fleet.ask("hit", "loopclosure", keys.loopclosure_topomap("hit"), "query:topomap",
              *_no_request_payloads(Pose2D(header=header, x=0.0, y=0.0, theta=0.0), rng))

    # The odometry, then the localizer's first estimate (lost, before the walk), to both: the streams have begun
    # (estimates wait for the odometry to reach their stamps from then on).
    first = {robot: Header(robot=robot, stamp_ns=SECOND // 2, frame_id="world") for robot in ("ref", "hit")}
    publishers = {(robot, kind): fleet.publisher(key(robot)) for robot in ("ref", "hit") for kind, key in (
        ("image", keys.camera_image), ("pose", keys.localizer_pose), ("odom", keys.odometry))}
    for kind, payload in (("odom", lambda h: encode(Odometry(header=h, v=0.0, omega=0.0, dt=0.5))),
                          ("pose", lambda h: _estimate(h, scenario.poses2d[0], state="lost"))):
        for robot in ("ref", "hit"):
            publishers[robot, kind].put(payload(first[robot]))
        wait_until(lambda: all(fleet.status(r, "loopclosure").inputs[kind].processed == 1 for r in ("ref", "hit")),
                   30, message=f"the first {kind}")
    header = Header(robot="hit", stamp_ns=SECOND, frame_id="world")
    fleet.flood("hit", "loopclosure", keys.localizer_pose("hit"), "pose", *_estimate_payloads(header, first["hit"],
                                                                                                rng))
    fleet.flood("hit", "loopclosure", keys.localizer_past_poses("hit"), "past_poses",
                *_past_poses_payloads(header, rng))
    fleet.flood("hit", "loopclosure", keys.odometry("hit"), "odom", *_odometry_payloads(
        header, rng, _odometry_limits(header) + _peer_payloads(lambda h: encode(Odometry(header=h, v=0.3, omega=0.1,
                                                                                         dt=0.2)), header)))
    # Passes valid on the wire from a frame the worker never saw: taken, and every pose refused ('anchor').
    unknown = [PastPoses(header=header, anchor_stamp_ns=7 * SECOND + k, stamps_ns=np.array([3, 2, 1], np.int64) * k,
                         poses=np.zeros((3, 3)), covariances=np.zeros((3, 3, 3))) for k in range(1, 6)]
    past = fleet.publisher(keys.localizer_past_poses("hit"))
    for frame in unknown:
        past.put(encode(frame))
    wait_until(lambda: fleet.status("hit", "loopclosure").inputs["past_poses"].processed == len(unknown), 30,
               message="the passes of unknown frames")

    # The clean sequence: the walk, then the same walk again - the second pass closes loops with the first. Before
    # each image its odometry, after it the localizer's estimate: lost for three frames, then localized at the truth.
    events = Received(session, {robot: keys.loopclosure_events(robot) for robot in ("ref", "hit")})
    updates = Received(session, {robot: keys.loopclosure_topomap(robot) for robot in ("ref", "hit")})
    sequence = list(range(len(scenario))) * 2
    stamps = [(seq + 1) * SECOND for seq in range(len(sequence))]
    truth = scenario.poses2d[sequence]
    odometry = {robot: _odometry_of(truth, stamps, robot) for robot in ("ref", "hit")}
    for seq, k in enumerate(sequence):
        for robot in ("ref", "hit"):
            header = Header(robot=robot, seq=seq, stamp_ns=stamps[seq])
            publishers[robot, "odom"].put(encode(odometry[robot][seq]))
            publishers[robot, "image"].put(encode(Image.from_pixels(header, scenario.image(k))))
            publishers[robot, "pose"].put(_estimate(header.model_copy(update={"frame_id": "world"}), truth[seq],
                                                    state="lost" if seq < 3 else "localized"))
    wait_until(lambda: all(len(events[r]) >= len(sequence) for r in ("ref", "hit")), 120,
               message=lambda: f"{len(sequence)} decisions each\n{fleet.procs.log('loopclosure-hit')[-3000:]}")
    wait_until(lambda: all((s := fleet.status(r, "loopclosure")).inputs["pose"].processed == 1 + len(sequence)
                           and s.inputs["odom"].processed == 1 + len(sequence) for r in ("ref", "hit")), 60,
               message="every estimate and odometry taken")

    def same_poses():
        ref, hit = (_frame_poses(updates[robot]) for robot in ("ref", "hit"))
        return ref.keys() == hit.keys() and all(np.array_equal(ref[f], hit[f], equal_nan=True) for f in ref)
    wait_until(same_poses, 30, message=lambda: f"the same frame poses: reference {_frame_poses(updates['ref'])}, "
               f"attacked {_frame_poses(updates['hit'])}")
    events.close()
    updates.close()
    ref, hit = (sorted(events[robot], key=lambda e: e.frame) for robot in ("ref", "hit"))
    assert [e.frame for e in hit] == [e.frame for e in ref] == list(range(len(sequence)))
    for a, b in zip(ref, hit):
        assert isinstance(b, LoopClosure) and (a.status, a.loops.tolist()) == (b.status, b.loops.tolist())
        np.testing.assert_allclose(a.beliefs, b.beliefs, rtol=1e-5, atol=1e-5)  # (their poses: as committed by then)
    assert sum(e.status == "loop_found" for e in hit[len(scenario):]) >= len(scenario) // 2  # loops were closed
    # the places recorded the same poses, those the estimates gave (three lost frames carried back along the odometry)
    poses = _frame_poses(updates["hit"])
    posed = [f for f in sorted(poses) if np.isfinite(poses[f][0])]
    assert len(posed) >= len(sequence) // 2
    for f in posed:
        assert np.hypot(*(np.array(poses[f][:2]) - truth[f][:2])) < 0.05, (f, poses[f], truth[f])
    assert any(np.isfinite(e.loop_poses).all() for e in hit if e.loops.size)  # loops carry their places' poses
    status = fleet.status("hit", "loopclosure")
    assert status.state == "running" and status.errors == 0 and status.inputs["image"].processed == len(sequence)
    assert status.details["past_poses_refused_anchor"] == 3 * len(unknown) and status.details["past_poses_filled"] == 0
