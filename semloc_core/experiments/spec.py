"""Experiment specs: typed settings in (pydantic models), read from YAML presets or files.

Every experiment of this package takes one spec: a frozen model whose fields are the experiment's settings, with
their defaults, ranges and meaning; an unknown or misspelt field is refused. A spec is built from a mapping
(``Spec.model_validate(dict)``, e.g. a YAML file), and the documented ones ship as presets:
``presets/<kind>/<name>.yaml`` (:func:`preset_file`).

A path in a spec may start with ``data:`` to name a file of the data folder (``$SEMLOC_SHARED_DATA``, or
``shared/data`` beside the repository), as ``sim:`` names a simulated world, and, in lists, be a glob pattern
(``data:rgbd_scenes_v2_poses/*.pose``), expanded sorted when the spec is built.
"""

from __future__ import annotations

import glob
from pathlib import Path
from typing import Annotated

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict

PRESETS_DIR = Path(__file__).resolve().parent / "presets"
DATA = "data:"


class Spec(BaseModel):
    """Base of every experiment spec: unknown fields refused, immutable once built."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def data_dir() -> Path | None:
    """The folder ``data:`` paths are in, or None when there is none."""
    from semloc_core.io.exemplars import shared_data_dir

    return shared_data_dir()


def expand_path(value: str | None) -> str | None:
    """``data:x`` -> the data folder's ``x``; other paths as they are."""
    if value is None or not value.startswith(DATA):
        return value
    folder = data_dir()
    if folder is None:
        raise ValueError(f"{value!r} names the data folder: set SEMLOC_SHARED_DATA to it")
    return str(folder / value[len(DATA):])


def expand_paths(values: list[str]) -> list[str]:
    """Each entry through :func:`expand_path`; a glob pattern (``*``, ``?``, ``[``) becomes its sorted matches."""
    out: list[str] = []
    for value in values:
        value = expand_path(value)
        if any(c in value for c in "*?["):
            matches = sorted(glob.glob(value))
            if not matches:
                raise ValueError(f"no file matches {value!r}")
            out += matches
        else:
            out.append(value)
    return out


DataPath = Annotated[str, AfterValidator(expand_path)]
DataPaths = Annotated[list[str], AfterValidator(expand_paths)]


def preset_names(kind: str) -> list[str]:
    """The presets of one kind of experiment (``mapping``, ``localization``, ...)."""
    return sorted(p.stem for p in (PRESETS_DIR / kind).glob("*.yaml"))


def preset_file(kind: str, name: str) -> Path:
    path = PRESETS_DIR / kind / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"no {kind} preset {name!r}; presets: {', '.join(preset_names(kind)) or 'none'}")
    return path


def read_spec_file(path: str | Path, what: str = "spec") -> dict:
    """A YAML file's mapping of fields (ValueError naming the file when it is missing, not YAML or not a
    mapping); ``what`` names the fields in the messages."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{what} file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise ValueError(f"{path} is not valid YAML: {' '.join(str(error).split())}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} must hold a mapping of {what} fields, got {type(data).__name__}")
    return data


def load_preset(kind: str, name: str) -> dict:
    """A preset's mapping of fields."""
    return read_spec_file(preset_file(kind, name))
