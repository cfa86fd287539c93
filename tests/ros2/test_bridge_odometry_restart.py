"""The ros2 bridge when the robot's odometry restarts (docs/ros2.md, "When the robot's router goes away"): a fake
robot drives straight ahead at 0.5 m/s, its odometry (/odom, or TF odom -> base_footprint) sampled at 10 Hz, and
reboots: a new publisher (rmw_zenoh: a new GID in the attachment), odometry from the identity again, its clock going
on or restarted behind. The semloc Odometry the bridge makes of it, integrated, must be the distance the robot
drove: no jump back to the new zero across the reboot, and no motion lost after it; a link that dropped (the same
publisher, the robot driving on meanwhile) still spans its gap with the true motion."""

from __future__ import annotations

import numpy as np
import pytest

from schemas import Header, Odometry, decode, encode, keys
from schemas.localization import PoseEstimate
from semloc_core.geometry import pose2d_to_transform
from services.ros2 import messages as ros
from services.ros2.wire import QoS, attachment, endpoint_token, entity_gid
from tests.ros2.test_bridge_worker import STAMP, STORE, _key, _odometry, _start, _status
from tests.service.conftest import hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service
SPEED, PERIOD_NS = 0.5, 100_000_000  # m/s; the odometry's 10 Hz


class Robot:
    """The robot's odometry publisher: one zenoh session id per boot (its GID follows from its token), a pose
    integrated from the commanded motion."""

    def __init__(self, session, convention: str, odometry_from: str):
        self.session, self.convention, self.odometry_from = session, convention, odometry_from
        self.topic, self.msgtype = ("/odom", ros.ODOMETRY) if odometry_from == "odom" else ("/tf", ros.TF_MESSAGE)
        self.sent = 0
        self.driven = 0.0  # the ground truth: metres driven since the first sample
        self.boot(STAMP)

    def boot(self, stamp: int) -> None:
        """A (re)started robot: a new publisher, odometry from the identity, its clock at ``stamp``."""
        self.boots = getattr(self, "boots", 0) + 1
        token = endpoint_token("MP", 0, f"{self.boots:032x}", 0, 1, "robot", self.topic, self.msgtype,
                               STORE.hash_rihs01(self.msgtype), QoS())
        self.gid, self.sequence, self.stamp, self.x = entity_gid(token), 0, stamp, 0.0

    def drive(self, samples: int, published: bool = True) -> None:
        """``samples`` odometry periods ahead, each sample put (``published``) or lost with the link."""
        for _ in range(samples):
            self.stamp += PERIOD_NS
            self.x += SPEED * PERIOD_NS * 1e-9
            self.driven += SPEED * PERIOD_NS * 1e-9
            self.sequence += 1
            if published:
                self.put()

    def put(self, attached: bytes | None = None) -> None:
        """The odometry sample now (``attached``: this attachment instead of rmw_zenoh's)."""
        T = pose2d_to_transform(self.x, 0.0, 0.0)
        msg = (_odometry(self.stamp, T) if self.odometry_from == "odom"
               else ros.tf_message(STORE, [(self.stamp, "odom", "base_footprint", T)]))
        key, payload = _key(self.convention, self.topic, self.msgtype), ros.encode_cdr(STORE, msg, self.msgtype)
        if self.convention == "rmw_zenoh":
            self.session.put(key, payload, attachment=attached or attachment(self.sequence, self.stamp, self.gid))
        else:
            self.session.put(key, payload)
        self.sent += 1


def _run(procs, session, hub, convention, odometry_from, script):
    """The bridge's semloc Odometry (in order) and status after ``script(robot)`` drove the robot."""
    process = _start(procs, hub, convention, "bridge", f"odometry_from={odometry_from}")
    wait_until(lambda: _status(session, procs, process), 60, message="bridge running")
    received = []
    subscriber = session.declare_subscriber(keys.odometry("r1"), lambda s: received.append(
        decode(s.payload.to_bytes(), expected=Odometry)))
    robot = Robot(session, convention, odometry_from)
    name = f"ros_{robot.topic[1:]}"

    def handled():
        status = _status(session, procs, process)
        entry = status.inputs[name] if status else None
        return status if entry and entry.processed + entry.rejected == robot.sent else None

    robot.put()
    wait_until(handled, 20, message="the first odometry sample")
    script(robot)
    status = wait_until(handled, 20, message=lambda: f"{robot.sent} handled: {_status(session, procs, process)}")
    # the status may come back before the last Odometry does (another key, another path through the hub)
    wait_until(lambda: len(received) == status.outputs["odometry"].published, 10,
               message=lambda: f"{status.outputs['odometry'].published} Odometry, {len(received)} received")
    subscriber.undeclare()
    assert status.errors == 0, status.last_error
    for odometry in received:
        assert (odometry.v_lateral, odometry.omega) == pytest.approx((0.0, 0.0), abs=1e-9)
    return robot, received, status, procs.log("bridge")


