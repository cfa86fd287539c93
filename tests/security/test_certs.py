"""`semloc certs`: the development CA and the certificates of deploy/secure/, as rustls and the access rules need
them (common name = identity, key usages, the names routers are dialled by), made fresh at every test run."""

from __future__ import annotations

import datetime as dt
import ipaddress
import stat

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from services.certs import certificate_path, common_name, key_path, load_ca, write_layout
from services.cli import main

IDENTITIES = ["base-router", "r1-router", "r1-workers", "base-station", "operator"]


def load(directory, name) -> x509.Certificate:
    return x509.load_pem_x509_certificate(certificate_path(directory, name).read_bytes())


def names(certificate) -> set[str]:
    try:
        alternative = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return set()
    return {str(n.value) for n in alternative}


def test_layout_certificates(tmp_path):
    written = write_layout(tmp_path, "r1", base_hosts=["base.lan", "10.0.0.5"], robot_hosts=["r1.lan"], days=30)
    assert {w.path.name for w in written} == {"ca.pem", "ca-key.pem", *(f"{n}.pem" for n in IDENTITIES)}
    _, ca = load_ca(tmp_path)
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name in IDENTITIES:
        certificate = load(tmp_path, name)
        assert common_name(certificate_path(tmp_path, name)) == name
        assert certificate.issuer == ca.subject
        certificate.verify_directly_issued_by(ca)
        assert not certificate.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usages = set(certificate.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
        router = name.endswith("-router")
        assert ExtendedKeyUsageOID.CLIENT_AUTH in usages
        assert (ExtendedKeyUsageOID.SERVER_AUTH in usages) == router
        lifetime = certificate.not_valid_after_utc - certificate.not_valid_before_utc
        assert dt.timedelta(days=30) <= lifetime <= dt.timedelta(days=30, minutes=10)
        assert stat.S_IMODE(key_path(tmp_path, name).stat().st_mode) == 0o600
    assert names(load(tmp_path, "base-router")) == {"base.lan", "10.0.0.5", "localhost", "127.0.0.1", "::1"}
    assert names(load(tmp_path, "r1-router")) == {"r1.lan", "localhost", "127.0.0.1", "::1"}
    assert names(load(tmp_path, "operator")) == set()
    alternative = load(tmp_path, "base-router").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ipaddress.ip_address("10.0.0.5") in alternative.get_values_for_type(x509.IPAddress)
    assert stat.S_IMODE(key_path(tmp_path, "ca").stat().st_mode) == 0o600


def test_rerun_keeps_the_ca_adds_a_robot_and_renews_one_identity(tmp_path):
    write_layout(tmp_path, "r1")
    ca_before = certificate_path(tmp_path, "ca").read_bytes()
    operator_before, station_before = load(tmp_path, "operator"), load(tmp_path, "base-station")
    written = {w.path.name: w.action for w in write_layout(tmp_path, "r2", renew=("operator",))}
    assert written["ca.pem"] == "kept" and written["operator.pem"] == "renewed"
    assert written["r2-router.pem"] == written["r2-workers.pem"] == "created"
    assert certificate_path(tmp_path, "ca").read_bytes() == ca_before
    _, ca = load_ca(tmp_path)
    operator = load(tmp_path, "operator")
    operator.verify_directly_issued_by(ca)
    assert operator.public_key() != operator_before.public_key()  # a new key, the same identity
    assert operator.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "operator"
    assert load(tmp_path, "base-station") == station_before
    with pytest.raises(ValueError, match="cannot renew nobody"):
        write_layout(tmp_path, "r2", renew=("nobody",))


def test_certs_command_prints_where_each_file_goes(tmp_path, capsys):
    assert main(["certs", str(tmp_path / "pki"), "--robot", "r1", "--base-host", "base.lan"]) == 0
    out = capsys.readouterr().out
    assert "not for production" in out
    for name in ["ca.pem", "ca-key.pem", *(f"{n}.pem" for n in IDENTITIES)]:
        line = next(line for line in out.splitlines() if f"/{name} " in line)
        assert line.split()[0] == "created" and len(line.split()) > 3  # what it is and where it goes
    assert main(["certs", str(tmp_path / "pki"), "--robot", "bad/name"]) == 2
    assert capsys.readouterr().err.startswith("semloc certs: ")
