"""``semloc worker <kind> [options]``: run one worker in this process (the launcher runs each node this way).

Options common to every worker, then one flag per scalar field of the worker's config (``--help`` lists them).
Precedence: defaults < ``--config`` YAML < ``SEMLOC__*`` environment < flags and ``--set``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from services import config as cfg
from services.bus import BUS_FLAGS, add_bus_arguments
from services.runtime import Worker, WorkerConfig
from services.workers import WorkerNotFound, available, load_worker

COMMON_FIELDS = set(WorkerConfig.model_fields)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("kind", nargs="?", help="worker module under services/workers (see --list)")
    parser.add_argument("--list", action="store_true", help="list the available workers")
    parser.add_argument("worker_args", nargs=argparse.REMAINDER, help="worker options (use `semloc worker KIND -h`)")


def worker_parser(cls: type[Worker]) -> tuple[argparse.ArgumentParser, list[str]]:
    parser = argparse.ArgumentParser(prog=f"semloc worker {cls.kind}", description=(cls.__doc__ or "").strip())
    parser.add_argument("--config", action="append", metavar="YAML", help="config file (repeatable, later wins)")
    parser.add_argument("--set", action="append", metavar="FIELD=VALUE", help="set a config field (dotted path)")
    parser.add_argument("--robot", help="robot namespace")
    parser.add_argument("--name", help="instance name (default: the worker kind)")
    parser.add_argument("--rerun-save", metavar="PATH", help="log to this .rrd file (or directory)")
    parser.add_argument("--rerun-connect", metavar="URL", nargs="?", const="default",
                        help="stream to a rerun viewer over gRPC (default URL: the local viewer)")
    parser.add_argument("--rerun-id", metavar="ID", help="rerun recording id (shared by a run's workers)")
    parser.add_argument("--state-dir", help="directory of crash-safe state snapshots")
    parser.add_argument("--run-dir", help="directory where the config snapshot of this run is written")
    parser.add_argument("--log-level", help="DEBUG, INFO, WARNING...")
    add_bus_arguments(parser)
    names = cfg.add_field_flags(parser, cls.Config, skip=COMMON_FIELDS)
    return parser, names


def build_config(cls: type[Worker], argv: list[str], environ=None) -> WorkerConfig:
    parser, names = worker_parser(cls)
    args = parser.parse_args(argv)
    layers = [cfg.read_yaml(path) for path in args.config or []]
    layers.append(cfg.from_env(cls.Config, environ))
    flags: dict = {}
    for field in ("robot", "name", "state_dir", "run_dir", "log_level"):
        if getattr(args, field) is not None:
            flags[field] = getattr(args, field)
    bus = {f: getattr(args, f) for f in BUS_FLAGS if getattr(args, f)}
    if bus:
        flags["bus"] = bus
    rerun: dict = {}
    if args.rerun_save:
        rerun.update(mode="save", path=args.rerun_save)
    if args.rerun_connect:
        rerun["mode"] = "grpc"
        if args.rerun_connect != "default":
            rerun["url"] = args.rerun_connect
    if args.rerun_id:
        rerun["recording_id"] = args.rerun_id
    if rerun:
        flags["rerun"] = rerun
    layers += [flags, cfg.from_field_flags(args, names), cfg.from_sets(args.set)]
    return cfg.build(cls.Config, *layers)


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), stream=sys.stderr,
                        format=f"%(asctime)s {name} %(levelname)s %(name)s: %(message)s", force=True)


def run_worker(kind: str, argv: list[str]) -> int:
    cls = load_worker(kind)
    config = build_config(cls, argv)
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
