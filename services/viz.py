"""rerun output of a worker: to a viewer over gRPC, to an ``.rrd`` file, served to a web viewer, or off.

Every worker of one run logs under the same recording id (the launcher sets it: the run id), so the viewer opens
their logs as one recording; each worker writes its own file (``<dir>/<worker>.rrd`` when the path is a directory).
Every recording carries the viewer layout (services/blueprint.py) unless ``layout`` is off. Entity paths read like a
tree: ``/<robot>/<worker>/<what>``. Timelines: ``frame`` (the frame's sequence number) and ``capture`` (its stamp).

The command-line options are rerun's usual ones (:func:`add_rerun_arguments`): ``--connect [URL]``,
``--rerun-save PATH``, ``--serve-web`` and ``--headless``. ``--serve-web`` hosts a gRPC server on loopback (``grpc_port``) and the web viewer
(``web_port``; rerun binds it on every interface, the data stays on loopback): the page at
``http://127.0.0.1:<web_port>/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A<grpc_port>%2Fproxy`` shows the run.
"""

from __future__ import annotations

import argparse
import logging
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Literal
from urllib.parse import quote, urlparse

from pydantic import BaseModel, ConfigDict, Field

log = logging.getLogger("semloc.viz")

DEFAULT_VIEWER = "rerun+http://127.0.0.1:9876/proxy"
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
SERVER_MEMORY_LIMIT = "25%"  # what a viewer connecting late still gets (the oldest data goes first)


class RerunConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    mode: Literal["off", "save", "grpc", "serve"] = "off"
    path: str | None = Field(None, description=".rrd file, or a directory for <worker>.rrd (mode save)")
    url: str = Field(DEFAULT_VIEWER, description="viewer gRPC URL (mode grpc)")
    grpc_port: int = Field(DEFAULT_GRPC_PORT, ge=0, le=65535, description="mode serve: the gRPC server's port "
                                                                           "(loopback)")
    web_port: int = Field(DEFAULT_WEB_PORT, ge=0, le=65535, description="mode serve: the web viewer's port")
    recording_id: str | None = Field(None, description="shared by every worker of a run; set by the launcher")
    jpeg_quality: int | None = Field(80, ge=1, le=100, description="images are logged JPEG-compressed; None = raw")
    layout: bool = Field(True, description="send the viewer layout (services/blueprint.py) with the recording")
    classes: list[str] = Field(default_factory=list, description="the layout's heatmap tabs (default: one view)")
    nodes: dict[str, str] = Field(default_factory=dict, description="role (camera, detector, ...) -> node name in "
                                                                    "the layout; set by the launcher")
    max_mb: float | None = Field(None, gt=0, description="mode save: a worker's .rrd files hold at most this many "
                                 "MB in all (rotated, the oldest deleted; RotatingSave); None: one file, unbounded")
    files: int = Field(4, ge=2, description="mode save with max_mb: the files a worker's output is split into")


def rrd_path(config: RerunConfig, worker: str) -> Path:
    if not config.path:
        return Path(f"{worker}.rrd")
    path = Path(config.path)
    if path.suffix != ".rrd" or path.is_dir():
        return path / f"{worker}.rrd"
    return path


def layout(config: RerunConfig, robot: str):
    """The viewer layout of a run on ``robot`` (None when ``layout`` is off)."""
    if not config.layout:
        return None
    from services.blueprint import semloc_blueprint

    return semloc_blueprint(robot, config.classes, config.nodes)


def grpc_url(port: int) -> str:
    return f"rerun+http://127.0.0.1:{port}/proxy"


def viewer_listens(url: str, timeout_s: float = 1.0) -> bool:
    """Whether something accepts connections at a viewer's gRPC URL (``rerun+http://host:port/proxy``)."""
    address = urlparse(url.removeprefix("rerun+"))
    try:
        with socket.create_connection((address.hostname or "127.0.0.1", address.port or 9876), timeout=timeout_s):
            return True
    except OSError:
        return False


def web_viewer_url(web_port: int, grpc_port: int) -> str:
    """The page of the web viewer showing the gRPC server's data."""
    return f"http://127.0.0.1:{web_port}/?url={quote(grpc_url(grpc_port), safe='')}"


def serve(stream, config: RerunConfig, blueprint=None) -> str:
    """Host the gRPC server (loopback) and the web viewer for ``stream``; returns the web viewer's URL."""
    import rerun as rr

    stream.set_sinks(rr.GrpcServerSink("127.0.0.1", config.grpc_port, server_memory_limit=SERVER_MEMORY_LIMIT),
                     default_blueprint=blueprint)
    rr.serve_web_viewer(web_port=config.web_port, open_browser=False, connect_to=grpc_url(config.grpc_port))
    return web_viewer_url(config.web_port, config.grpc_port)


