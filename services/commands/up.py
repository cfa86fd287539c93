"""``semloc up GRAPH``: launch a dataflow graph, one process per node, until Ctrl-C or ``semloc stop``. GRAPH is a
graph file or a built-in graph's name (``local``, ``camera-sink``, ``two-machines/robot``: deploy/*.yaml, shipped with
semloc); relative paths inside a graph file are read from its folder."""

from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path

import yaml

from services.config import ConfigError, deep_merge, from_sets
from services.launcher import Launcher, find_graph, load_graph
from services.viz import add_rerun_arguments, rerun_overrides, viewer_listens
from services.security import (exposure_warnings, link_problems, placeholder_endpoints, secure_overrides,
                               use_secure_hub)

log = logging.getLogger("semloc.up")


def add_arguments(parser) -> None:
    parser.add_argument("graph", help="graph file, or a built-in graph's name (local, camera-sink, ...)")
    parser.add_argument("--robot", help="robot namespace (overrides the graph)")
    parser.add_argument("--hub", help="hub endpoint the launcher listens on (overrides the graph)")
    parser.add_argument("--camera", metavar="SOURCE",
                        help="the `camera` node's source: device index, rtsp/http URL, video, folder, bag, MCAP, data "
                             "set (= --set nodes.camera.config.source=SOURCE, source_type auto)")
    parser.add_argument("--save", metavar="DIR",
                        help="write the run's outputs to DIR while it runs: trajectory.tum, objects.json, voxels.npz/"
                             ".ply, topomap.json/.graphml (a `saver` node; docs/conventions.md)")
    parser.add_argument("--run-dir", help="where node configs, config snapshots and logs go (default runs/<id>)")
    add_rerun_arguments(parser, save="--rerun-save", save_help="every node writes DIR/<node>.rrd (one recording)")
    parser.add_argument("--set", action="append", metavar="PATH=VALUE",
                        help="override a graph field, e.g. nodes.camera.config.rate=5")
    parser.add_argument("--console", action="store_true", help="node output to this terminal instead of log files")
    parser.add_argument("--secure", metavar="DIR",
                        help="mutual TLS and access control between machines: the graph's secure_hub_zenoh_config "
                             "with the certificates in DIR (semloc certs; docs/security.md)")
    parser.add_argument("--dry-run", action="store_true",
                        help="write the node configs, print the commands, the start order and the security of "
                             "every endpoint")


