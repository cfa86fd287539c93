"""The frame codec: ``[u32 little-endian header length][msgpack header][padding][raw array bytes]``.

The msgpack header is a map ``{"schema": str, "version": int, "header": {...}, <fields>...}``; every ndarray in
the fields (at any depth) is replaced by a descriptor map ``{"__array__": true, "dtype", "shape", "offset",
"nbytes"}`` whose bytes live in the data section, which starts at the first multiple of 8 after the msgpack header.
Arrays are little-endian, C order, each at an 8-aligned offset. :func:`decode` returns read-only arrays that share
the payload buffer (no copy). Full description: docs/wire.md.
"""

from __future__ import annotations

import math
import struct

import msgpack
import numpy as np
from pydantic import BaseModel, ValidationError

from schemas.base import WIRE_DTYPES, Frame, FrameError, lookup

# Hard ceiling for any payload, before the schema is known (a frame type's own ``max_bytes`` applies after).
MAX_PAYLOAD_BYTES = 256 << 20
_MAX_RANK = 8
_ALIGN = 8
_U32 = struct.Struct("<I")
_SCALARS = frozenset({str, int, float, bool, type(None)})
_DTYPES = {name: np.dtype(name).newbyteorder("<") for name in WIRE_DTYPES}
_CANONICAL = {np.dtype(name).newbyteorder("<"): name for name in WIRE_DTYPES} | {
    np.dtype(name): name for name in WIRE_DTYPES
}


