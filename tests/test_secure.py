"""The secure profile with real zenoh sessions on loopback: mutual TLS refusals and access-control denials.

The base station is a router session opened from the JSON5 file that ``generate_fleet`` rendered (only the
listen port differs from a field deployment); robots open their own rendered configs.
"""

from __future__ import annotations

import json
import socket
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("cryptography")

from waiting import wait_until  # noqa: E402

from services import certs  # noqa: E402
from services.certs import CertificateError, FleetSecrets, certificate_common_name, generate_fleet  # noqa: E402

FLEET = "f1"
ROOT = f"lrs/{FLEET}"
WAIT_S = 10.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Inbox:
    """Thread-safe record of (key, payload) the base station's subscriber received."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: Any) -> None:
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def has(self, payload: bytes) -> bool:
        with self._lock:
            return any(p == payload for _, p in self.items)

    def keys_of(self, payload: bytes) -> list[str]:
        with self._lock:
            return [k for k, p in self.items if p == payload]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> FleetSecrets:
    port = _free_port()
    out = tmp_path_factory.mktemp("secure")
    return generate_fleet(out, FLEET, ["rov1", "rov2"], listen=[f"tls/127.0.0.1:{port}"])


@pytest.fixture(scope="module")
def base(fleet: FleetSecrets) -> Iterator[tuple[Any, Inbox]]:
    """The base station: router opened from the rendered base.json5, subscribed to every robot's keys."""
    inbox = Inbox()
    with zenoh.open(zenoh.Config.from_file(str(fleet.configs["base"]))) as session:
        sub = session.declare_subscriber(f"{ROOT}/**", inbox)
        qs = [
            session.declare_queryable(f"{ROOT}/base/status", lambda q: q.reply(q.key_expr, b"real-status")),
            session.declare_queryable(
                f"{ROOT}/base/calib/*", lambda q: q.reply(q.key_expr, b"real-calib:" + str(q.key_expr).encode())
            ),
        ]
        yield session, inbox
        for q in qs:
            q.undeclare()
        sub.undeclare()


def _open_robot(fleet: FleetSecrets, name: str) -> Any:
    return zenoh.open(zenoh.Config.from_file(str(fleet.configs[name])))


def _connected_publisher(session: Any, key: str) -> Any:
    """A BLOCK publisher on ``key``, once the base station's subscriber matches it (i.e. the link is up)."""
    pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    assert wait_until(lambda: pub.matching_status.matching, WAIT_S), f"{key}: the base station never matched"
    return pub


def _tls_only_config(port: int, extra_tls: dict[str, Any], mode: str = "client") -> Any:
    conf = {
        "mode": mode,
        "connect": {"endpoints": [f"tls/127.0.0.1:{port}"], "timeout_ms": 0 if mode == "client" else -1},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": extra_tls}},
    }
    return zenoh.Config.from_json5(json.dumps(conf))


def _port(fleet: FleetSecrets) -> int:
    text = fleet.configs["base"].read_text()
    data = json.loads(text[text.index("{") :])
    return int(data["listen"]["endpoints"][0].rsplit(":", 1)[1])


# ---------------------------------------------------------------------------------------------------------
# Generated material
# ---------------------------------------------------------------------------------------------------------