def _demo_world(graph) -> dict:
    """The files of the demo's world for a graph that names them WORLD/... (deploy/demo.yaml): the cached demo world,
    generated first if there is none (as `semloc demo` does), as overrides the command line's own --set beat."""
    if "WORLD/" not in find_graph(graph).read_text():
        return {}
    from semloc_core.experiments.demo_world import ensure_world
    from services.demo_run import DemoSpec, world_overrides

    spec = DemoSpec()
    return world_overrides(spec, ensure_world(spec.world(), log=log.info))


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s launcher %(levelname)s: %(message)s", force=True)
    overrides: dict = from_sets(args.set)
    if args.robot:
        overrides["robot"] = args.robot
    if args.hub:
        overrides["hub"] = args.hub
    if args.camera:
        # Absolute: the node configs written to the run directory name the file wherever they are read from.
        source = str(Path(args.camera).resolve()) if Path(args.camera).exists() else args.camera
        overrides = deep_merge(overrides, {"nodes": {"camera": {"config": {"source": source,
                                                                           "source_type": "auto"}}}})
    if args.save:
        overrides = deep_merge(overrides, {"nodes": {"saver": {"worker": "saver",
                                                               "config": {"folder": str(Path(args.save).resolve())}}}})
    if rerun_overrides(args):
        overrides = deep_merge(overrides, {"rerun": rerun_overrides(args)})
    try:
        overrides = deep_merge(_demo_world(args.graph), overrides)
        graph = load_graph(args.graph, overrides)
        if args.secure:
            graph = load_graph(args.graph, deep_merge(overrides, secure_overrides(graph)))
        if args.save:
            graph = _saver_first(graph)
        launcher = Launcher(graph, run_dir=args.run_dir, console=args.console)
        if args.secure:
            use_secure_hub(launcher, args.secure)
        endpoints, access = _endpoint_security(launcher)
        # The operator's file: under --secure the hub runs a copy of the secure one, completed in the run folder.
        placeholders = placeholder_endpoints(endpoints, graph.secure_hub_zenoh_config if args.secure
                                             else graph.hub_zenoh_config)
    except ConfigError as error:
        print(f"semloc up: {error}", file=sys.stderr)
        return 2
    if args.dry_run:
        for name, node in launcher.nodes.items():
            after = f"  (starts after {', '.join(node.start_after)} run)" if node.start_after else ""
            print(f"{name}: {' '.join(node.command)}{after}")
        print(f"\nendpoints ({access}):")
        for row in endpoints:
            print(f"  {row.line()}")
        for warning in exposure_warnings(endpoints) + placeholders:
            print(f"warning: {warning}")
        return 0
    if placeholders:  # a link that can never come up: say so rather than wait
        for problem in placeholders:
            print(f"semloc up: {problem}", file=sys.stderr)
        return 2
    for warning in exposure_warnings(endpoints):
        log.warning("%s", warning)
    stop = threading.Event()

    def on_signal(signum, _frame):
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    rerun = launcher.graph.rerun
    if rerun.mode == "grpc" and not viewer_listens(rerun.url):
        # The nodes' streams would go nowhere, and the log would say "streaming to" the URL all the same.
        log.warning("rerun: no viewer listens at %s: start it first (`rerun`), or use --serve-web or --rerun-save",
                    rerun.url)
    print(f"run {launcher.run_id}: {len(launcher.nodes)} nodes, logs in {launcher.run_dir / 'logs'}", flush=True)
    launcher.start()
    if launcher.web_viewer_url:
        print(f"rerun web viewer: {launcher.web_viewer_url}", flush=True)
    if launcher.graph.hub_zenoh_config:
        for problem in link_problems(launcher.graph.hub_zenoh_config):
            log.warning("hub: %s", problem)
    try:
        while not stop.is_set() and not launcher.finished() and not _camera_config_errors(launcher):
            stop.wait(0.2)
    finally:
        launcher.stop()
    for name, why in _camera_config_errors(launcher).items():
        print(f"semloc up: node {name}: {why}", file=sys.stderr, flush=True)
        return 2
    failed = {name: s["last_exit"] for name, s in launcher.summary().items() if s["last_exit"] not in (0, None)}
    return 1 if failed and not stop.is_set() else 0



def _saver_first(graph):
    """The graph whose waiting nodes (start_after) wait for the saver too: it saves from the first frame on."""
    nodes = {name: spec.model_copy(update={"start_after": [*spec.start_after, "saver"]})
             if spec.start_after and name != "saver" else spec for name, spec in graph.nodes.items()}
    return graph.model_copy(update={"nodes": nodes})


def _camera_config_errors(launcher: Launcher) -> dict[str, str]:
    """Camera nodes stopped for good by a bad configuration or file (exit 2; e.g. frames the calibration does not
    fit): without its input the graph can do nothing, so `semloc up` stops and exits 2 with that line. Other nodes
    so stopped are left down while the rest runs on."""
    kinds = {name: spec.worker or name for name, spec in launcher.graph.nodes.items()}
    return {name: why for name, why in launcher.config_errors().items() if kinds.get(name) == "camera"}


def _endpoint_security(launcher: Launcher):
    from services.security import endpoint_security

    buses = {name: (yaml.safe_load((launcher.run_dir / f"{name}.yaml").read_text()) or {}).get("bus") or {}
             for name in launcher.nodes}
    return endpoint_security(launcher.graph, buses)
