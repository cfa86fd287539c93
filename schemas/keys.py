"""Every zenoh key expression of semloc, in one place (docs/wire.md, "Dataflow and keys").

Keys are namespaced per robot so many robots share one zenoh network: ``semloc/<robot>/...``. Names (robot,
camera, worker) are single key chunks: letters, digits, ``_``, ``.``, ``-``.

| key | frame | who writes |
|---|---|---|
| ``semloc/<robot>/camera/<cam>/image`` | Image | camera |
| ``semloc/<robot>/camera/<cam>/model`` | CameraModel (also a queryable) | camera |
| ``semloc/<robot>/odom`` | Odometry | odometry source (robot, camera worker on a data set) |
| ``semloc/<robot>/groundtruth/pose`` | Pose3D of the body in the world | camera worker on a data set |
| ``semloc/<robot>/groundtruth/pose2d`` | Pose2D of the body in the world | camera worker on a data set |
| ``semloc/<robot>/detector/heatmaps`` | Heatmaps | detector |
| ``semloc/<robot>/detector/heatlines`` | Heatlines | detector |
| ``semloc/<robot>/loopclosure/events`` | LoopClosure | loop closure |
| ``semloc/<robot>/loopclosure/topomap`` | TopoMap | loop closure |
| ``semloc/<robot>/loopclosure/similarity`` | SimilarityRow | loop closure |
| ``semloc/<robot>/loopclosure/features`` | LoopFeatures (instead of images: features computed elsewhere) | a feature extractor |
| ``semloc/<robot>/localizer/pose`` | PoseEstimate | localizer |
| ``semloc/<robot>/localizer/past_poses`` | PastPoses (a backward pass's poses of earlier frames) | localizer |
| ``semloc/<robot>/localizer/set_initial_pose`` | queryable: Pose2D -> Ack | localizer |
| ``semloc/<robot>/localizer/relocalize`` | queryable: (nothing) -> Ack | localizer |
| ``semloc/<robot>/mapper/objects`` | ObjectMap | mapper |
| ``semloc/<robot>/mapper/map`` | queryable: (nothing) -> ObjectMap | mapper |
| ``semloc/<robot>/mapper/save`` | queryable: save the map (issue 30; its access rule is in deploy/secure/) | mapper |
| ``semloc/<robot>/<worker>/status`` | Status (published periodically, also a queryable) | every worker |
| ``semloc/<robot>/<worker>/alive`` | liveliness token | every worker |
| ``semloc/<robot>/launcher/<launcher>/nodes`` | LauncherStatus (published periodically, also a queryable) | ``semloc up`` |
| ``semloc/<robot>/launcher/<launcher>/logs`` | queryable: LogRequest -> LogTail (``semloc logs``) | ``semloc up`` |
| ``semloc/<robot>/launcher/<launcher>/alive`` | liveliness token | ``semloc up`` |
| ``semloc/<robot>/launcher/<launcher>/stop`` | queryable: (nothing) -> Ack, then the graph stops (``semloc stop``) | ``semloc up`` |
| ``semloc/<robot>/launcher/<launcher>/restart/<node>`` | queryable: (nothing) -> Ack, then the node restarts (``semloc restart``) | ``semloc up`` |
"""

from __future__ import annotations

from schemas.base import check_name

PREFIX = "semloc"
# The robot namespace when none is given (a worker, the commands' --robot): the shipped graphs' (deploy/*.yaml), so
# that a worker started by hand next to `semloc up local` is on the same robot
DEFAULT_ROBOT = "r1"

ALL = f"{PREFIX}/**"
ALL_STATUS = f"{PREFIX}/*/*/status"  # every worker's Status (not replayed: services/recording.py)
ALL_ALIVE = f"{PREFIX}/*/*/alive"  # every worker's liveliness token: the robots on the bus
ALL_LAUNCHERS_ALIVE = f"{PREFIX}/*/launcher/*/alive"  # every launcher's: a robot whose workers have not started


def _robot(robot: str) -> str:
    return f"{PREFIX}/{check_name(robot, 'robot name')}"


def camera_image(robot: str, camera: str = "front") -> str:
    return f"{_robot(robot)}/camera/{check_name(camera, 'camera name')}/image"


