"""What a graph exposes: `semloc up --dry-run` prints every endpoint's protection, and `--secure` keeps this host's
plain endpoints on loopback; every bus command takes the TLS identity."""

from __future__ import annotations

import argparse
import shutil

import pytest
import yaml

from services.bus import BusConfig, add_bus_arguments, bus_from_args, bus_from_env
from services.cli import build_parser, main
from services.config import ConfigError
from services.launcher import Launcher
from services.security import endpoint_parts, secure_hub_endpoint
from tests.security.helpers import SECURE, TWO, ROBOT


@pytest.mark.parametrize("endpoint, parts", [
    ("tls/base.lan:7448", ("tls", "base.lan", 7448)),
    ("tcp/[::1]:7447#iface=lo", ("tcp", "::1", 7447)),
    ("tcp/127.0.0.1:7447?prio=1", ("tcp", "127.0.0.1", 7447)),
    ("unixsock-stream//run/semloc/r1.sock", ("unixsock-stream", "/run/semloc/r1.sock", None)),
])
def test_endpoint_parts(endpoint, parts):
    assert endpoint_parts(endpoint) == parts


@pytest.mark.parametrize("hub, secure", [
    ("tcp/0.0.0.0:7447", "tcp/127.0.0.1:7447"),
    ("tcp/[::]:7447", "tcp/127.0.0.1:7447"),
    ("tcp/127.0.0.1:7000", "tcp/127.0.0.1:7000"),
    ("tcp/localhost:7000", "tcp/localhost:7000"),
    ("unixsock-stream//tmp/hub.sock", "unixsock-stream//tmp/hub.sock"),
    ("tcp/192.168.1.10:7447", None),
    ("tls/0.0.0.0:7447", None),
])
def test_secure_hub_stays_on_this_host(hub, secure):
    if secure is None:
        with pytest.raises(ConfigError, match="not a loopback or unixsock-stream endpoint"):
            secure_hub_endpoint(hub)
    else:
        assert secure_hub_endpoint(hub) == secure


def endpoint_rows(out: str) -> dict[tuple[str, str], str]:
    rows = {}
    for line in out.split("\nendpoints (", 1)[1].splitlines()[1:]:
        role, endpoint, protection = line[:31].strip(), line[31:66].strip(), line[66:].strip()
        rows[(role, endpoint)] = protection
    return rows


def test_dry_run_prints_every_endpoint(tmp_path, capsys, pki):
    assert main(["up", str(TWO / "base.yaml"), "--dry-run", "--run-dir", str(tmp_path / "plain")]) == 0
    out = capsys.readouterr().out
    assert "access control off" in out
    rows = endpoint_rows(out.split("\nwarning: ")[0])
    assert rows[("hub listens", "tcp/0.0.0.0:7447")].startswith("PLAIN on a network address")
    assert [line for line in out.splitlines() if line.startswith("warning: ")] == [
        "warning: hub listens tcp/0.0.0.0:7447: PLAIN on a network address: whoever reaches it may read and write "
        "every key (semloc up --secure DIR: docs/security.md)"]
    assert rows[("node localizer connects", "tcp/127.0.0.1:7447")] == "plain, loopback only (this host)"
    assert main(["up", str(TWO / "robot.yaml"), "--dry-run", "--secure", str(pki),
                 "--run-dir", str(tmp_path / "secure")]) == 0
    out = capsys.readouterr().out
    assert "access control on, default deny" in out
    rows = endpoint_rows(out)
    assert rows[("hub listens", "tcp/127.0.0.1:7447")] == "plain, loopback only (this host)"
    assert rows[("hub listens", "tls/0.0.0.0:7448")] == f"mutual TLS: clients need a certificate of {pki}/ca.pem"
    assert rows[("hub connects", "tls/BASE_HOST:7448#so_sndbuf=16384")] == f"mutual TLS as {pki}/{ROBOT}-router.pem"
    assert not any(p.startswith("PLAIN") for p in rows.values())
    assert [line for line in out.splitlines() if line.startswith("warning: ")] == [
        f"warning: hub connects tls/BASE_HOST:7448#so_sndbuf=16384: put the base station's address for BASE_HOST in "
        f"{SECURE / 'robot-router.json5'} (in a copy of the graph's folder: docs/deploy.md, \"Several machines\")"]
    assert main(["up", str(TWO / "robot.yaml"), "--dry-run", "--secure", str(tmp_path / "none"),
                 "--run-dir", str(tmp_path / "x")]) == 2
    assert "semloc certs" in capsys.readouterr().err


def test_up_refuses_a_router_still_dialling_the_placeholder_host(tmp_path, capsys, monkeypatch):
    """The shipped robot router dials BASE_HOST until the operator sets it; zenoh would retry that link silently
    forever, so `semloc up` stops at once naming the file. Set (a copy of the folder), the graph launches."""
    launched = []
    monkeypatch.setattr(Launcher, "start", lambda self: launched.append(self) or self)
    monkeypatch.setattr(Launcher, "finished", lambda self: True)
    assert main(["up", str(TWO / "robot.yaml"), "--run-dir", str(tmp_path / "unset")]) == 2
    err = capsys.readouterr().err
    assert (f"tcp/BASE_HOST:7447#so_sndbuf=16384: put the base station's address for BASE_HOST in "
            f"{TWO / 'robot-router.json5'}") in err
    assert not launched
    copy = tmp_path / "deploy"
    shutil.copytree(TWO.parent, copy)
    router = copy / "two-machines" / "robot-router.json5"
    router.write_text(router.read_text().replace("BASE_HOST", "192.168.1.10"))
    assert main(["up", str(copy / "two-machines" / "robot.yaml"), "--run-dir", str(tmp_path / "set")]) == 0
    assert len(launched) == 1 and "BASE_HOST" not in capsys.readouterr().err


@pytest.mark.parametrize("command", ["status", "record", "replay"])
def test_bus_commands_take_a_tls_identity(command, tmp_path):
    required = {"status": [], "record": ["-o", "x.mcap"], "replay": ["x.mcap"]}[command]
    args = build_parser().parse_args([command, *required, "--connect", "tls/base.lan:7448", "--tls",
                                      str(tmp_path / "operator")])
    bus = bus_from_args(args)
    assert (bus.tls.ca, bus.tls.certificate, bus.tls.private_key) == (
        str(tmp_path / "ca.pem"), str(tmp_path / "operator.pem"), str(tmp_path / "operator-key.pem"))


def test_worker_and_environment_take_a_tls_identity(tmp_path, monkeypatch, capsys):
    assert main(["worker", "sink", "--tls", "pki/r1-workers", "--print-config"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["bus"]["tls"]["certificate"] == "pki/r1-workers.pem"
    monkeypatch.setenv("SEMLOC_TLS", "pki/base-station")
    assert bus_from_env().tls.private_key == "pki/base-station-key.pem"
    assert BusConfig.model_validate({"tls": {"ca": "ca.pem"}}).tls.certificate is None
    with pytest.raises(ValueError, match="give both or neither"):
        BusConfig.model_validate({"tls": {"ca": "ca.pem", "certificate": "x.pem"}})
    parser = argparse.ArgumentParser()
    add_bus_arguments(parser)
    assert "--tls" in parser.format_help()
