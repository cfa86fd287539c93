"""semloc demo: the whole system on a simulated table top, in one command, with its results (docs/demo.md).

A tabletop world is generated once (cached), camera, detector, loop closure, localizer and mapper run as separate
processes over zenoh on loopback (deploy/demo.yaml), the sequence plays, and the results table (loop closure P/R,
localization RMSE, mapping P/R, per-stage throughput and latency) is printed and written to OUTPUT with the merged
rerun recording run.rrd. What is played is a spec (services/demo_run.py DemoSpec: frames, laps, seed, appearance,
rate, localizer_start, ...): the full preset by default, --fast for the reduced one, --set to change a field, e.g.

  semloc demo --fast --set appearance=generated --set localizer_start=global
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from services.commands import fail, print_json
from services.config import ConfigError, build, from_sets
from services.viz import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT, add_rerun_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", default="runs/demo",
                        help="where run.rrd, results.{md,json}, plots/ and the workers' logs go (default runs/demo)")
    parser.add_argument("--cache", metavar="DIR", help="where generated worlds are kept (default $SEMLOC_CACHE_DIR, "
                                                       "else the user cache folder: ~/.cache/semloc on Linux)")
    parser.add_argument("--fast", action="store_true", help="the reduced run (preset fast: 120 frames, 2 laps)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="a DemoSpec field over the preset's, e.g. frames=200 or appearance=generated")
    parser.add_argument("--seed", type=int, help="the world's seed (= --set seed=N)")
    # rerun's usual options instead of writing run.rrd; --headless: no rerun output at all (fastest)
    add_rerun_arguments(parser)
    parser.add_argument("--record", action="store_true",
                        help="also record the session's bus traffic to OUTPUT/session.mcap (semloc replay plays it)")
    parser.add_argument("--graph", help="the demo's graph: a file or a built-in graph's name (default demo)")
    parser.add_argument("--robot", help="robot namespace (default: the graph's)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    parser.add_argument("--quiet", action="store_true", help="only the results")


def run(args: argparse.Namespace) -> int:
    from semloc_core.experiments.spec import load_preset
    from services.demo_run import DemoError, DemoOptions, DemoSpec, run_demo

    try:
        spec = build(DemoSpec, load_preset("demo", "fast" if args.fast else "full"),
                     {} if args.seed is None else {"seed": args.seed}, from_sets(args.set))
    except ConfigError as error:
        return fail("demo", error)
    command = "semloc demo " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 1 and \
        sys.argv[1] == "demo" else "semloc demo"
    options = DemoOptions(workdir=Path(args.output), cache_dir=Path(args.cache) if args.cache else None,
                          rerun="off" if args.headless else "connect" if args.rerun_connect else
                          "serve" if args.serve_web else "save", rerun_url=args.rerun_connect,
                          rerun_ports=(args.serve_web or DEFAULT_WEB_PORT, DEFAULT_GRPC_PORT),
                          record=args.record, robot=args.robot, quiet=args.quiet, command=command,
                          **({"graph": Path(args.graph)} if args.graph else {}))
    try:
        doc, markdown = run_demo(spec, options)
    except (ConfigError, ValueError, FileNotFoundError) as error:
        return fail("demo", error)
    except DemoError as error:
        print(f"semloc demo: {error}", file=sys.stderr)
        return 1
    workdir = Path(args.output).resolve()
    if args.json:
        print_json(doc)
    else:
        print(markdown)
        if not doc["run"]["write_error"]:
            print(f"results: {workdir / 'results.md'}, {workdir / 'results.json'}, plots in {workdir / 'plots'}")
    if doc["run"]["write_error"]:
        print(f"semloc demo: results not saved: {doc['run']['write_error']}", file=sys.stderr)
    if doc["run"]["rrd"]:
        print(f"recording: {doc['run']['rrd']}  (view it with: rerun {shlex.quote(doc['run']['rrd'])})")
    if options.viewer is not None:
        print("rerun web viewer: serving until Ctrl-C", file=sys.stderr, flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            options.viewer.disconnect()
    if doc["run"]["restarts_or_failures"]:
        print(f"warning: node restarts or failures: {json.dumps(doc['run']['restarts_or_failures'])}", file=sys.stderr)
    return 1 if doc["run"]["write_error"] else 0
