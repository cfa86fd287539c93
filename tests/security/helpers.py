"""Helpers of the security tests (and of the secure two-machine run): the secure router configs of deploy/secure/
on loopback ports, secure launchers as `semloc up --secure` builds them, clients with an identity."""

from __future__ import annotations

from pathlib import Path

from services.bus import BusConfig, TlsFiles, open_session
from services.config import deep_merge
from services.launcher import Launcher, load_graph
from services.security import secure_overrides, use_secure_hub
from tests.service.conftest import REPO_ROOT

SECURE = REPO_ROOT / "deploy" / "secure"
TWO = REPO_ROOT / "deploy" / "two-machines"
ROBOT = "r1"


def identity(pki: Path, name: str) -> TlsFiles:
    return TlsFiles.model_validate(str(pki / name))


def client(endpoint: str, tls: TlsFiles | None = None):
    """A zenoh client session of ``endpoint`` with the TLS credentials ``tls``."""
    return open_session(BusConfig(mode="client", connect=[endpoint], tls=tls))


def secure_configs(directory: Path, base_tls_port: int, robot_tls_port: int) -> Path:
    """deploy/secure/ copied to ``directory`` with its TLS endpoints on this test's loopback ports (what an operator
    does by setting BASE_HOST); nothing else changes."""
    directory.mkdir(parents=True, exist_ok=True)
    for path in SECURE.glob("*.json5"):
        text = path.read_text()
        port = base_tls_port if path.name.startswith("base") else robot_tls_port
        text = text.replace("tls/0.0.0.0:7448", f"tls/127.0.0.1:{port}")
        text = text.replace("tls/BASE_HOST:7448", f"tls/localhost:{base_tls_port}")
        (directory / path.name).write_text(text)
    return directory


def secure_launcher(graph_file: Path, overrides: dict, pki: Path, secure_config: Path, run_dir: Path) -> Launcher:
    """What `semloc up GRAPH --secure PKI` builds (services/commands/up.py), with the secure config given."""
    overrides = deep_merge(overrides, {"secure_hub_zenoh_config": str(secure_config)})
    graph = load_graph(graph_file, deep_merge(overrides, secure_overrides(load_graph(graph_file, overrides))))
    launcher = Launcher(graph, run_dir=run_dir)
    use_secure_hub(launcher, pki)
    return launcher
