"""rerun output of a worker: to a viewer over gRPC, to an ``.rrd`` file, or off.

Every worker of one run logs under the same recording id (the launcher sets it), so the viewer merges them; each
worker writes its own file (``<dir>/<worker>.rrd`` when the path is a directory). Entity paths read like a tree:
``/<robot>/<worker>/<what>``. Timelines: ``frame`` (the frame's sequence number) and ``capture`` (its stamp).
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

log = logging.getLogger("semloc.viz")

DEFAULT_VIEWER = "rerun+http://127.0.0.1:9876/proxy"


class RerunConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    mode: Literal["off", "save", "grpc"] = "off"
    path: str | None = Field(None, description=".rrd file, or a directory for <worker>.rrd (mode save)")
    url: str = Field(DEFAULT_VIEWER, description="viewer gRPC URL (mode grpc)")
    recording_id: str | None = Field(None, description="shared by every worker of a run; set by the launcher")
    jpeg_quality: int | None = Field(80, ge=1, le=100, description="images are logged JPEG-compressed; None = raw")


def rrd_path(config: RerunConfig, worker: str) -> Path:
    if not config.path:
        return Path(f"{worker}.rrd")
    path = Path(config.path)
    if path.suffix != ".rrd" or path.is_dir():
        return path / f"{worker}.rrd"
    return path


def open_recording(config: RerunConfig, worker: str):
    """A ``rerun.RecordingStream`` for this worker, or None when rerun output is off."""
    if config.mode == "off":
        return None
    import rerun as rr  # ~0.8 s: only when asked for

    recording_id = config.recording_id or str(uuid.uuid4())
    stream = rr.RecordingStream("semloc", recording_id=recording_id)
    if config.mode == "save":
        path = rrd_path(config, worker)
        path.parent.mkdir(parents=True, exist_ok=True)
        stream.save(str(path))
        log.info("rerun: saving to %s (recording %s)", path, recording_id)
    else:
        stream.connect_grpc(config.url)
        log.info("rerun: streaming to %s (recording %s)", config.url, recording_id)
    return stream
