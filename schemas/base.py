"""Base classes of the wire contract: the error type, the frame header, the frame base class and array fields.

A frame type is one pydantic v2 model subclassing :class:`Frame` with two class keywords::

    class Heatmaps(Frame, schema="semloc.Heatmaps", version=1, max_bytes=64 << 20):
        classes: tuple[str, ...]
        scores: Array(dtypes=("uint8", "float16", "float32"), ndim=3, finite=True)

Subclassing registers the type (name, version) -> class; :func:`frame_types` also imports every module of the
``schemas`` package, so a new module dropped next to this one is found without any other edit. See docs/wire.md.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainSerializer, PlainValidator, WithJsonSchema


class FrameError(ValueError):
    """Any violation of the wire contract: undecodable bytes, unknown schema or version, a bad dtype or shape,
    NaN where forbidden, a size over the limit, or a model validation failure. The only error :func:`decode`
    raises; workers count it as a *rejected* frame, per ``reason``.

    ``reason`` is a short code naming the kind of violation (``[a-z_]+``), counted per input in the worker's
    status (``InputStats.rejected_reasons``): ``decode`` (not a frame), ``schema`` (unknown or unexpected type or
    version), ``size`` (over a limit), ``array`` (a bad array descriptor), ``range`` (a value outside its physical
    range, docs/wire.md, or a worker's configured limit), ``nonfinite`` (NaN or infinity), ``image_header`` (a
    compressed image whose header does not match its declared size), ``classes`` (class names outside the
    worker's configured set), ``calibration`` (does not match the camera model), ``nonfinite_state`` (a step that
    would have made the worker's state non-finite), ``invalid`` (any other violation of the model)."""

    def __init__(self, message: str, reason: str = "invalid"):
        super().__init__(message)
        if not _REASON_RE.match(reason):
            raise ValueError(f"FrameError reason must match {_REASON_RE.pattern}, got {reason!r}")
        self.reason = reason


# Every dtype allowed on the wire, by its canonical numpy name. Always little-endian on the wire.
WIRE_DTYPES: tuple[str, ...] = (
    "bool",
    "uint8",
    "int8",
    "uint16",
    "int16",
    "uint32",
    "int32",
    "uint64",
    "int64",
    "float16",
    "float32",
    "float64",
)

_REASON_RE = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
_NAME_PATTERN = r"^[A-Za-z0-9_.\-]+$"
_NAME_RE = re.compile(_NAME_PATTERN)
# A field that names a key chunk (a robot, a launcher): a frame naming one otherwise is refused when decoded.
KeyName = Annotated[str, Field(pattern=_NAME_PATTERN, max_length=64)]


def check_name(value: str, what: str = "name") -> str:
    """A key-expression-safe name: letters, digits, '_', '.', '-' (no '/', '*', '$', '#', '?')."""
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise ValueError(f"{what} must match {_NAME_PATTERN}, got {value!r}")
    return value


class Header(BaseModel):
    """Common header of every frame (the schema name and version are added from the frame's class on the wire).

    * ``robot``  - robot namespace of the stream, e.g. ``"r1"``.
    * ``stream`` - logical stream name, e.g. ``"camera/front"``.
    * ``seq``    - per-stream sequence number, starting at 0.
    * ``stamp_ns`` - capture time, integer nanoseconds (UNIX epoch for live data, the data set's clock otherwise).
    * ``frame_id`` - coordinate frame of the payload (``"world"``, ``"body"``, ``"cam0"``...), may be empty.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    robot: KeyName
    stream: Annotated[str, Field(max_length=256)] = ""
    seq: Annotated[int, Field(ge=0, lt=2**63)] = 0
    stamp_ns: Annotated[int, Field(ge=0, lt=2**63)] = 0
    frame_id: Annotated[str, Field(max_length=128)] = ""


def _array_json_schema(dtypes: tuple[str, ...], ndim: tuple[int, ...] | None, bounds, finite: bool,
                       max_elements: int | None, description: str | None) -> dict:
    shape: dict[str, Any] = {"type": "array", "items": {"type": "integer", "minimum": 0}}
    if ndim is not None:
        shape["minItems"] = min(ndim)
        shape["maxItems"] = max(ndim)
    extra: dict[str, Any] = {}
    if bounds is not None:  # the range of every element (JSON Schema cannot say it of the data section's bytes)
        extra["x-semloc-element-minimum"], extra["x-semloc-element-maximum"] = bounds
    if finite:
        extra["x-semloc-finite"] = True
    if max_elements is not None:
        extra["x-semloc-max-elements"] = max_elements
    return {**extra,
        "type": "object",
        "description": "array descriptor; raw little-endian bytes in the frame's data section"
                       + (f"; {description}" if description else ""),
        "properties": {
            "__array__": {"const": True},
            "dtype": {"enum": list(dtypes)},
            "shape": shape,
            "offset": {"type": "integer", "minimum": 0, "description": "byte offset in the data section"},
            "nbytes": {"type": "integer", "minimum": 0},
        },
        "required": ["__array__", "dtype", "shape", "offset", "nbytes"],
        "additionalProperties": False,
    }


def Array(
    dtypes: tuple[str, ...] | str = WIRE_DTYPES,
    ndim: int | tuple[int, ...] | None = None,
    shape: tuple[int | None, ...] | None = None,
    finite: bool = False,
    max_elements: int | None = None,
    bounds: tuple[float, float] | None = None,
    description: str | None = None,
):
    """An ndarray field: validated without copying (dtype whitelist, rank, fixed dims, size, finiteness, range).

    ``shape`` fixes dimensions (``None`` = any), e.g. ``shape=(4, 4)`` or ``shape=(None, 3)``; it implies ``ndim``.
    ``bounds=(lo, hi)``: every element in [lo, hi] (reason ``range``); ``finite``: no NaN or infinity (reason
    ``nonfinite``); over ``max_elements``: reason ``size``. ``description``: what the model checks besides, for
    the JSON Schema. Python lists are accepted when building a frame and converted to the first allowed dtype.
    """
    allowed = (dtypes,) if isinstance(dtypes, str) else tuple(dtypes)
    for name in allowed:
        if name not in WIRE_DTYPES:
            raise ValueError(f"dtype {name!r} is not a wire dtype {WIRE_DTYPES}")
    if shape is not None:
        ndims: tuple[int, ...] | None = (len(shape),)
    elif ndim is None:
        ndims = None
    else:
        ndims = (ndim,) if isinstance(ndim, int) else tuple(ndim)
    allowed_dtypes = tuple(np.dtype(name) for name in allowed)

    def validate(value):
        if not isinstance(value, np.ndarray):
            if isinstance(value, (list, tuple)) or np.isscalar(value):
                value = np.asarray(value, dtype=allowed_dtypes[0])
            else:
                raise ValueError(f"expected a numpy array, got {type(value).__name__}")
        if value.dtype.newbyteorder("=") not in allowed_dtypes or value.dtype.byteorder == ">":
            raise ValueError(f"dtype {value.dtype} not allowed here, expected one of {allowed}")
        if ndims is not None and value.ndim not in ndims:
            raise ValueError(f"expected {' or '.join(map(str, ndims))} dimensions, got shape {value.shape}")
        if shape is not None:
            for axis, (want, got) in enumerate(zip(shape, value.shape)):
                if want is not None and want != got:
                    raise ValueError(f"expected shape {shape}, got {value.shape} (axis {axis})")
        if max_elements is not None and value.size > max_elements:
            raise FrameError(f"array of {value.size} elements exceeds the limit of {max_elements}", reason="size")
        if finite and value.dtype.kind == "f" and value.size and not np.isfinite(value).all():
            raise FrameError("array contains NaN or infinite values", reason="nonfinite")
        if bounds is not None and value.size:
            low, high = value.min(), value.max()
            if not (low >= bounds[0] and high <= bounds[1]):  # NaN fails too
                raise FrameError(f"array values [{low}, {high}] outside [{bounds[0]}, {bounds[1]}]", reason="range")
        return value

    return Annotated[
        np.ndarray,
        PlainValidator(validate),
        PlainSerializer(lambda a: a.tolist(), when_used="json"),
        WithJsonSchema(_array_json_schema(allowed, ndims, bounds, finite, max_elements, description)),
    ]


# (schema name, version) -> frame class
_REGISTRY: dict[tuple[str, int], type["Frame"]] = {}
_DISCOVERED = False


class Frame(BaseModel):
    """Base of every frame type: a frozen model with a :class:`Header`.

    Class keywords: ``schema`` (dotted name, unique), ``version`` (int >= 1), ``max_bytes`` (encoded size limit,
    default 16 MiB). Floats must be finite unless a field says otherwise.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, protected_namespaces=())

    schema_name: ClassVar[str] = ""
    schema_version: ClassVar[int] = 0
    max_bytes: ClassVar[int] = 16 << 20

    header: Header

    def __init_subclass__(cls, schema: str | None = None, version: int = 1, max_bytes: int | None = None, **kw):
        super().__init_subclass__(**kw)
        if schema is None:
            return  # an abstract intermediate class
        check_name(schema, "schema name")
        if not isinstance(version, int) or version < 1:
            raise ValueError(f"schema version must be an int >= 1, got {version!r}")
        key = (schema, version)
        previous = _REGISTRY.get(key)
        if previous is not None and previous.__qualname__ != cls.__qualname__:
            raise ValueError(f"frame type {schema} v{version} already registered by {previous!r}")
        cls.schema_name = schema
        cls.schema_version = version
        if max_bytes is not None:
            cls.max_bytes = int(max_bytes)
        _REGISTRY[key] = cls

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs) -> None:
        super().__pydantic_init_subclass__(**kwargs)
        reserved = {"schema", "version"} & set(cls.model_fields)
        if reserved:
            _REGISTRY.pop((cls.schema_name, cls.schema_version), None)
            raise TypeError(f"{cls.__name__}: field names {sorted(reserved)} are reserved by the wire header")


