"""The core's settings classes: one definition of each setting, with its default, meaning and checks.

``FilterConfig``, ``MapperConfig``, ``ExtractionConfig``, the loop closure's ``EngineParams``, ``MrfParams``,
``AlignmentParams`` and ``FeatureParams`` are frozen pydantic dataclasses made by :func:`settings`. Built in code
they check their values (a ValueError on one line naming the class, the field and what is wrong); a worker's
configuration nests them as they are, so a graph file's ``filter:``, ``extraction:`` or ``engine:`` block is
validated against the same fields, defaults and documentation, and an unknown field is refused.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import fields

from pydantic import ConfigDict, TypeAdapter, ValidationError
from pydantic.dataclasses import dataclass

from semloc_core.validation import describe_validation

# Unknown fields are refused; infinities (an unlimited depth) survive a JSON round trip as "Infinity".
SETTINGS_CONFIG = ConfigDict(extra="forbid", ser_json_inf_nan="strings")


def _describe(error: ValidationError) -> str:
    return describe_validation(error).replace("<document>: ", "")


def settings(cls=None, /, *, eq: bool = True):
    """Decorator: ``cls`` as a frozen, validated dataclass (``@settings`` or ``@settings(eq=False)``)."""
    def wrap(target):
        made = dataclass(frozen=True, eq=eq, config=SETTINGS_CONFIG)(target)
        validate = made.__init__

        @functools.wraps(validate)
        def __init__(self, *args, **kwargs):
            try:
                validate(self, *args, **kwargs)
            except ValidationError as error:  # one line, as every error of the core's
                raise ValueError(f"{made.__name__}: {_describe(error)}") from None

        made.__init__ = __init__
        return made

    return wrap if cls is None else wrap(cls)


def updated(config, values: Mapping, where: str = ""):
    """``config`` with ``values`` (a mapping of its fields, e.g. read from a file) replacing those fields, checked as
    its class checks them: a ValueError ``<where><field>: what is wrong`` otherwise."""
    current = {f.name: getattr(config, f.name) for f in fields(config)}
    try:
        return TypeAdapter(type(config)).validate_python({**current, **values})
    except ValidationError as error:
        raise ValueError(f"{where}{_describe(error)}") from None
