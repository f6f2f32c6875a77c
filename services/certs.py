"""The secure profile: a fleet's certificate authority, TLS certificates and Zenoh configurations.

One call, :func:`generate_fleet`, writes everything a fleet needs for mutual TLS and access control::

    OUT/ca/ca.pem, ca-key.pem                 the fleet's certificate authority (keep ca-key.pem offline)
    OUT/base/ca.pem, base.pem, base-key.pem   the base station (CN ``base``; SAN 127.0.0.1, localhost, --hosts)
    OUT/base/base.json5                       router config: TLS listener, mTLS, access control
    OUT/<robot>/ca.pem, <robot>.pem, <robot>-key.pem, <robot>.json5
                                              one ROV: client certificate with CN = robot name
    OUT/operator/...                          optional read-only shore tools (CN ``operator``)

Each deployment folder is self-contained: copy it to the machine that runs it (``--config-dir`` tells where it
will live there, so the JSON5 points at the right files).

Access-control policy (rendered by :func:`router_config`; default permission ``deny``):

- the base station (CN ``base``) may do anything under ``<prefix>/<fleet>/**``;
- a robot (CN = robot name) owns ``<prefix>/<fleet>/<robot>/**`` (publish, answer queries, liveliness),
  may ask and subscribe under ``<prefix>/<fleet>/base/**`` and ``<prefix>/<fleet>/map/**`` and receives the
  answers, and nothing else: it cannot publish under another robot's key nor answer the fleet's queryables;
- an operator (CN ``operator``) may query and subscribe anywhere in the fleet, and publish nothing.

Keys are ECDSA P-256 (PKCS#8 PEM), certificates X.509 v3 signed with SHA-256. Private keys are written with
mode 0600. Certificate generation needs the ``cryptography`` package (the ``base`` extra); it is imported
lazily, with a clear message when missing.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lrsensor.atomic import atomic_write

from .errors import ServiceError
from .keys import FleetKeys, check_robot_name

#: Common name of the base station's certificate (the ACL subject that may do everything in the fleet).
BASE_CN = "base"
#: Common name of the read-only shore tools' certificate.
OPERATOR_CN = "operator"
#: Default TLS endpoint the base station listens on.
DEFAULT_BASE_LISTEN = "tls/0.0.0.0:7447"
#: Every message type zenoh 1.x access control knows.
ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)


class CertificateError(ServiceError):
    """Certificates could not be generated or written (bad name, bad host, missing ``cryptography``)."""


@dataclass(frozen=True)
class Identity:
    """One certificate and its private key on disk.

    Attributes:
        name: the certificate's common name (``base``, ``operator`` or a robot name).
        cert: path of the PEM certificate.
        key: path of the PEM (PKCS#8) private key, mode 0600.
        ca: path of the fleet CA certificate copied next to it.
    """

    name: str
    cert: Path
    key: Path
    ca: Path


@dataclass(frozen=True)
class FleetSecrets:
    """What :func:`generate_fleet` wrote.

    Attributes:
        out_dir: the output folder.
        ca_cert: the CA certificate; ca_key: its private key (keep it offline).
        base: the base station's identity; robots: one identity per robot; operator: optional shore tools.
        configs: deployment name (``base``, robot names, ``operator``) -> rendered JSON5 config path.
    """

    out_dir: Path
    ca_cert: Path
    ca_key: Path
    base: Identity
    robots: Mapping[str, Identity]
    operator: Identity | None
    configs: Mapping[str, Path]


def _crypto() -> Any:
    try:
        import cryptography
    except ImportError as err:  # pragma: no cover - depends on the install
        msg = (
            "generating certificates needs the 'cryptography' package: pip install 'lrsensor[base]' "
            "(or pip install cryptography)"
        )
        raise CertificateError(msg) from err
    return cryptography


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, readable by the owner only (private keys)."""
    atomic_write(path, data, mode=0o600)


def _write_public(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, readable by everyone (certificates, configs)."""
    atomic_write(path, data, mode=0o644)


def _san_entries(hosts: Sequence[str]) -> list[Any]:
    from cryptography import x509

    entries: list[Any] = []
    seen: set[str] = set()
    for host in ["127.0.0.1", "localhost", *hosts]:
        host = host.strip()
        if not host or host in seen:
            continue
        seen.add(host)
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            if not all(part and len(part) <= 63 for part in host.split(".")) or any(
                c.isspace() or c in "/:@" for c in host
            ):
                msg = f"host {host!r} is neither an IP address nor a DNS name"
                raise CertificateError(msg) from None
            entries.append(x509.DNSName(host))
    return entries


def _issue(
    cn: str,
    *,
    ca_key: Any,
    ca_cert: Any,
    days: int,
    server: bool,
    hosts: Sequence[str] = (),
) -> tuple[bytes, bytes]:
    """A new key pair and a certificate for ``cn`` signed by the CA: (cert PEM, key PEM)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    now = _dt.datetime.now(_dt.timezone.utc)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if server:
        usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _dt.timedelta(minutes=5))
        .not_valid_after(now + _dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=True,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
    )
    if server:
        builder = builder.add_extension(x509.SubjectAlternativeName(_san_entries(hosts)), critical=False)
    else:
        builder = builder.add_extension(x509.SubjectAlternativeName([x509.DNSName(cn)]), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    cert_pem = cert.public_bytes(serialization.Encoding.PEM)
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    return cert_pem, key_pem


def _make_ca(fleet: str, days: int) -> tuple[Any, Any, bytes, bytes]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    now = _dt.datetime.now(_dt.timezone.utc)
    name = x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, f"lrsensor fleet {fleet} CA"),
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "lrsensor"),
        ]
    )
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _dt.timedelta(minutes=5))
        .not_valid_after(now + _dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    cert_pem = cert.public_bytes(serialization.Encoding.PEM)
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    return key, cert, cert_pem, key_pem


def _load_ca(ca_dir: Path) -> tuple[Any, Any, bytes]:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    cert_path, key_path = ca_dir / "ca.pem", ca_dir / "ca-key.pem"
    try:
        cert_pem = cert_path.read_bytes()
        cert = x509.load_pem_x509_certificate(cert_pem)
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as err:
        msg = f"cannot reuse the CA in {ca_dir}: {err}"
        raise CertificateError(msg) from err
    return key, cert, cert_pem


def _identity(dir_: Path, name: str, cert_pem: bytes, key_pem: bytes, ca_pem: bytes) -> Identity:
    cert, key, ca = dir_ / f"{name}.pem", dir_ / f"{name}-key.pem", dir_ / "ca.pem"
    _write_public(cert, cert_pem)
    _write_private(key, key_pem)
    _write_public(ca, ca_pem)
    return Identity(name, cert, key, ca)


# ---------------------------------------------------------------------------------------------------------
# Zenoh configurations
# ---------------------------------------------------------------------------------------------------------


def access_control(fleet_keys: FleetKeys, robots: Sequence[str], *, operator: bool = True) -> dict[str, Any]:
    """The zenoh ``access_control`` section of the base station's router (default deny).

    Args:
        fleet_keys: the fleet's key layout (prefix and fleet name).
        robots: the robot names; each becomes an ACL subject matched by its certificate's common name.
        operator: also admit the read-only ``operator`` certificate.

    Returns:
        A JSON-able dict for ``access_control`` (zenoh 1.x schema: rules, subjects, policies).
    """
    root = fleet_keys.root
    fleet_side = [f"{root}/base/**", f"{root}/map/**"]  # "a/**" also matches "a" itself
    rules: list[dict[str, Any]] = [
        {
            "id": "base-all",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": list(ALL_MESSAGES),
            "key_exprs": [f"{root}/**"],
        },
        # What any robot may ask of the fleet side, and hear back from it.
        {
            "id": "robot-ask-fleet",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["query", "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": fleet_side,
        },
        {
            "id": "robot-hear-fleet",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put", "delete", "reply", "declare_queryable", "liveliness_token"],
            "key_exprs": fleet_side,
        },
        # A robot's publisher must learn that the base subscribes to ``<root>/*/cloud`` (a wildcard that is
        # not inside the robot's own prefix), or zenoh's write-side filtering never sends its samples.
        {
            "id": "robot-see-subscribers",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["declare_subscriber", "declare_liveliness_subscriber"],
            "key_exprs": [f"{root}/**"],
        },
    ]
    subjects: list[dict[str, Any]] = [{"id": "base", "cert_common_names": [BASE_CN]}]
    policies: list[dict[str, Any]] = [{"id": "base", "rules": ["base-all"], "subjects": ["base"]}]
    for robot in robots:
        check_robot_name(robot)
        rules.append(
            {
                "id": f"own-{robot}",
                "permission": "allow",
                "flows": ["ingress", "egress"],
                "messages": list(ALL_MESSAGES),
                "key_exprs": [f"{root}/{robot}/**"],
            }
        )
        subjects.append({"id": f"robot-{robot}", "cert_common_names": [robot]})
        policies.append(
            {
                "id": f"robot-{robot}",
                "rules": [f"own-{robot}", "robot-ask-fleet", "robot-hear-fleet", "robot-see-subscribers"],
                "subjects": [f"robot-{robot}"],
            }
        )
    if operator:
        rules.append(
            {
                "id": "operator-read",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["query", "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
                "key_exprs": [f"{root}/**"],
            }
        )
        rules.append(
            {
                "id": "operator-hear",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put", "delete", "reply", "declare_queryable", "liveliness_token"],
                "key_exprs": [f"{root}/**"],
            }
        )
        subjects.append({"id": "operator", "cert_common_names": [OPERATOR_CN]})
        policies.append({"id": "operator", "rules": ["operator-read", "operator-hear"], "subjects": ["operator"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _scouting_off() -> dict[str, Any]:
    return {"multicast": {"enabled": False}, "gossip": {"enabled": False}}


def router_config(
    fleet_keys: FleetKeys,
    robots: Sequence[str],
    *,
    ca: str,
    cert: str,
    key: str,
    listen: Sequence[str] = (DEFAULT_BASE_LISTEN,),
    operator: bool = True,
) -> dict[str, Any]:
    """The base station's zenoh config: a router on TLS endpoints only, mutual TLS, access control.

    Args:
        fleet_keys: the fleet's key layout.
        robots: the robots admitted (one ACL subject each).
        ca, cert, key: paths of the CA certificate and the base station's certificate and key, as they will
            be on the base station.
        listen: ``tls/HOST:PORT`` endpoints.
        operator: admit the read-only ``operator`` certificate.
    """
    for ep in listen:
        if not ep.startswith("tls/"):
            msg = f"secure listen endpoint {ep!r} must be a tls/ endpoint"
            raise CertificateError(msg)
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": _scouting_off(),
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": ca,
                    "listen_certificate": cert,
                    "listen_private_key": key,
                    "connect_certificate": cert,
                    "connect_private_key": key,
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                    "close_link_on_expiration": True,
                },
            }
        },
        "access_control": access_control(fleet_keys, robots, operator=operator),
    }


def client_config(*, ca: str, cert: str, key: str, connect: Sequence[str], mode: str = "peer") -> dict[str, Any]:
    """A robot's (or operator's) zenoh config: connects to the base station over mutual TLS, listens nowhere.

    Args:
        ca, cert, key: paths of the CA certificate and this machine's certificate and key.
        connect: ``tls/HOST:PORT`` endpoints of the base station; HOST must be in the base certificate's
            subject alternative names (``lrsensor certs --hosts``).
        mode: ``"peer"`` (robots: the session opens at once even when the base station is down and keeps
            connecting in the background, ``connect.timeout_ms = -1``, so the ROV can start and fill its
            outbox offline) or ``"client"`` (shore tools: opening fails at once when the base is unreachable).
    """
    for ep in connect:
        if not ep.startswith("tls/"):
            msg = f"secure connect endpoint {ep!r} must be a tls/ endpoint"
            raise CertificateError(msg)
    if mode not in {"peer", "client"}:
        msg = f"mode must be 'peer' or 'client', got {mode!r}"
        raise CertificateError(msg)
    return {
        "mode": mode,
        "connect": {
            "endpoints": list(connect),
            "timeout_ms": -1 if mode == "peer" else 0,
            "exit_on_failure": mode == "client",
        },
        "listen": {"endpoints": []},
        "scouting": _scouting_off(),
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": ca,
                    "connect_certificate": cert,
                    "connect_private_key": key,
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                    "close_link_on_expiration": True,
                },
            }
        },
    }


