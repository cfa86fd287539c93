"""Worker modules: ``services/workers/<kind>.py`` defines ``WORKER = <Worker subclass>``.

``semloc worker <kind>`` and the launcher find workers by module name (see docs/runtime.md).
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil

from services.runtime import Worker


class WorkerNotFound(LookupError):
    pass


def available() -> list[str]:
    """Kinds of worker that exist in this installation."""
    return sorted(info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_"))


def exists(kind: str) -> bool:
    return importlib.util.find_spec(f"services.workers.{kind}") is not None if kind.isidentifier() else False


def load_worker(kind: str) -> type[Worker]:
    if not kind.isidentifier() or not exists(kind):
        raise WorkerNotFound(f"no worker {kind!r}; available: {', '.join(available()) or 'none'}")
    module = importlib.import_module(f"services.workers.{kind}")
    cls = getattr(module, "WORKER", None)
    if not (isinstance(cls, type) and issubclass(cls, Worker)):
        raise WorkerNotFound(f"services/workers/{kind}.py must define WORKER = <a Worker subclass>")
    if not cls.kind:
        cls.kind = kind
    return cls
