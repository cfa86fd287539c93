"""A worker's setup in a fresh interpreter (this one's numba kernels may have run in earlier tests): which kernels
setup loads, and whether a real input afterwards needs any it did not. For the workers that compile their kernels
in setup, so that a fresh install's first frames are not stalled."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

SCRIPT = """\
import importlib, json, sys
import numba
from services.bus import BusConfig, open_session
modules = [importlib.import_module(name) for name in {modules!r}]
def loaded():
    return {{f'{{m.__name__}}.{{k}}': len(v.signatures) for m in modules for k, v in vars(m).items()
             if isinstance(v, numba.core.registry.CPUDispatcher)}}
worker_class = importlib.import_module('services.workers.{worker}').WORKER
before = loaded()
with open_session(BusConfig(listen=['tcp/127.0.0.1:0'])) as session:
    worker = worker_class(worker_class.Config.model_validate_json(sys.argv[1]))
    worker.session = session
    worker.setup()
    after_setup = loaded()
    args, result = sys.argv[2:], None
{run}
print(json.dumps([before, after_setup, loaded(), result]))
"""


def check_setup_compiles(worker: str, config, modules: list[str], run: str, *args: str, expected: tuple[str, ...]):
    """Set up ``services.workers.<worker>`` of ``config`` in a fresh interpreter, then run ``run`` (statements using
    ``worker`` and ``args``; ``result`` is returned). Asserts that no kernel of ``modules`` was loaded before setup,
    that those named in ``expected`` (``module.kernel``) were after it, and that ``run`` needed none that setup did
    not load."""
    script = SCRIPT.format(modules=modules, worker=worker, run=textwrap.indent(textwrap.dedent(run), "    "))
    done = subprocess.run([sys.executable, "-c", script, config.model_dump_json(), *args], capture_output=True,
                          text=True, timeout=300, cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr[-2000:]
    before, after_setup, after_run, result = json.loads(done.stdout.strip().splitlines()[-1])
    assert not any(before.values()), before
    assert all(after_setup[name] for name in expected), after_setup
    new = {name: after_run[name] - after_setup[name] for name in after_run if after_run[name] > after_setup[name]}
    assert not new, f"kernels the worker's setup did not compile: {new}"
    return result