def render_json5(config: Mapping[str, Any], title: str) -> str:
    """The config as JSON5 text (plain JSON is valid JSON5) with a comment header."""
    header = "\n".join(f"// {line}" if line else "//" for line in title.splitlines())
    return f"{header}\n{json.dumps(config, indent=2)}\n"


# ---------------------------------------------------------------------------------------------------------
# The whole fleet
# ---------------------------------------------------------------------------------------------------------


def generate_fleet(
    out_dir: str | os.PathLike[str],
    fleet: str,
    robots: Sequence[str],
    *,
    hosts: Sequence[str] = (),
    prefix: str = "lrs",
    listen: Sequence[str] = (DEFAULT_BASE_LISTEN,),
    connect: Sequence[str] | None = None,
    config_dir: str | None = None,
    operator: bool = True,
    days: int = 825,
    reuse_ca: bool = True,
) -> FleetSecrets:
    """Write the CA, the base station's and every robot's certificates and their zenoh configs.

    Args:
        out_dir: output folder (created).
        fleet: fleet name; robots: robot names (the certificates' common names).
        hosts: extra IP addresses or DNS names of the base station, added to its certificate's SAN next to
            ``127.0.0.1`` and ``localhost``.
        prefix: key prefix (``lrs``).
        listen: the base station's ``tls/`` listen endpoints.
        connect: the endpoints the robots connect to (default: the first host, else 127.0.0.1, on the
            listen port).
        config_dir: where each deployment folder will live on its machine (e.g. ``/etc/lrsensor/secure``);
            the JSON5 files point there. Default: the absolute output folders themselves.
        operator: also issue a read-only ``operator`` certificate for shore tools.
        days: validity of the issued certificates, days.
        reuse_ca: keep an existing ``OUT/ca`` (so new robots join an existing fleet) instead of making a new one.

    Returns:
        The paths written, as :class:`FleetSecrets`.
    """
    _crypto()
    keys = FleetKeys(fleet=fleet, prefix=prefix)
    robots = [check_robot_name(r) for r in robots]
    if len(set(robots)) != len(robots):
        msg = f"robot names must be distinct, got {robots}"
        raise CertificateError(msg)
    if OPERATOR_CN in robots:
        msg = f"robot name {OPERATOR_CN!r} is reserved for the shore tools' certificate"
        raise CertificateError(msg)
    if days < 1:
        msg = f"certificate validity must be at least one day, got {days}"
        raise CertificateError(msg)
    out = Path(out_dir).resolve()
    ca_dir = out / "ca"
    if reuse_ca and (ca_dir / "ca.pem").is_file() and (ca_dir / "ca-key.pem").is_file():
        ca_key, ca_cert, ca_pem = _load_ca(ca_dir)
    else:
        ca_key, ca_cert, ca_pem, ca_key_pem = _make_ca(fleet, days=max(days, 3650))
        _write_public(ca_dir / "ca.pem", ca_pem)
        _write_private(ca_dir / "ca-key.pem", ca_key_pem)

    if connect is None:
        port = listen[0].rsplit(":", 1)[-1] if listen else "7447"
        host = hosts[0] if hosts else "127.0.0.1"
        host = f"[{host}]" if ":" in host else host
        connect = [f"tls/{host}:{port}"]

    def where(name: str, file: Path) -> str:
        return str(Path(config_dir) / name / file.name) if config_dir else str(file)

    configs: dict[str, Path] = {}
    cert_pem, key_pem = _issue(BASE_CN, ca_key=ca_key, ca_cert=ca_cert, days=days, server=True, hosts=hosts)
    base = _identity(out / "base", BASE_CN, cert_pem, key_pem, ca_pem)
    cfg = router_config(
        keys,
        robots,
        ca=where("base", base.ca),
        cert=where("base", base.cert),
        key=where("base", base.key),
        listen=listen,
        operator=operator,
    )
    configs["base"] = out / "base" / "base.json5"
    _write_public(
        configs["base"],
        render_json5(
            cfg,
            f"lrsensor secure profile: base station of fleet {fleet!r} (router, mutual TLS, access control)\n"
            f"run: lrsensor base --fleet {fleet} --config {where('base', configs['base'])}",
        ).encode(),
    )

    robot_ids: dict[str, Identity] = {}
    for robot in robots:
        cert_pem, key_pem = _issue(robot, ca_key=ca_key, ca_cert=ca_cert, days=days, server=False)
        ident = _identity(out / robot, robot, cert_pem, key_pem, ca_pem)
        robot_ids[robot] = ident
        cfg = client_config(
            ca=where(robot, ident.ca), cert=where(robot, ident.cert), key=where(robot, ident.key), connect=connect
        )
        configs[robot] = out / robot / f"{robot}.json5"
        _write_public(
            configs[robot],
            render_json5(
                cfg,
                f"lrsensor secure profile: ROV {robot!r} of fleet {fleet!r} (peer connecting to the base, mutual TLS)\n"
                f"run: lrsensor rov --fleet {fleet} --robot {robot} --config "
                f"{where(robot, configs[robot])} ...",
            ).encode(),
        )

    op: Identity | None = None
    if operator:
        cert_pem, key_pem = _issue(OPERATOR_CN, ca_key=ca_key, ca_cert=ca_cert, days=days, server=False)
        op = _identity(out / OPERATOR_CN, OPERATOR_CN, cert_pem, key_pem, ca_pem)
        cfg = client_config(
            ca=where(OPERATOR_CN, op.ca),
            cert=where(OPERATOR_CN, op.cert),
            key=where(OPERATOR_CN, op.key),
            connect=connect,
            mode="client",
        )
        configs[OPERATOR_CN] = out / OPERATOR_CN / f"{OPERATOR_CN}.json5"
        _write_public(
            configs[OPERATOR_CN],
            render_json5(
                cfg, f"lrsensor secure profile: read-only shore tools of fleet {fleet!r} (client, mutual TLS)"
            ).encode(),
        )

    return FleetSecrets(
        out_dir=out,
        ca_cert=ca_dir / "ca.pem",
        ca_key=ca_dir / "ca-key.pem",
        base=base,
        robots=robot_ids,
        operator=op,
        configs=configs,
    )


