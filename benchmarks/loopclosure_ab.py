"""Per-frame loop-closure engine CPU of this checkout against another one's (a reference commit) on the same cached
features, and whether their results are bit-identical.

The engine of another commit cannot share this process (one ``semloc_core`` per interpreter), so each run is a
fresh interpreter with that tree first on its path; runs alternate between the trees (--rounds), so both see the
same machine load, and per frame the median over runs is taken. Each run first warms up on --warm frames (numba's
cached kernels loaded, not timed). Features: ``route`` seed --seed as ``benchmarks/loopclosure.py`` caches them
(same --cache; run that once first), vocabulary learnt offline on seed 2, ``EngineParams()`` of each tree.

    git archive <commit> | tar -x -C /tmp/ref           # e.g. 39138f8, the engine before issue 33
    .venv/bin/python benchmarks/loopclosure_ab.py /tmp/ref [--rounds 6] [--frames 1000] [--cache DIR] [--digest]

Prints CPU p50 / p95 over frames 100-200, the last 100 and every 200 frames, the whole run's CPU, the ratio of this
checkout to the reference, and the load average. ``--digest`` also hashes every frame's result (candidates, scores,
loops, beliefs, revisions, map update, decision) and the final lattice, map and state, and says where they differ:
a change that should not change any result is tested with the reference set to the commit before it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]


def run_tree(tree: str, cache: Path, seed: int, frames: int, warm: int, digest: bool, out: str) -> None:
    """One timed run of ``tree``'s engine (this function runs in a fresh interpreter with ``tree`` on its path)."""
    import hashlib
    import time

    import semloc_core
    from semloc_core.io.loopclosure import load_features, load_vocabulary
    from semloc_core.loopclosure import EngineParams, LoopClosureEngine

    if not Path(semloc_core.__file__).resolve().is_relative_to(Path(tree).resolve()):
        raise SystemExit(f"{tree}: its semloc_core was not the one imported ({semloc_core.__file__})")

    sequences = [p for p in sorted(cache.glob(f"route_s{seed}_n*_f500.npz"))
                 if int(p.name.split("_n")[1].split("_")[0]) >= frames]
    if not sequences:
        raise SystemExit(f"no cached route seed {seed} with {frames} frames in {cache}: run benchmarks/loopclosure.py")
    features = load_features(sequences[0])[0][:frames]
    vocabulary = load_vocabulary(next(cache.glob("vocabulary_route_s2_*.npz")))

    def update(h, *parts):
        for part in parts:
            h.update(np.ascontiguousarray(part).tobytes() if isinstance(part, np.ndarray) else repr(part).encode())

    for part in (features[:warm], features):
        engine = LoopClosureEngine(EngineParams(), vocabulary)
        cpu, hashes = np.zeros(len(part)), []
        for k, f in enumerate(part):
            c = time.process_time()
            r = engine.add_frame(f)
            cpu[k] = time.process_time() - c
            if digest:
                h = hashlib.sha256()
                update(h, r.frame, str(r.status), r.candidates, r.retrieval_scores, r.similarity, r.loops,
                       r.loop_beliefs, r.node, repr(getattr(r, "decision", None)), repr(r.map_update))
                for j in sorted(r.revised):
                    update(h, j, r.revised[j])
                hashes.append(h.hexdigest())
    final = {}
    if digest:
        arrays, _ = engine.state()
        for name, values in (("lattice", engine.mrf.cells()), ("map", engine.topomap.state().values()),
                             ("state", [arrays[k] for k in sorted(arrays)])):
            h = hashlib.sha256()
            update(h, *(np.asarray(v) for v in values))
            final[name] = h.hexdigest()
    Path(out).write_text(json.dumps({"cpu_ms": (cpu * 1e3).tolist(), "frames": hashes, "final": final,
                                     "load": open("/proc/loadavg").read().split()[:3]}))


def windows(cpu: np.ndarray) -> dict[str, tuple[float, float]]:
    n = cpu.size
    ends = sorted({min(200, n), *range(200, n + 1, 200), n})
    return {f"{max(0, e - 100)}-{e}": (float(np.percentile(cpu[max(0, e - 100):e], 50)),
                                       float(np.percentile(cpu[max(0, e - 100):e], 95))) for e in ends}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reference", help="the other checkout's root (holding its semloc_core)")
    parser.add_argument("--rounds", type=int, default=6, help="runs of each tree, alternating")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--warm", type=int, default=100, help="frames of an untimed run first")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", default=".semloc-cache/loopclosure")
    parser.add_argument("--digest", action="store_true", help="also compare every frame's result")
    parser.add_argument("--run", nargs=2, metavar=("TREE", "OUT"), help=argparse.SUPPRESS)  # one run, internal
    args = parser.parse_args()
    if args.run:
        sys.path.insert(0, args.run[0])
        run_tree(args.run[0], Path(args.cache).resolve(), args.seed, args.frames, args.warm, args.digest, args.run[1])
        return 0
    trees = {"this checkout": str(HERE), "reference": str(Path(args.reference).resolve())}
    cache = str(Path(args.cache).resolve())
    results: dict[str, list[dict]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory() as scratch:
        for r in range(args.rounds):
            for name, tree in trees.items():
                out = f"{scratch}/{r}-{len(results[name])}-{name[0]}.json"
                command = [sys.executable, str(Path(__file__).resolve()), tree, "--run", tree, out, "--frames",
                           str(args.frames), "--warm", str(args.warm), "--seed", str(args.seed), "--cache", cache]
                subprocess.run(command + (["--digest"] if args.digest else []), check=True, cwd=tree)
                results[name].append(json.loads(Path(out).read_text()))
    medians = {}
    for name, runs in results.items():
        cpu = np.median(np.array([run["cpu_ms"] for run in runs]), axis=0)
        medians[name] = cpu
        totals = [float(np.sum(run["cpu_ms"])) / 1e3 for run in runs]
        print(f"{name} ({trees[name]}): whole run {np.median(totals):.2f} s CPU (median of {len(runs)}); per-frame CPU "
              "p50 / p95 ms: " + ", ".join(f"{w} {a:.2f} / {b:.2f}" for w, (a, b) in windows(cpu).items()))
        print(f"    load average at each run's end: {', '.join('/'.join(run['load']) for run in runs)}")
    mine, ref = (windows(medians[name]) for name in trees)
    print("this checkout / reference: " + ", ".join(f"{w} p50 {mine[w][0] / ref[w][0]:.2f} p95 "
                                                     f"{mine[w][1] / ref[w][1]:.2f}" for w in mine))
    if args.digest:
        a, b = (results[name][-1] for name in trees)
        differ = [k for k, (x, y) in enumerate(zip(a["frames"], b["frames"])) if x != y]
        print(f"results: {len(a['frames']) - len(differ)} of {len(a['frames'])} frames identical"
              + (f" (first difference at frame {differ[0]})" if differ else "") + "; final "
              + ", ".join(f"{k} {'identical' if a['final'][k] == b['final'][k] else 'DIFFERENT'}" for k in a["final"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
