"""The ros2 bridge when the robot's router goes away and comes back (docs/ros2.md, "When the robot's router goes
away"). The robot's rmw_zenohd is a zenoh router in a process of its own; the base station's router (this process)
connects to it through a Relay standing for the Wi-Fi; the bridge is a client of the base station's router, as in
a whole graph; the ROS side is a client of the robot's router. Two outages: the link cut 15 s (Relay.cut) then
restored, and the robot's router killed and a new one started on the same port. Through each: the bridge's status
says the robot is silent (degraded, with why), and after it the node's and topics' liveliness tokens are back on the
ROS side, a late transient-local subscriber gets the last pose, ROS odometry and images reach semloc again, and the
status is back to running. Figures (seconds from the link's return) are printed: pytest -s."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh
import zenoh.ext

from schemas import Header, Image, Odometry, Status, decode, encode, keys
from schemas.localization import PoseEstimate
from semloc_core.geometry import pose2d_to_transform
from services.bus import BusConfig, free_port, open_session, query
from services.ros2 import messages as ros
from services.ros2.wire import attachment
from tests.e2e.relay import Relay
from tests.ros2.test_bridge_worker import STAMP, STORE, T, _key, _odometry
from tests.service.conftest import REPO_ROOT, procs, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service
SILENCE_S = 2.0  # the bridge's ros_silence_s here
ROUTER = ("import signal, sys; from services.bus import BusConfig, open_session; "
          "s = open_session(BusConfig(mode='router', listen=[sys.argv[1]])); signal.pause()")


def _robot_router(procs, port: int) -> subprocess.Popen:
    """The robot's rmw_zenohd: a zenoh router (timestamping on, as routers have it) listening on ``port``."""
    process = subprocess.Popen([sys.executable, "-c", ROUTER, f"tcp/127.0.0.1:{port}"], cwd=REPO_ROOT,
                               env={**os.environ, "PYTHONPATH": str(REPO_ROOT)}, start_new_session=True)
    procs.started.append(process)

    def listening():
        with socket.socket() as probe:
            return probe.connect_ex(("127.0.0.1", port)) == 0
    wait_until(listening, 20, message="the robot's router listening")
    return process