def certificate_common_name(path: str | os.PathLike[str]) -> str:
    """The subject common name of a PEM certificate (for checks and tests)."""
    _crypto()
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    except (OSError, ValueError) as err:
        msg = f"cannot read certificate {path}: {err}"
        raise CertificateError(msg) from err
    attrs = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(attrs[0].value) if attrs else ""


def example_configs(
    fleet: str = "reef",
    robots: Sequence[str] = ("rov1", "rov2"),
    host: str = "192.168.2.1",
    config_dir: str = "/etc/lrsensor/secure",
) -> dict[str, str]:
    """The JSON5 files shipped in ``deploy/secure/`` (file name -> text), rendered without any certificate.

    They are what ``lrsensor certs --out OUT --fleet reef --robots rov1,rov2 --hosts 192.168.2.1
    --config-dir /etc/lrsensor/secure`` writes next to the certificates; a test keeps them in step.
    """
    keys = FleetKeys(fleet=fleet)
    d = Path(config_dir)
    files: dict[str, str] = {}
    base = router_config(
        keys,
        robots,
        ca=str(d / "base" / "ca.pem"),
        cert=str(d / "base" / "base.pem"),
        key=str(d / "base" / "base-key.pem"),
    )
    files["base.json5"] = render_json5(
        base,
        f"lrsensor secure profile: base station of fleet {fleet!r} (router, mutual TLS, access control)\n"
        f"Generated by: lrsensor certs --out OUT --fleet {fleet} --robots {','.join(robots)} --hosts {host} "
        f"--config-dir {config_dir}\n"
        f"run: lrsensor base --fleet {fleet} --config {d / 'base' / 'base.json5'}",
    )
    for robot in robots:
        cfg = client_config(
            ca=str(d / robot / "ca.pem"),
            cert=str(d / robot / f"{robot}.pem"),
            key=str(d / robot / f"{robot}-key.pem"),
            connect=[f"tls/{host}:7447"],
        )
        files[f"{robot}.json5"] = render_json5(
            cfg,
            f"lrsensor secure profile: ROV {robot!r} of fleet {fleet!r} (peer connecting to the base, mutual TLS)\n"
            f"run: lrsensor rov --fleet {fleet} --robot {robot} --config {d / robot / f'{robot}.json5'} ...",
        )
    return files
