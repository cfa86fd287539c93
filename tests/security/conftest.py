"""Security-test fixtures: certificates made at test time by services/certs.py (session-scoped: one CA for every
module; nothing committed that could expire). Routers and workers are module-scoped in the modules that need them.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest

from services.certs import load_ca, make_ca, write_identity, write_layout
from tests.security.helpers import ROBOT


@pytest.fixture(scope="session")
def pki(tmp_path_factory) -> Path:
    """``semloc certs DIR --robot r1``'s layout, plus ``stranger`` (this CA, a name no rule knows),
    ``expired/operator`` (this CA, validity over) and ``foreign/operator`` (a valid certificate of another CA)."""
    directory = tmp_path_factory.mktemp("pki")
    write_layout(directory, ROBOT)
    ca_key, ca_certificate = load_ca(directory)
    write_identity(directory, "stranger", ca_key, ca_certificate)
    long_ago = datetime.now(timezone.utc) - timedelta(days=30)
    write_identity(directory / "expired", "operator", ca_key, ca_certificate, days=1, start=long_ago)
    (directory / "expired" / "ca.pem").write_bytes((directory / "ca.pem").read_bytes())
    foreign_key, foreign_certificate = make_ca("another CA")
    write_identity(directory / "foreign", "operator", foreign_key, foreign_certificate)
    write_identity(directory / "foreign", "base-router", foreign_key, foreign_certificate,
                   server_hosts=("localhost", "127.0.0.1"))
    (directory / "foreign" / "ca.pem").write_bytes((directory / "ca.pem").read_bytes())  # trusts the real CA
    return directory