def test_generated_certificates_and_configs(fleet: FleetSecrets) -> None:
    assert certificate_common_name(fleet.base.cert) == "base"
    assert certificate_common_name(fleet.robots["rov1"].cert) == "rov1"
    assert certificate_common_name(fleet.robots["rov2"].cert) == "rov2"
    assert fleet.operator is not None
    assert certificate_common_name(fleet.operator.cert) == "operator"
    for ident in [fleet.base, *fleet.robots.values(), fleet.operator]:
        assert stat.S_IMODE(ident.key.stat().st_mode) == 0o600, ident.key
        assert ident.ca.read_bytes() == fleet.ca_cert.read_bytes()
    assert stat.S_IMODE(fleet.ca_key.stat().st_mode) == 0o600
    for name, path in fleet.configs.items():
        zenoh.Config.from_file(str(path))  # zenoh itself accepts every rendered file
        text = path.read_text()
        data = json.loads(text[text.index("{") :])
        tls = data["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True, name
        assert Path(tls["root_ca_certificate"]).is_file()
        assert data["transport"]["link"]["protocols"] == ["tls"]
    base = json.loads(fleet.configs["base"].read_text().split("\n", 2)[2])
    assert base["mode"] == "router"
    assert base["access_control"]["default_permission"] == "deny"
    rov1 = json.loads(fleet.configs["rov1"].read_text().split("\n", 2)[2])
    assert rov1["transport"]["link"]["tls"]["connect_certificate"] == str(fleet.robots["rov1"].cert)


def test_reuse_ca_and_config_dir(tmp_path: Path) -> None:
    first = generate_fleet(tmp_path, "reef", ["a1"], hosts=["10.1.2.3", "shore.local"], config_dir="/etc/lrs")
    text = first.configs["a1"].read_text()
    assert '"/etc/lrs/a1/a1.pem"' in text
    assert '"tls/10.1.2.3:7447"' in text
    ca_pem = first.ca_cert.read_bytes()
    second = generate_fleet(tmp_path, "reef", ["a1", "a2"], hosts=["10.1.2.3"])
    assert second.ca_cert.read_bytes() == ca_pem  # a new robot joins the same CA
    third = generate_fleet(tmp_path, "reef", ["a1"], reuse_ca=False)
    assert third.ca_cert.read_bytes() != ca_pem


@pytest.mark.parametrize(
    ("robots", "hosts"),
    [
        (["base"], []),
        (["map"], []),
        (["a/b"], []),
        (["r*"], []),
        (["x", "x"], []),
        (["operator"], []),
        (["ok"], ["bad host"]),
        (["ok"], ["a/b"]),
    ],
)
def test_bad_names_are_refused(tmp_path: Path, robots: list[str], hosts: list[str]) -> None:
    from services.errors import ServiceError

    with pytest.raises(ServiceError):
        generate_fleet(tmp_path, "reef", robots, hosts=hosts)


def test_plain_tcp_endpoint_is_refused() -> None:
    from services.keys import FleetKeys

    with pytest.raises(CertificateError, match="tls/"):
        certs.router_config(FleetKeys("f"), ["r"], ca="c", cert="c", key="k", listen=["tcp/0.0.0.0:7447"])
    with pytest.raises(CertificateError, match="tls/"):
        certs.client_config(ca="c", cert="c", key="k", connect=["tcp/1.2.3.4:7447"])


def test_cli_certs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lrsensor.cli import main

    code = main(["certs", "--out", str(tmp_path), "--fleet", "reef", "--robots", "rov1,rov2", "--hosts", "10.0.0.5"])
    assert code == 0
    out = capsys.readouterr().out
    assert "| rov2 |" in out
    for rel in ["ca/ca.pem", "base/base.json5", "rov1/rov1-key.pem", "rov2/rov2.json5", "operator/operator.pem"]:
        assert (tmp_path / rel).is_file(), rel
    assert main(["certs", "--out", str(tmp_path), "--fleet", "reef", "--robots", "base"]) == 2


# ---------------------------------------------------------------------------------------------------------
# Mutual TLS
# ---------------------------------------------------------------------------------------------------------


def test_session_without_certificate_cannot_connect(fleet: FleetSecrets, base: tuple[Any, Inbox]) -> None:
    port = _port(fleet)
    # A client that trusts the CA but shows no certificate: the TLS handshake is refused, open fails.
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(_tls_only_config(port, {"root_ca_certificate": str(fleet.ca_cert)}))
    # Plain TCP to the TLS port: refused too.
    plain = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": 0},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(zenoh.Config.from_json5(json.dumps(plain)))


def test_certificate_from_another_ca_cannot_connect(
    fleet: FleetSecrets, base: tuple[Any, Inbox], tmp_path: Path
) -> None:
    rogue = generate_fleet(tmp_path, FLEET, ["rov1"])  # same names, different CA
    tls = {
        "root_ca_certificate": str(fleet.ca_cert),  # even trusting the real CA for the server side
        "connect_certificate": str(rogue.robots["rov1"].cert),
        "connect_private_key": str(rogue.robots["rov1"].key),
        "enable_mtls": True,
    }
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(_tls_only_config(_port(fleet), tls))


def test_peer_without_certificate_opens_but_nothing_flows(fleet: FleetSecrets, base: tuple[Any, Inbox]) -> None:
    _, inbox = base
    conf = _tls_only_config(_port(fleet), {"root_ca_certificate": str(fleet.ca_cert)}, mode="peer")
    with zenoh.open(conf) as intruder, _open_robot(fleet, "rov2") as rov2:
        pub = intruder.declare_publisher(f"{ROOT}/rov2/cloud")
        legit = _connected_publisher(rov2, f"{ROOT}/rov2/cloud")
        for _ in range(5):
            pub.put(b"intruder")
            time.sleep(0.05)
        legit.put(b"rov2-after-intruder")
        assert wait_until(lambda: inbox.has(b"rov2-after-intruder"), WAIT_S)
        assert not pub.matching_status.matching
        assert not inbox.has(b"intruder")


# ---------------------------------------------------------------------------------------------------------
# Access control
# ---------------------------------------------------------------------------------------------------------


def test_robot_may_publish_only_under_its_own_prefix(fleet: FleetSecrets, base: tuple[Any, Inbox]) -> None:
    _, inbox = base
    with _open_robot(fleet, "rov1") as rov1:
        own = _connected_publisher(rov1, f"{ROOT}/rov1/cloud")
        # Forbidden keys first, then a legit sample: same link, in order, so once the legit one arrived
        # the forbidden ones would have arrived too had the router let them in.
        for key in [f"{ROOT}/rov2/cloud", f"{ROOT}/base/status", f"{ROOT}/map/updates", "lrs/other/rov1/cloud"]:
            rov1.put(key, b"spoof")
            rov1.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK).put(b"spoof")
        own.put(b"rov1-own")
        assert wait_until(lambda: inbox.has(b"rov1-own"), WAIT_S)
        assert inbox.keys_of(b"rov1-own") == [f"{ROOT}/rov1/cloud"]
        time.sleep(0.2)
        assert not inbox.has(b"spoof"), inbox.keys_of(b"spoof")