class RosSide:
    """The robot's nodes: a client of its router putting /odom and images at 10 Hz, stamps going on."""

    def __init__(self, port: int, start: bool = True):
        self.session = open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
        self.stop = threading.Event()
        self.sequence = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        pixels = np.zeros((24, 32, 3), np.uint8)
        while not self.stop.wait(0.1):
            self.sequence += 1
            stamp = time.time_ns()  # the robot's clock: it goes on through an outage
            header = ros.ros_header(STORE, stamp, "cam")
            for topic, msgtype, msg in (
                    ("/odom", ros.ODOMETRY, _odometry(stamp, pose2d_to_transform(0.01 * self.sequence, 0.0, 0.0))),
                    ("/cam/image_raw", ros.IMAGE, T[ros.IMAGE](header=header, height=24, width=32, encoding="bgr8",
                                                                is_bigendian=0, step=96, data=pixels.reshape(-1)))):
                self.session.put(_key("rmw_zenoh", topic, msgtype), ros.encode_cdr(STORE, msg, msgtype),
                                 attachment=attachment(self.sequence, stamp, bytes(16)))

    def tokens(self) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get("@ros2_lv/0/**", timeout=0.5) if r.ok]

    def late_pose(self, timeout: float) -> list:
        """What a transient-local subscriber joining now gets of /amcl_pose (history, as rmw_zenoh's has)."""
        got = []
        subscriber = zenoh.ext.declare_advanced_subscriber(
            self.session, _key("rmw_zenoh", "/amcl_pose", ros.POSE_WITH_COVARIANCE_STAMPED), got.append,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
        try:
            wait_until(lambda: got, timeout, message="the last pose from the bridge's cache")
        finally:
            subscriber.undeclare()
        return [ros.decode_cdr(STORE, s.payload.to_bytes(), ros.POSE_WITH_COVARIANCE_STAMPED) for s in got]

    def close(self) -> None:
        self.stop.set()
        if self.thread.is_alive():
            self.thread.join(5)
        self.session.close()


def _status(base, name="bridge") -> Status | None:
    replies = query(base, keys.status("r1", name), reply_type=Status, timeout=0.5)
    return replies[0] if replies else None


def _watch(session, received: dict) -> list:
    """Subscribers keeping the semloc frames the bridge makes of ROS input, with when they arrived."""
    return [session.declare_subscriber(key, lambda s, n=name, t=frame_type: received[n].append(
        (time.monotonic(), decode(s.payload.to_bytes(), expected=t))))
        for name, key, frame_type in (("odom", keys.odometry("r1"), Odometry),
                                      ("image", keys.camera_image("r1"), Image))]


@pytest.mark.parametrize("outage,via,seconds", [("link cut", "base station", 15), ("router restart", "direct", 5),
                                                ("link cut", "direct", 6), ("router restart", "base station", 5)])
def test_bridge_comes_back_with_the_robot(procs, tmp_path, outage, via, seconds):
    """``via``: the bridge is a client of the base station's router (a whole graph; its status is read there, also
    during the outage) or of the robot's router itself (the documented single worker; read on the robot's side).
    ``seconds``: how long the robot is out of reach. Times are from the link's return (the new router listening)."""
    robot_port, hub = free_port(), f"tcp/127.0.0.1:{free_port()}"
    zenoh_config = tmp_path / "bridge.json5"
    zenoh_config.write_text(json.dumps({"timestamping": {"enabled": True}}))
    router = _robot_router(procs, robot_port)
    with Relay(robot_port) as relay, open_session(BusConfig(mode="router", listen=[hub], connect=[
            f"tcp/127.0.0.1:{relay.port}"])) as base:
        connect = hub if via == "base station" else f"tcp/127.0.0.1:{relay.port}"
        bridge = procs.semloc("worker", "ros2", "--mode", "client", "--connect", connect, "--zenoh-config",
                              str(zenoh_config), "--robot", "r1", "--name", "bridge", "--set", "status_period_s=0.2",
                              "--set", f"ros_silence_s={SILENCE_S}", "--set", "topics.image.name=/cam/image_raw",
                              "--set", "topics.camera_info.name=/cam/camera_info", "--log-level", "INFO",
                              name="bridge")
        ros_side = RosSide(robot_port, start=False)
        observer = base if via == "base station" else ros_side.session
        received = {"odom": [], "image": []}
        watching = _watch(observer, received)
        # (a status query unanswered within its 0.5 s on a loaded machine is asked again, not a failure)
        waiting = wait_until(lambda: bridge.poll() is None and (s := _status(observer)) and s.state == "degraded" and s,
                             60, message=lambda: f"the bridge up, no robot yet: {procs.log('bridge')[-2000:]}")
        assert "no ROS input since the start" in waiting.state_reason
        ros_side.start()
        wait_until(lambda: received["odom"] and received["image"], 20, message="ROS input through")
        wait_until(lambda: getattr(_status(observer), "state", None) == "running", 10,
                   message=lambda: _status(observer))
        pose = PoseEstimate(header=Header(robot="r1", stream="pose", stamp_ns=STAMP, frame_id="world"), x=3.0,
                            y=-1.0, theta=0.7, covariance=np.eye(3) * 0.01, status="converged", particles=500,
                            effective_sample_size=300.0, mean=np.array([3.0, -1.0, 0.7]),
                            mean_covariance=np.eye(3) * 0.01)
        observer.put(keys.localizer_pose("r1"), encode(pose))
        late = ros_side.late_pose(10)
        assert ros.transform_to_pose2d(ros.pose_matrix(late[-1].pose.pose)) == pytest.approx([3.0, -1.0, 0.7])

        # The outage: the robot's side is out of reach; the base station still reaches the bridge.
        if outage == "link cut":
            relay.cut("refuse")
        else:
            ros_side.close()
            os.killpg(router.pid, signal.SIGKILL)
            router.wait()
        time.sleep(seconds)
        if via == "base station":
            during = wait_until(lambda: _status(base), 10, message="the bridge's status during the outage")
            assert during.state == "degraded" and "no ROS input for" in during.state_reason, during
            assert during.details["robot_silences"] == 2, during.details  # at the start, and now
        if outage == "link cut":
            back = time.monotonic()
            relay.restore()
        else:
            router = _robot_router(procs, robot_port)
            back = time.monotonic()
            ros_side = RosSide(robot_port)
            if via == "direct":
                watching, observer = _watch(ros_side.session, received), ros_side.session
        figures = {}
        try:
            def tokens_back():
                tokens = ros_side.tokens()
                return (any(t.endswith("/NN/%/%/semloc") for t in tokens)
                        and any("/MP/" in t and "%amcl_pose" in t for t in tokens)
                        and any("/MS/" in t and "%odom/" in t for t in tokens))
            wait_until(tokens_back, 20, interval=0.1, message=lambda: f"tokens back: {ros_side.tokens()}")
            figures["tokens"] = time.monotonic() - back
            wait_until(lambda: received["odom"][-1][0] > back and received["image"][-1][0] > back, 20,
                       message="odometry and images through again")
            figures["odometry"] = next(t for t, _ in received["odom"] if t > back) - back
            late = ros_side.late_pose(10)
            figures["late pose"] = time.monotonic() - back
            assert ros.transform_to_pose2d(ros.pose_matrix(late[-1].pose.pose)) == pytest.approx([3.0, -1.0, 0.7])
            after = wait_until(lambda: (s := _status(observer)) and s.state == "running" and s, 10,
                               message=lambda: _status(observer))
            figures["running"] = time.monotonic() - back
            assert after.details["robot_silences"] == 2 and after.rejected == 0 and after.errors == 0, after
            assert after.details["robot_silent_s"] > seconds, after.details
            print(f"{outage} via {via}: " + ", ".join(f"{k} {v:.2f} s" for k, v in figures.items())
                  + f"; bus lost/regained {after.bus_lost}/{after.bus_regained} (load {os.getloadavg()[0]:.1f})")
        finally:
            ros_side.close()
            for subscriber in watching:
                subscriber.undeclare()