def camera_model(robot: str, camera: str = "front") -> str:
    return f"{_robot(robot)}/camera/{check_name(camera, 'camera name')}/model"


def odometry(robot: str) -> str:
    return f"{_robot(robot)}/odom"


def groundtruth_pose(robot: str) -> str:
    return f"{_robot(robot)}/groundtruth/pose"


def groundtruth_pose2d(robot: str) -> str:
    return f"{_robot(robot)}/groundtruth/pose2d"


def detector_heatmaps(robot: str) -> str:
    return f"{_robot(robot)}/detector/heatmaps"


def detector_heatmap_levels(robot: str) -> str:
    return f"{_robot(robot)}/detector/heatmap_levels"


def detector_heatlines(robot: str) -> str:
    return f"{_robot(robot)}/detector/heatlines"


def loopclosure_events(robot: str) -> str:
    return f"{_robot(robot)}/loopclosure/events"


def loopclosure_topomap(robot: str) -> str:
    return f"{_robot(robot)}/loopclosure/topomap"


def loopclosure_similarity(robot: str) -> str:
    return f"{_robot(robot)}/loopclosure/similarity"


def loopclosure_features(robot: str) -> str:
    """Precomputed bearing-sorted feature sequences (LoopFeatures), an alternative to images."""
    return f"{_robot(robot)}/loopclosure/features"


def localizer_pose(robot: str) -> str:
    return f"{_robot(robot)}/localizer/pose"


def localizer_past_poses(robot: str) -> str:
    """Poses a backward filter pass gave the frames before a localized stretch (PastPoses)."""
    return f"{_robot(robot)}/localizer/past_poses"


def localizer_set_initial_pose(robot: str) -> str:
    return f"{_robot(robot)}/localizer/set_initial_pose"


def localizer_relocalize(robot: str) -> str:
    return f"{_robot(robot)}/localizer/relocalize"


def mapper_objects(robot: str) -> str:
    return f"{_robot(robot)}/mapper/objects"


def mapper_map(robot: str) -> str:
    return f"{_robot(robot)}/mapper/map"


def mapper_save(robot: str) -> str:
    """The mapper's save-the-map command (an operator's control query)."""
    return f"{_robot(robot)}/mapper/save"


def status(robot: str, worker: str) -> str:
    return f"{_robot(robot)}/{check_name(worker, 'worker name')}/status"


def alive(robot: str, worker: str) -> str:
    return f"{_robot(robot)}/{check_name(worker, 'worker name')}/alive"


def launcher_nodes(robot: str, launcher: str) -> str:
    """A launcher's view of its nodes (five chunks: never matches a worker's status or liveliness key)."""
    return f"{_robot(robot)}/launcher/{check_name(launcher, 'launcher name')}/nodes"


def all_launcher_nodes(robot: str = "*") -> str:
    """The LauncherStatus key of every launcher (of one robot, or of all with ``*``)."""
    return f"{PREFIX}/{robot}/launcher/*/nodes"


def launcher_logs(robot: str, launcher: str) -> str:
    """A launcher's nodes' logs (an operator's query)."""
    return f"{_robot(robot)}/launcher/{check_name(launcher, 'launcher name')}/logs"


def all_launcher_logs(robot: str) -> str:
    """Every launcher of one robot's logs query (``for_robots`` makes it every robot's)."""
    return f"{_robot(robot)}/launcher/*/logs"


def launcher_alive(robot: str, launcher: str) -> str:
    """A launcher's liveliness token (five chunks: never matches a worker's): its robot is found on the bus while
    none of its workers runs (``semloc stop`` of a graph whose nodes wait for a restart)."""
    return f"{_robot(robot)}/launcher/{check_name(launcher, 'launcher name')}/alive"


def all_launcher_alive(robot: str) -> str:
    """The liveliness token of every launcher of one robot."""
    return f"{_robot(robot)}/launcher/*/alive"


def launcher_stop(robot: str, launcher: str) -> str:
    """Stop a launcher's graph (an operator's control query)."""
    return f"{_robot(robot)}/launcher/{check_name(launcher, 'launcher name')}/stop"


def all_launcher_stop(robot: str) -> str:
    """Every launcher of one robot's stop query (``for_robots`` makes it every robot's)."""
    return f"{_robot(robot)}/launcher/*/stop"


