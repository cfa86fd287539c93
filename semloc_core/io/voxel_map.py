"""Voxel map files: the mapper's state as .npz (no pickle) and hot voxels as a binary PLY point cloud.

* ``save_voxel_snapshot(path, arrays)`` / ``load_voxel_snapshot(path)``: the named arrays of
  ``semloc_core.mapping.VoxelMapper.snapshot()`` in an uncompressed ``.npz`` (written atomically; read with
  ``allow_pickle=False``). Restore with ``VoxelMapper.from_snapshot(load_voxel_snapshot(path))``.
* ``save_voxel_map(path, class_names, origin, voxel_size, scores, views, frames)`` / ``load_voxel_map(path)``: the
  mapper's score volumes as plain arrays in an ``.npz`` (format ``semloc.voxel_map`` v1), for any numpy user:
  ``scores`` (C, nz, ny, nx) float32 indexed ``[class, k, j, i]``, voxel (i, j, k) centred at
  ``origin + (i + 0.5, j + 0.5, k + 0.5) * voxel_size`` (world frame, metres), ``views`` (nz, ny, nx) how many
  frames saw each voxel, ``class_names`` (C,) strings, ``frames`` the frames integrated.
* ``save_ply(path, points, colors, scalars)``: a ``binary_little_endian`` PLY of vertices (x, y, z float32,
  optional red/green/blue uchar, optional extra float32 properties such as the score and the class index) -
  readable by MeshLab, CloudCompare, Open3D and rerun's loaders. ``load_ply`` reads such files back.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from semloc_core.io.atomic import replacing

class VoxelMapFileError(ValueError):
    """A voxel map file that cannot be read or does not hold what it should."""


def save_voxel_snapshot(path, arrays: dict[str, np.ndarray], compress: bool = False) -> None:
    """Write named arrays to ``path`` (.npz), atomically: a crash mid-write leaves the previous file intact."""
    path = Path(path)
    for name, array in arrays.items():
        if np.asarray(array).dtype == object:
            raise ValueError(f"array {name!r} has dtype object, which cannot be stored without pickle")
    # np.savez's layout, with a fixed member time: the same arrays give the same bytes (files compare equal)
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with replacing(path) as file, zipfile.ZipFile(file, "w", compression=method) as archive:
        for name, array in arrays.items():
            member = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            member.compress_type = method
            with archive.open(member, "w", force_zip64=True) as stream:
                np.lib.format.write_array(stream, np.asanyarray(array), allow_pickle=False)


def load_voxel_snapshot(path) -> dict[str, np.ndarray]:
    """All arrays of an .npz written by ``save_voxel_snapshot``; VoxelMapFileError with the reason otherwise."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise VoxelMapFileError(f"cannot read voxel map {path}: {error}") from None


VOXEL_MAP_FORMAT = "semloc.voxel_map"
VOXEL_MAP_VERSION = 1


def save_voxel_map(path, class_names, origin, voxel_size: float, scores, views, frames: int) -> None:
    """Write the score volumes of a voxel map as plain arrays (see the module docstring), atomically."""
    scores = np.asarray(scores, np.float32)
    views = np.asarray(views, np.float32)
    names = [str(name) for name in class_names]
    if scores.ndim != 4 or scores.shape[0] != len(names) or views.shape != scores.shape[1:]:
        raise ValueError(f"scores must be (C={len(names)}, nz, ny, nx) and views (nz, ny, nx), got {scores.shape} "
                         f"and {views.shape}")
    save_voxel_snapshot(path, {
        "format": np.array(VOXEL_MAP_FORMAT), "version": np.array(VOXEL_MAP_VERSION),
        "class_names": np.array(names, dtype=str), "origin": np.asarray(origin, np.float64).reshape(3),
        "voxel_size": np.array(float(voxel_size)), "frames": np.array(int(frames)), "scores": scores,
        "views": views})


def load_voxel_map(path) -> dict[str, np.ndarray]:
    """The arrays of a file written by :func:`save_voxel_map`; VoxelMapFileError if it is not one."""
    arrays = load_voxel_snapshot(path)
    if str(arrays.get("format", "")) != VOXEL_MAP_FORMAT or int(arrays.get("version", 0)) != VOXEL_MAP_VERSION:
        raise VoxelMapFileError(f"{path}: not a {VOXEL_MAP_FORMAT} v{VOXEL_MAP_VERSION} file")
    scores, views = arrays.get("scores"), arrays.get("views")
    if scores is None or views is None or scores.ndim != 4 or views.shape != scores.shape[1:] \
            or len(arrays.get("class_names", ())) != scores.shape[0]:
        raise VoxelMapFileError(f"{path}: scores, views and class_names do not agree")
    return arrays


def save_ply(path, points, colors=None, scalars: dict[str, np.ndarray] | None = None) -> None:
    """Write points (N, 3) with optional uchar colours (N, 3) and float32 scalar properties as binary PLY."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(points)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [points[:, 0], points[:, 1], points[:, 2]]
    header = ["ply", "format binary_little_endian 1.0", "comment written by semloc", f"element vertex {n}",
              "property float x", "property float y", "property float z"]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (n, 3):
            raise ValueError(f"colors must be (N, 3) for N={n} points, got {colors.shape}")
        colors = np.clip(colors, 0, 255).astype(np.uint8)
        for axis, name in enumerate(("red", "green", "blue")):
            fields.append((name, "u1"))
            columns.append(colors[:, axis])
            header.append(f"property uchar {name}")
    for name, values in (scalars or {}).items():
        values = np.asarray(values, dtype=np.float32).reshape(-1)
        if values.shape != (n,) or not name.isidentifier():
            raise ValueError(f"scalar {name!r} must be an identifier with one value per point")
        fields.append((name, "<f4"))
        columns.append(values)
        header.append(f"property float {name}")
    header.append("end_header")
    record = np.empty(n, dtype=np.dtype(fields))
    for (name, _), column in zip(fields, columns):
        record[name] = column
    with replacing(path) as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(record.tobytes())


_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "ushort": "<u2", "uint16": "<u2", "short": "<i2", "int16": "<i2",
              "uint": "<u4", "uint32": "<u4", "int": "<i4", "int32": "<i4"}


def load_ply(path) -> np.ndarray:
    """The vertex records of a binary little-endian PLY with only a vertex element (what ``save_ply`` writes)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise VoxelMapFileError(f"cannot read {path}: {error}") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise VoxelMapFileError(f"{path} is not a PLY file")
    fields, count = [], None
    for line in io.StringIO(data[:end].decode("ascii", errors="replace")):
        words = line.split()
        if words[:2] == ["format", "ascii"] or words[:2] == ["format", "binary_big_endian"]:
            raise VoxelMapFileError(f"{path}: only binary_little_endian PLY is supported")
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[:1] == ["element"]:
            raise VoxelMapFileError(f"{path}: only a vertex element is supported, found {words[1]!r}")
        elif words[:1] == ["property"]:
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise VoxelMapFileError(f"{path}: unsupported property line {line.strip()!r}")
            fields.append((words[2], _PLY_TYPES[words[1]]))
    if count is None:
        raise VoxelMapFileError(f"{path}: no vertex element")
    dtype = np.dtype(fields)
    body = data[end + len(b"end_header\n"):]
    if len(body) != count * dtype.itemsize:
        raise VoxelMapFileError(f"{path}: expected {count} vertices of {dtype.itemsize} bytes, got {len(body)} bytes")
    return np.frombuffer(body, dtype=dtype, count=count)