class Sub(BaseModel):
    """Base for nested (non-frame) models inside frames: frozen, strict, finite floats."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, protected_namespaces=())


# Modules of this package that hold no frame types; every other module is imported by discovery.
_NOT_FRAME_MODULES = {"base", "codec", "keys", "export", "limits"}


def discover() -> None:
    """Import every module of the ``schemas`` package so that all frame types are registered."""
    global _DISCOVERED
    if _DISCOVERED:
        return
    package = importlib.import_module("schemas")
    for info in pkgutil.iter_modules(package.__path__):
        if info.name.startswith("_") or info.name in _NOT_FRAME_MODULES or info.ispkg:
            continue
        importlib.import_module(f"schemas.{info.name}")
    _DISCOVERED = True


def frame_types() -> dict[tuple[str, int], type[Frame]]:
    """All registered frame types, (schema name, version) -> class, after discovery."""
    discover()
    return dict(sorted(_REGISTRY.items()))


def lookup(schema: str, version: int) -> type[Frame]:
    """The class of a (schema, version); raises :class:`FrameError` when unknown."""
    cls = _REGISTRY.get((schema, version))
    if cls is None and not _DISCOVERED:
        discover()
        cls = _REGISTRY.get((schema, version))
    if cls is None:
        known = sorted(v for (n, v) in _REGISTRY if n == schema)
        if known:
            raise FrameError(f"unsupported version {version} of schema {schema!r} (known: {known})", reason="schema")
        raise FrameError(f"unknown schema {schema!r}", reason="schema")
    return cls