def test_robot_cannot_answer_the_fleet_queryables(fleet: FleetSecrets, base: tuple[Any, Inbox]) -> None:
    assert fleet.operator is not None
    with _open_robot(fleet, "rov1") as rov1, zenoh.open(zenoh.Config.from_file(str(fleet.configs["operator"]))) as op:
        hijacks = [
            rov1.declare_queryable(key, lambda q: q.reply(q.key_expr, b"fake"))
            for key in [f"{ROOT}/base/status", f"{ROOT}/map", f"{ROOT}/base/**", f"{ROOT}/**"]
        ]
        # Declared after the hijacks on the same link: once it answers, the hijacks were seen by the router.
        own = rov1.declare_queryable(f"{ROOT}/rov1/calib", lambda q: q.reply(q.key_expr, b"rov1-calib"))

        def answers(key: str) -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in op.get(key, timeout=2.0) if r.ok is not None]

        assert wait_until(lambda: answers(f"{ROOT}/rov1/calib") == [b"rov1-calib"], WAIT_S)
        assert answers(f"{ROOT}/base/status") == [b"real-status"]
        assert answers(f"{ROOT}/map") == []  # nobody legit serves it here, and the robot may not
        # The robot itself may ask the fleet side and gets the real answer.
        got = [r.ok.payload.to_bytes() for r in rov1.get(f"{ROOT}/base/calib/rov1", timeout=2.0) if r.ok]
        assert got == [f"real-calib:{ROOT}/base/calib/rov1".encode()]
        for q in [*hijacks, own]:
            q.undeclare()


def test_unknown_certificate_name_is_denied(fleet: FleetSecrets, base: tuple[Any, Inbox], tmp_path: Path) -> None:
    """A certificate of the fleet's CA whose name is in no policy gets nothing through (default deny)."""
    _, inbox = base
    ca_key, ca_cert, ca_pem = certs._load_ca(fleet.ca_cert.parent)
    cert_pem, key_pem = certs._issue("rov9", ca_key=ca_key, ca_cert=ca_cert, days=1, server=False)
    ident = certs._identity(tmp_path, "rov9", cert_pem, key_pem, ca_pem)
    conf = certs.client_config(
        ca=str(ident.ca), cert=str(ident.cert), key=str(ident.key), connect=[f"tls/127.0.0.1:{_port(fleet)}"]
    )
    with zenoh.open(zenoh.Config.from_json5(json.dumps(conf))) as rov9, _open_robot(fleet, "rov2") as rov2:
        pub = rov9.declare_publisher(f"{ROOT}/rov9/cloud")
        legit = _connected_publisher(rov2, f"{ROOT}/rov2/cloud")
        time.sleep(0.5)  # rov9's TLS link is up by now (same CA): only the ACL stands in the way
        pub.put(b"rov9")
        rov9.put(f"{ROOT}/rov9/cloud", b"rov9")
        time.sleep(0.1)
        legit.put(b"rov2-after-rov9")
        assert wait_until(lambda: inbox.has(b"rov2-after-rov9"), WAIT_S)
        time.sleep(0.2)
        assert not inbox.has(b"rov9")
        assert [r for r in rov9.get(f"{ROOT}/base/status", timeout=1.0) if r.ok] == []


def test_shipped_templates_are_what_the_generator_renders() -> None:
    deploy = Path(__file__).resolve().parents[1] / "deploy" / "secure"
    for name, text in certs.example_configs().items():
        assert (deploy / name).read_text() == text, f"deploy/secure/{name} is stale: re-render it"
        zenoh.Config.from_json5(text)
