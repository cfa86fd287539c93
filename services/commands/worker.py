"""``semloc worker <kind> [options]``: run one worker in this process (the launcher runs each node this way).

A worker's own settings are its config's fields: ``--config FILE.yaml`` and ``--set field=value`` (``semloc worker
KIND --print-config`` shows them all, resolved). Precedence: defaults < ``--config`` YAML < ``SEMLOC__*``
environment < the options below and ``--set``.
"""

from __future__ import annotations

import argparse
import logging
import sys

import yaml

from services import config as cfg
from services.bus import BUS_FLAGS, add_bus_arguments
from services.runtime import Worker, WorkerConfig
from services.workers import WorkerNotFound, available, load_worker


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("kind", nargs="?", help="worker module under services/workers (see --list)")
    parser.add_argument("--list", action="store_true", help="list the available workers")
    parser.add_argument("worker_args", nargs=argparse.REMAINDER, help="worker options (use `semloc worker KIND -h`)")


def worker_parser(cls: type[Worker]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"semloc worker {cls.kind}", description=(cls.__doc__ or "").strip())
    parser.add_argument("--config", action="append", metavar="YAML", help="config file (repeatable, later wins)")
    parser.add_argument("--set", action="append", metavar="FIELD=VALUE",
                        help="set a config field (dotted path, YAML value), e.g. rerun.mode=grpc")
    parser.add_argument("--robot", help="robot namespace")
    parser.add_argument("--name", help="instance name (default: the worker kind)")
    parser.add_argument("--rerun-save", metavar="PATH", help="log to this .rrd file (or directory)")
    parser.add_argument("--state-dir", help="directory of crash-safe state snapshots")
    parser.add_argument("--log-level", help="DEBUG, INFO, WARNING...")
    parser.add_argument("--print-config", action="store_true", help="print the resolved config (YAML) and exit")
    add_bus_arguments(parser)
    return parser


def build_config(cls: type[Worker], args: argparse.Namespace, environ=None) -> WorkerConfig:
    """The worker's config: defaults < --config files < environment < options and --set (ConfigError)."""
    layers = [cfg.read_yaml(path) for path in args.config or []]
    layers.append(cfg.from_env(cls.Config, environ))
    flags: dict = {}
    for field in ("robot", "name", "state_dir", "log_level"):
        if getattr(args, field) is not None:
            flags[field] = getattr(args, field)
    bus = {f: getattr(args, f) for f in BUS_FLAGS if getattr(args, f)}
    if bus:
        flags["bus"] = bus
    if args.rerun_save:
        flags["rerun"] = {"mode": "save", "path": args.rerun_save}
    layers += [flags, cfg.from_sets(args.set)]
    return cfg.build(cls.Config, *layers)


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), stream=sys.stderr,
                        format=f"%(asctime)s {name} %(levelname)s %(name)s: %(message)s", force=True)


def run_worker(kind: str, argv: list[str]) -> int:
    cls = load_worker(kind)
    args = worker_parser(cls).parse_args(argv)
    config = build_config(cls, args)
    if args.print_config:
        print(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False), end="")
        return 0
    setup_logging(config.log_level, config.name or kind)
    return cls(config).main()


def run(args) -> int:
    if args.list or not args.kind:
        for kind in available():
            try:
                doc = (load_worker(kind).__doc__ or "").strip().splitlines()[0]
            except Exception as error:  # a broken module must not hide the others
                doc = f"(cannot load: {error})"
            print(f"{kind:14s} {doc}")
        return 0
    try:
        return run_worker(args.kind, list(args.worker_args))
    except (WorkerNotFound, cfg.ConfigError) as error:
        print(f"semloc worker: {error}", file=sys.stderr)
        return 2