def open_recording(config: RerunConfig, worker: str, robot: str):
    """A ``rerun.RecordingStream`` for this worker (with the run's layout), or None when rerun output is off."""
    if config.mode == "off":
        return None
    import rerun as rr  # ~0.8 s: only when asked for

    recording_id = config.recording_id or str(uuid.uuid4())
    stream = rr.RecordingStream("semloc", recording_id=recording_id)
    blueprint = layout(config, robot)
    if config.mode == "save":
        path = rrd_path(config, worker)
        path.parent.mkdir(parents=True, exist_ok=True)
        stream.save(str(path), default_blueprint=blueprint)
        log.info("rerun: saving to %s (recording %s%s)", path, recording_id,
                 f", {config.max_mb:g} MB at most in {config.files} files" if config.max_mb else "")
        if config.max_mb:
            started_ns = time.time_ns()  # the recording's start time, sent again into every file
            stream.send_recording_start_time_nanos(started_ns)
            return RotatingSave(stream, path, blueprint, int(config.max_mb * 1e6) // config.files, config.files,
                                started_ns)
    elif config.mode == "serve":
        log.info("rerun: web viewer at %s (recording %s)", serve(stream, config, blueprint), recording_id)
    else:
        stream.connect_grpc(config.url, default_blueprint=blueprint)
        log.info("rerun: streaming to %s (recording %s)", config.url, recording_id)
    return stream


def _arrow_bytes(entity) -> int:
    """The bytes of an archetype's data (its components' Arrow arrays): about what it takes in an .rrd."""
    try:
        return sum(batch.as_arrow_array().nbytes for batch in entity.as_component_batches())
    except Exception:  # not an archetype rerun can tell the size of: counted as nothing
        return 0


class RotatingSave:
    """A recording stream saved to a bounded set of files: once the open file holds ``file_bytes``, the stream is
    saved to the next (``run.rrd``, ``run.1.rrd``, ``run.2.rrd`` ...: same recording id, the layout sent again) and
    the oldest beyond ``files`` is deleted. rerun sends a static entity once, to the sink of the moment, so the last
    value of each one logged is logged again into every new file, and so is the recording's start time (a property,
    sent once too): each file opens alone with the map, the layout and the run's start. Otherwise a
    ``rerun.RecordingStream`` (what the runtime calls on it)."""

    def __init__(self, stream, path: Path, blueprint, file_bytes: int, files: int, started_ns: int):
        self._stream, self._blueprint, self.file_bytes, self.files = stream, blueprint, file_bytes, files
        self._started_ns = started_ns
        self._base, self._index = path, 0
        self.paths = [path]  # the files kept, oldest first; the last is open
        self._static: dict[str, object] = {}  # entity path -> its last static archetype
        self._logged = 0  # bytes logged into the open file
        self._lock = threading.Lock()

    def __getattr__(self, name):
        return getattr(self._stream, name)

    def log(self, entity_path: str, entity, *, static: bool = False) -> None:
        with self._lock:
            # Counted as logged (the file's size on disk lags by rerun's batches, a MB or more); the next file is
            # begun with the next entity, so none holds the layout alone.
            if self._logged >= self.file_bytes:
                self._rotate()
            self._stream.log(entity_path, entity, static=static)
            self._logged += _arrow_bytes(entity)
            if static:
                self._static[entity_path] = entity

    def _rotate(self) -> None:
        self._index += 1
        path = self._base.with_name(f"{self._base.name.removesuffix('.rrd')}.{self._index}.rrd")
        self._stream.save(str(path), default_blueprint=self._blueprint)  # what was logged before goes to the last
        self._stream.send_recording_start_time_nanos(self._started_ns)
        for entity_path, entity in self._static.items():
            self._stream.log(entity_path, entity, static=True)
        self._logged = sum(map(_arrow_bytes, self._static.values()))
        self.paths.append(path)
        while len(self.paths) > self.files:
            self.paths.pop(0).unlink(missing_ok=True)
        log.info("rerun: saving to %s (%d files kept)", path, len(self.paths))


def add_rerun_arguments(parser: argparse.ArgumentParser, *, connect: bool = True, save: str | None = None,
                        save_help: str = "log to this .rrd file (or directory: <node>.rrd per node)") -> None:
    """rerun's usual options (the names of ``rr.script_add_args``): ``--connect [URL]`` and ``--headless`` (unless
    ``connect`` is False: ``semloc worker``, where ``--connect`` is the zenoh endpoint and rerun is off unless asked
    for), ``--serve-web [PORT]`` and ``save`` (the option's name; None: none). :func:`rerun_overrides` turns them
    into ``rerun`` config fields."""
    group = parser.add_mutually_exclusive_group()
    if connect:
        group.add_argument("--connect", dest="rerun_connect", metavar="URL", nargs="?", const=DEFAULT_VIEWER,
                           help=f"stream to a running rerun viewer (default {DEFAULT_VIEWER})")
    group.add_argument("--serve-web", nargs="?", metavar="WEB_PORT", type=int, const=DEFAULT_WEB_PORT,
                       help=f"serve the web viewer (port {DEFAULT_WEB_PORT}) with the data on a loopback gRPC "
                            f"server (port {DEFAULT_GRPC_PORT}; semloc up: --set rerun.grpc_port=N)")
    if connect:
        group.add_argument("--headless", action="store_true", help="no rerun output (overrides the graph's)")
    if save is not None:
        group.add_argument(save, dest="rerun_save", metavar="PATH", help=save_help)


def rerun_overrides(args: argparse.Namespace) -> dict:
    """The ``rerun`` config fields the options of :func:`add_rerun_arguments` set ({} when none is given)."""
    if getattr(args, "headless", False):
        return {"mode": "off"}
    if getattr(args, "rerun_connect", None):
        return {"mode": "grpc", "url": args.rerun_connect}
    if getattr(args, "serve_web", None) is not None:
        return {"mode": "serve", "web_port": args.serve_web}
    if getattr(args, "rerun_save", None):
        return {"mode": "save", "path": args.rerun_save}
    return {}