@pytest.mark.parametrize("odometry_from", ["odom", "tf"])
def test_a_rebooted_robot_makes_no_jump(procs, session, hub, odometry_from):
    """1 m driven; the link drops for 1.1 s while the robot drives 0.55 m more (spanned: the same publisher); 1 m;
    the robot reboots (3 s standing, then a new publisher from the identity, its clock going on); 1 m. The bridge's
    odometry integrates to the 3.55 m driven - not to 1 m, what the spanning twist back to the new zero leaves. A
    sample whose attachment is not rmw_zenoh's is rejected (``attachment``), the chain going on."""
    def script(robot):
        robot.drive(20)
        robot.drive(10, published=False)
        robot.drive(21)
        robot.stamp += 3_000_000_000
        robot.boot(robot.stamp)
        robot.put()
        robot.drive(19)
        robot.drive(1, published=False)
        robot.put(attached=attachment(robot.sequence, robot.stamp, robot.gid)[:-1])
        robot.put()

    robot, received, status, log = _run(procs, session, hub, "rmw_zenoh", odometry_from, script)
    driven = sum(o.v * o.dt for o in received)
    assert robot.driven == pytest.approx(3.55)
    assert driven == pytest.approx(robot.driven, abs=1e-6), f"integrated {driven:.3f} m, driven {robot.driven:.3f} m"
    spans = [round(o.dt, 6) for o in received if o.dt > 0.15]
    assert spans == [1.1], spans  # the link drop's gap, not the reboot's
    assert status.details["odometry_restarts"] == 1, status.details
    assert status.inputs[f"ros_{robot.topic[1:]}"].rejected_reasons == {"attachment": 1}, status
    assert log.count("odometry restarted") == 1 and "a new publisher" in log, log[-2000:]


@pytest.mark.parametrize("convention,odometry_from", [("rmw_zenoh", "odom"), ("rmw_zenoh", "tf"), ("bridge", "odom")])
def test_a_clock_restarted_behind_does_not_stop_the_odometry(procs, session, hub, convention, odometry_from):
    """1 m driven; the robot reboots with its clock an hour behind (no RTC, NTP not synced yet); 1 m. Each sample
    after the reboot's first makes an Odometry at once (none refused as going back in time), and they integrate to
    the 2 m driven. zenoh-bridge-ros2dds carries no publisher GID: the stamps going back more than a second tell.
    The localizer's estimate at a stamp after the reboot gives map -> odom on /tf from the new odometry."""
    def script(robot):
        robot.drive(20)
        robot.boot(robot.stamp - 3600 * 10**9)
        robot.put()
        robot.drive(20)

    robot, received, status, log = _run(procs, session, hub, convention, odometry_from, script)
    assert len(received) == 40 and sorted(o.header.stamp_ns for o in received[20:]) == [
        o.header.stamp_ns for o in received[20:]] and received[20].header.stamp_ns < received[19].header.stamp_ns
    driven = sum(o.v * o.dt for o in received)
    assert driven == pytest.approx(robot.driven, abs=1e-6), f"integrated {driven:.3f} m, driven {robot.driven:.3f} m"
    assert status.details["odometry_restarts"] == 1 and status.rejected == 0, status
    reason = "a new publisher" if convention == "rmw_zenoh" else "3600.0 s behind"
    assert log.count("odometry restarted") == 1 and reason in log, log[-2000:]

    tf = []
    subscriber = session.declare_subscriber(_key(convention, "/tf", ros.TF_MESSAGE), lambda s: tf.extend(
        t for t in ros.decode_cdr(STORE, s.payload.to_bytes(), ros.TF_MESSAGE).transforms
        if t.header.frame_id == "map"))
    stamp = robot.stamp - 5 * PERIOD_NS  # x = 0.75 m in the new odometry
    estimate = PoseEstimate(header=Header(robot="r1", stream="pose", stamp_ns=stamp, frame_id="world"), x=3.0, y=-1.0,
                            theta=0.7, covariance=np.eye(3) * 0.01, status="converged", particles=500,
                            effective_sample_size=300.0, mean=np.array([3.0, -1.0, 0.7]),
                            mean_covariance=np.eye(3) * 0.01)
    session.put(keys.localizer_pose("r1"), encode(estimate))
    wait_until(lambda: tf, 10, message="map -> odom on /tf")
    subscriber.undeclare()
    T_map_odom = ros.transform_matrix(tf[0].transform)
    np.testing.assert_allclose(T_map_odom @ pose2d_to_transform(0.75, 0.0, 0.0), pose2d_to_transform(3.0, -1.0, 0.7),
                               atol=1e-9)