def launcher_restart(robot: str, launcher: str, node: str = "*") -> str:
    """Restart one node of a launcher's graph (an operator's control query). The node is the last chunk, in the key
    rather than a payload so that an access rule can name the nodes an identity may restart; the launcher answers
    on ``*`` and reads the node with :func:`restarted_node`."""
    return f"{_robot(robot)}/launcher/{check_name(launcher, 'launcher name')}/restart/{_node(node)}"


def all_launcher_restart(robot: str, node: str = "*") -> str:
    """Every launcher of one robot's restart query for ``node`` (``for_robots`` makes it every robot's)."""
    return f"{_robot(robot)}/launcher/*/restart/{_node(node)}"


def restarted_node(key: str) -> str:
    """The node a restart query's key names (:func:`launcher_restart`): its last chunk, not checked (the launcher
    answers a name that is none of its nodes with the list of them)."""
    return str(key).rsplit("/", 1)[-1]


def _node(node: str) -> str:
    return node if node == "*" else check_name(node, "node name")


def robot_all(robot: str) -> str:
    """Every key of one robot (recording a session)."""
    return f"{_robot(robot)}/**"


def robot_recovery(robot: str) -> str:
    """What zenoh's advanced publishers and subscribers exchange under one robot's keys to recover a stream's missed
    frames (services/bus.py): its cache's queryable and replies, below a verbatim ``@adv`` chunk that ``**`` does not
    match."""
    return f"{_robot(robot)}/**/@adv/**"


# The streams a cut robot <-> base station link must not lose for good (docs/deploy.md, "When the link drops"): the
# frames their publishers keep for the subscribers that missed them (30 s at 10 Hz; odometry 10 s at 100 Hz), within
# the byte budget of services/bus.py's recover_cache; every subscriber of the exact key asks for what it missed. Small
# streams only: a subscriber also asks every second for what it has not had yet, so on a thin link whose queues hold a
# second or more, a big stream's frames still on their way are sent again, and the link collapses (heatlines and
# heatmaps at 1 Mbit/s: poses 6.4 -> 0.6 Hz, the camera's loop held). A graph turns them on for a link with headroom
# (`outputs: {heatmaps: {recover: 300}}` at the detector, `inputs: {heatmaps: {recover: true}}` at the mapper).
RECOVERABLE_STREAMS = {odometry: 1000, groundtruth_pose: 300, localizer_pose: 300}


def recover_frames(key: str) -> int:
    """The frames the publisher of ``key`` keeps for a subscriber that missed them (0: a plain stream)."""
    robot = robot_of(key)
    return 0 if robot is None else next((n for key_of, n in RECOVERABLE_STREAMS.items() if key_of(robot) == key), 0)


def robot_statuses(robot: str) -> str:
    """The Status key of every worker of one robot."""
    return f"{_robot(robot)}/*/status"


def robot_alive(robot: str) -> str:
    """The liveliness token of every worker of one robot."""
    return f"{_robot(robot)}/*/alive"


def loopclosure_all(robot: str) -> str:
    """Every output of the loop-closure worker (events, similarity rows, map updates, features)."""
    return f"{_robot(robot)}/loopclosure/**"


def for_robots(key_of, robot: str) -> str:
    """The key ``key_of(robot)`` (e.g. ``localizer_relocalize``), or its expression over every robot when
    ``robot`` is ``*``: what an operator's query asks."""
    if robot != "*":
        return key_of(robot)
    return f"{PREFIX}/*" + key_of("robot")[len(_robot("robot")):]


def robot_of(key: str) -> str | None:
    """The robot a key expression names (``semloc/<robot>/...``); None when it names none in particular (a wildcard
    in the robot's chunk, a key outside semloc's, e.g. a ROS 2 topic's)."""
    parts = str(key).split("/")
    if len(parts) < 2 or parts[0] != PREFIX:
        return None
    try:
        return check_name(parts[1], "robot name")
    except ValueError:  # '*', '**', '$*': any robot
        return None


def worker_of(key: str) -> tuple[str, str]:
    """(robot, worker) of a status or liveliness key; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[3] not in ("status", "alive"):
        raise ValueError(f"not a worker status/liveliness key: {key!r}")
    return parts[1], parts[2]
