"""JSON Schema of every frame type, for peers written in other languages (``semloc schema``).

Each file ``schemas/jsonschema/<schema>.v<version>.json`` describes the msgpack header map of one frame type
(docs/wire.md): the ``schema`` and ``version`` constants, the ``header`` and the fields, with arrays as descriptor
maps pointing into the data section.
"""

from __future__ import annotations

import json
from pathlib import Path

from schemas.base import frame_types

DEFAULT_DIR = Path(__file__).resolve().parent / "jsonschema"


def frame_json_schema(cls) -> dict:
    schema = cls.model_json_schema(mode="validation")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = f"semloc:{cls.schema_name}:v{cls.schema_version}"
    schema["title"] = cls.schema_name
    schema["properties"] = {
        "schema": {"const": cls.schema_name},
        "version": {"const": cls.schema_version},
        **schema["properties"],
    }
    schema["required"] = ["schema", "version", *schema.get("required", [])]
    schema["x-semloc-max-bytes"] = cls.max_bytes
    return schema


def export_all() -> dict[str, str]:
    """File name -> JSON text, for every registered frame type."""
    return {
        f"{name}.v{version}.json": json.dumps(frame_json_schema(cls), indent=2, sort_keys=True) + "\n"
        for (name, version), cls in frame_types().items()
        if cls.__module__.startswith("schemas.")  # frame types defined elsewhere (tests, plugins) are not ours
    }


def write(directory: Path = DEFAULT_DIR) -> list[Path]:
    """Write every schema file into ``directory`` and remove stale ``*.json`` files there."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    files = export_all()
    for stale in directory.glob("*.json"):
        if stale.name not in files:
            stale.unlink()
    written = []
    for name, text in files.items():
        path = directory / name
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
        written.append(path)
    return written


def differences(directory: Path = DEFAULT_DIR) -> list[str]:
    """Human-readable differences between the models and the files in ``directory`` (empty = in sync)."""
    directory = Path(directory)
    files = export_all()
    problems = []
    for name, text in files.items():
        path = directory / name
        if not path.exists():
            problems.append(f"missing {path}")
        elif path.read_text() != text:
            problems.append(f"out of date {path}")
    for path in sorted(directory.glob("*.json")):
        if path.name not in files:
            problems.append(f"stale {path} (no such frame type)")
    return problems