def _aligned(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN


def _msgpack_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot encode {type(value).__name__} in a frame")


def encode(frame: Frame, into: bytearray | None = None) -> bytes | bytearray:
    """Serialise a frame to its wire bytes (one copy of each array).

    ``into``: a bytearray to reuse (resized to the frame's length and returned), which saves allocating a new
    buffer per frame on a steady stream; the caller must not reuse it while the bytes are still needed."""
    if not isinstance(frame, Frame) or not type(frame).schema_name:
        raise FrameError(f"can only encode registered Frame instances, got {type(frame).__name__}")
    chunks: list = []
    cursor = 0

    def walk(value):
        nonlocal cursor
        if type(value) in _SCALARS:  # most values: return before the isinstance chain (encode is per frame)
            return value
        if isinstance(value, np.ndarray):
            name = _CANONICAL.get(value.dtype)
            if name is None:
                raise FrameError(f"dtype {value.dtype} cannot travel on the wire")
            array = np.ascontiguousarray(value, dtype=_DTYPES[name])
            offset = _aligned(cursor)
            if offset != cursor:
                chunks.append(bytes(offset - cursor))
            chunks.append(array.reshape(-1).view(np.uint8).data)
            cursor = offset + array.nbytes
            return {"__array__": True, "dtype": name, "shape": list(array.shape), "offset": offset, "nbytes": array.nbytes}
        if isinstance(value, BaseModel):
            # a model's __dict__ holds exactly its fields, in declaration order (extras and private attributes
            # live elsewhere); reading it skips pydantic's per-access descriptors
            return {name: walk(item) for name, item in value.__dict__.items()}
        if isinstance(value, (list, tuple)):
            return [walk(item) for item in value]
        if isinstance(value, dict):
            return {key: walk(item) for key, item in value.items()}
        return value

    body = walk(frame)
    body["schema"] = frame.schema_name
    body["version"] = frame.schema_version
    header = msgpack.packb(body, default=_msgpack_default, use_bin_type=True)
    lead = 4 + len(header)
    parts = [_U32.pack(len(header)), header]
    if chunks:
        parts.append(bytes(_aligned(lead) - lead))
        parts.extend(chunks)
    total = sum(memoryview(part).nbytes for part in parts)
    if total > frame.max_bytes:
        raise FrameError(f"{frame.schema_name} frame of {total} bytes exceeds its limit of {frame.max_bytes}")
    if into is None:
        return b"".join(parts)
    if len(into) != total:
        into[total:] = b""
        if len(into) < total:
            into.extend(bytes(total - len(into)))
    view = memoryview(into)
    offset = 0
    for part in parts:
        size = memoryview(part).nbytes
        view[offset : offset + size] = part
        offset += size
    view.release()
    return into


def peek_schema(data) -> tuple[str, int] | None:
    """(schema name, version) of a payload without validating it, or None if it is not a frame."""
    try:
        body = _unpack_header(memoryview(data), None)
        return str(body["schema"]), int(body["version"])
    except Exception:
        return None


def peek_header(data) -> tuple[str, str, int] | None:
    """(robot, stream, stamp_ns) of a frame's header without validating the frame (its arrays untouched), or None if
    it has none."""
    try:
        header = _unpack_header(memoryview(data), None)["header"]
        return str(header["robot"]), str(header.get("stream", "")), int(header.get("stamp_ns", 0))
    except Exception:
        return None


def _unpack_header(view: memoryview, object_hook):
    size = len(view)
    if size < 4:
        raise FrameError(f"payload of {size} bytes is too short for a frame", reason="decode")
    (header_len,) = _U32.unpack_from(view, 0)
    if header_len > size - 4:
        raise FrameError(f"header length {header_len} exceeds the payload ({size} bytes)", reason="decode")
    try:
        body = msgpack.unpackb(view[4 : 4 + header_len], object_hook=object_hook, raw=False, strict_map_key=True)
    except FrameError:
        raise
    except Exception as error:  # msgpack raises several unrelated types on garbage
        raise FrameError(f"undecodable frame header: {type(error).__name__}: {error}", reason="decode") from None
    if not isinstance(body, dict):
        raise FrameError("frame header is not a map", reason="decode")
    if not isinstance(body.get("schema"), str) or type(body.get("version")) is not int:
        raise FrameError("frame header lacks a string 'schema' and an integer 'version'", reason="decode")
    return body


def decode(data, expected: type[Frame] | tuple[type[Frame], ...] | None = None) -> Frame:
    """Validate wire bytes and build the frame; arrays are read-only views of ``data``.

    ``expected`` restricts the accepted frame types. Raises :class:`FrameError` on any violation.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise FrameError(f"expected bytes, got {type(data).__name__}", reason="decode")
    view = memoryview(data).toreadonly()
    if view.ndim != 1 or view.itemsize != 1:
        view = view.cast("B")
    size = len(view)
    if size > MAX_PAYLOAD_BYTES:
        raise FrameError(f"payload of {size} bytes exceeds the hard limit of {MAX_PAYLOAD_BYTES}", reason="size")
    if size >= 4:
        data_start = _aligned(4 + _U32.unpack_from(view, 0)[0])
    else:
        data_start = size
    data_size = size - data_start

    def array_hook(obj: dict):
        if "__array__" not in obj:
            return obj
        dtype_name, shape, offset, nbytes = obj.get("dtype"), obj.get("shape"), obj.get("offset"), obj.get("nbytes")
        if len(obj) != 5 or obj["__array__"] is not True:
            raise FrameError("malformed array descriptor", reason="array")
        if dtype_name not in _DTYPES:
            raise FrameError(f"dtype {dtype_name!r} is not allowed on the wire", reason="array")
        if (
            not isinstance(shape, list)
            or len(shape) > _MAX_RANK
            or not all(type(d) is int and d >= 0 for d in shape)
        ):
            raise FrameError(f"bad array shape {shape!r}", reason="array")
        if type(offset) is not int or type(nbytes) is not int or offset < 0 or nbytes < 0 or offset % _ALIGN:
            raise FrameError("bad array offset or size", reason="array")
        dtype = _DTYPES[dtype_name]
        count = math.prod(shape)
        if count * dtype.itemsize != nbytes:
            raise FrameError(f"shape {shape} of {dtype_name} needs {count * dtype.itemsize} bytes, header says {nbytes}",
                             reason="array")
        if offset + nbytes > data_size:
            raise FrameError(
                f"array of {nbytes} bytes at offset {offset} runs past the data section ({max(data_size, 0)} bytes)",
                reason="array")
        array = np.frombuffer(view, dtype=dtype, count=count, offset=data_start + offset).reshape(shape)
        if dtype_name == "bool" and count and array.view(np.uint8).max() > 1:
            raise FrameError("bool array holds values other than 0 and 1", reason="array")
        return array

    body = _unpack_header(view, array_hook)
    cls = lookup(body.pop("schema"), body.pop("version"))
    if expected is not None and not issubclass(cls, expected):
        names = [e.schema_name for e in (expected if isinstance(expected, tuple) else (expected,))]
        raise FrameError(f"expected {' or '.join(names)}, got {cls.schema_name}", reason="schema")
    if size > cls.max_bytes:
        raise FrameError(f"{cls.schema_name} frame of {size} bytes exceeds its limit of {cls.max_bytes}", reason="size")
    try:
        return cls.model_validate(body)
    except ValidationError as error:
        raise FrameError(f"invalid {cls.schema_name} frame: {_summarise(error)}", reason=_reason(error)) from None


# pydantic's error types -> FrameError reasons (the others are ``invalid``)
_RANGE_ERRORS = frozenset({"greater_than", "greater_than_equal", "less_than", "less_than_equal", "multiple_of"})
_REASONS = {**dict.fromkeys(_RANGE_ERRORS, "range"), "finite_number": "nonfinite", "too_long": "size",
            "string_too_long": "size", "bytes_too_long": "size"}


def _reason(error: ValidationError) -> str:
    """The reason of a model validation failure: its first error's (a validator's FrameError keeps its own)."""
    first = error.errors(include_url=False)[0]
    raised = (first.get("ctx") or {}).get("error")
    if isinstance(raised, FrameError):
        return raised.reason
    return _REASONS.get(first["type"], "invalid")


def _summarise(error: ValidationError, limit: int = 3) -> str:
    parts = []
    for item in error.errors(include_url=False)[:limit]:
        where = ".".join(str(p) for p in item["loc"]) or "<frame>"
        parts.append(f"{where}: {item['msg']}")
    more = error.error_count() - limit
    return "; ".join(parts) + (f" (+{more} more)" if more > 0 else "")
