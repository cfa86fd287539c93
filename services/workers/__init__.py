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


def module_name(kind: str) -> str:
    """``camera`` -> ``services.workers.camera``; a dotted name (``my_pkg.my_worker``) is used as is, so workers
    living outside semloc (or in tests) run the same way."""
    return kind if "." in kind else f"services.workers.{kind}"


def exists(kind: str) -> bool:
    if not all(part.isidentifier() for part in kind.split(".")):
        return False
    try:
        return importlib.util.find_spec(module_name(kind)) is not None
    except ModuleNotFoundError:  # a dotted name whose package does not exist
        return False


def load_worker(kind: str) -> type[Worker]:
    if not exists(kind):
        raise WorkerNotFound(f"no worker {kind!r}; available: {', '.join(available()) or 'none'}")
    module = importlib.import_module(module_name(kind))
    cls = getattr(module, "WORKER", None)
    if not (isinstance(cls, type) and issubclass(cls, Worker)):
        raise WorkerNotFound(f"{module.__name__} must define WORKER = <a Worker subclass>")
    if not cls.kind:
        cls.kind = kind.rsplit(".", 1)[-1]
    return cls


def check_node_config(node: str, kind: str, config: dict, environ: dict | None = None) -> dict:
    """A graph node's ``config`` validated as the worker will build it (its config file < the ``SEMLOC__*``
    environment), in the launcher's working directory, where nodes run; returns ``config``. ConfigError naming
    the node and every bad field: a misspelt field fails here, at load and in ``semloc up --dry-run``, not when
    the worker starts."""
    from services.config import ConfigError, build, from_env

    try:
        cls = load_worker(kind)
    except WorkerNotFound as error:
        raise ConfigError(f"node {node}: {error}") from None
    try:
        build(cls.Config, config, from_env(cls.Config, environ))
    except ConfigError as error:
        raise ConfigError(f"node {node}: {error}") from None
    return config
