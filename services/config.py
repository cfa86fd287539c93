"""Layered settings, one override syntax for every command: model defaults < YAML files < environment < command
line, validated by pydantic.

* YAML: a mapping of the model's fields (a worker's ``--config file.yaml``, an experiment's ``--spec`` or preset).
* Environment (workers): ``SEMLOC__<FIELD>[__<SUBFIELD>...]=value``, e.g. ``SEMLOC__ROBOT=r2``,
  ``SEMLOC__RERUN__RECORDING_ID=run-7``. Variables naming a field the model lacks are ignored (one environment
  serves every worker of a graph).
* Command line: ``--set field.sub=value`` (repeatable), in every command.

Values given as strings (environment, ``--set``) are parsed as YAML scalars/flow values: ``30`` -> 30,
``true`` -> True, ``[a, b]`` -> list, ``{k: 1}`` -> mapping.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from semloc_core.experiments.spec import read_spec_file
from semloc_core.validation import describe_validation, one_line

ENV_PREFIX = "SEMLOC__"


# The exit code of a worker or command stopped by a bad configuration or file: a launcher does not restart it.
CONFIG_ERROR_EXIT = 2


class ConfigError(ValueError):
    """A configuration file, variable or flag is invalid (the message, one line, says which)."""

    def __init__(self, message):
        super().__init__(one_line(message))


def parse_value(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def deep_merge(base: dict, update: Mapping) -> dict:
    merged = dict(base)
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(dict(merged[key]), value)
        else:
            merged[key] = value
    return merged


def dotted(path: str, value: Any) -> dict:
    """``"a.b.c", v`` -> ``{"a": {"b": {"c": v}}}``."""
    parts = [p for p in path.replace("-", "_").split(".") if p]
    if not parts:
        raise ConfigError(f"empty config path in {path!r}")
    result: Any = value
    for part in reversed(parts):
        result = {part: result}
    return result


def read_yaml(path: str | Path) -> dict:
    """A YAML file's mapping of config fields (ConfigError when it is missing, not YAML or not a mapping)."""
    try:
        return read_spec_file(path, "config")
    except ValueError as error:
        raise ConfigError(str(error)) from None


def from_env(model: type[BaseModel], environ: Mapping[str, str] | None = None) -> dict:
    environ = os.environ if environ is None else environ
    layer: dict = {}
    for name, text in environ.items():
        if not name.startswith(ENV_PREFIX):
            continue
        path = name[len(ENV_PREFIX) :].lower().split("__")
        if path[0] not in model.model_fields:
            continue
        layer = deep_merge(layer, dotted(".".join(path), parse_value(text)))
    return layer


def from_sets(sets: list[str] | None) -> dict:
    """``["a.b=1", "c=[x, y]"]`` (``--set`` options) -> ``{"a": {"b": 1}, "c": ["x", "y"]}``."""
    layer: dict = {}
    for item in sets or []:
        if "=" not in item:
            raise ConfigError(f"--set expects field.path=value, got {item!r}")
        path, text = item.split("=", 1)
        layer = deep_merge(layer, dotted(path.strip(), parse_value(text)))
    return layer


def build(model: type[BaseModel], *layers: Mapping) -> BaseModel:
    """``model`` from ``layers`` deep-merged in order (later wins); ConfigError naming every bad field."""
    merged: dict = {}
    for layer in layers:
        merged = deep_merge(merged, layer or {})
    try:
        return model.model_validate(merged)
    except ValidationError as error:
        raise ConfigError(f"invalid {model.__name__}: {describe_validation(error, limit=5)}") from None
