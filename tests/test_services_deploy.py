"""The shipped deployments: every Zenoh JSON5 file loads, the flags override its endpoints, a ROV config talks
to a base config on loopback, and the systemd units' command lines parse with the real CLI."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from lrsensor.cli import build_parser
from services.testnet import free_port
from services.zconfig import NetworkOptions, make_config, open_session

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
CONFIGS = sorted([*(DEPLOY / "fleet").glob("*.json5"), *(DEPLOY / "single-rov").glob("*.json5")])


def test_the_deployments_are_shipped() -> None:
    names = {p.relative_to(DEPLOY).as_posix() for p in DEPLOY.rglob("*") if p.is_file()}
    for need in (
        "README.md",
        "fleet/base.json5",
        "fleet/rov1.json5",
        "fleet/rov2.json5",
        "fleet/rov3.json5",
        "fleet/lrsensor-base.service",
        "fleet/lrsensor-rov@.service",
        "single-rov/shore.json5",
        "single-rov/rov.json5",
    ):
        assert need in names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.relative_to(DEPLOY).as_posix())
def test_config_loads_with_multicast_off(path: Path) -> None:
    conf = make_config(NetworkOptions(config_file=str(path)))
    mode = json.loads(conf.get_json("mode"))
    assert mode == ("router" if path.stem in {"base", "shore"} else "client")
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


@pytest.mark.parametrize(
    ("base_cfg", "rov_cfg"),
    [("fleet/base.json5", "fleet/rov2.json5"), ("single-rov/shore.json5", "single-rov/rov.json5")],
)
def test_rov_config_reaches_base_config_on_loopback(base_cfg: str, rov_cfg: str) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    router_opts = NetworkOptions(config_file=str(DEPLOY / base_cfg), listen=(ep,))
    rov_opts = NetworkOptions(config_file=str(DEPLOY / rov_cfg), connect=(ep,))
    with open_session(router_opts) as router:
        assert json.loads(make_config(router_opts).get_json("listen/endpoints")) == [ep]
        got: list[str] = []
        q = router.declare_queryable("lrs/x/base/status", lambda query: query.reply(query.key_expr, b"{}"))
        with open_session(rov_opts) as rov:
            for reply in rov.get("lrs/x/base/status", timeout=5):
                if reply.ok is not None:
                    got.append(reply.ok.payload.to_string())
        q.undeclare()
    assert got == ["{}"]


def _exec_args(unit: Path, env: dict[str, str], instance: str = "") -> list[str]:
    text = unit.read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("ExecStart="))
    cmd = line.removeprefix("ExecStart=").replace("%i", instance)
    for k, v in env.items():
        cmd = cmd.replace(f"${k}", v)
    assert "$" not in cmd, cmd
    args = shlex.split(cmd)
    assert args[0].endswith("/lrsensor")
    return args[1:]


def test_systemd_units_parse_with_the_cli() -> None:
    parser = build_parser()
    args = parser.parse_args(_exec_args(DEPLOY / "fleet" / "lrsensor-base.service", {}))
    assert (args.command, args.fleet, args.state) == ("base", "reef", "/var/lib/lrsensor")
    env_text = (DEPLOY / "fleet" / "rov2.env").read_text()
    m = re.search(r"^LRS_ROV_ARGS=(.*)$", env_text, re.MULTILINE)
    assert m
    args = parser.parse_args(
        _exec_args(DEPLOY / "fleet" / "lrsensor-rov@.service", {"LRS_ROV_ARGS": m.group(1)}, "rov2")
    )
    assert (args.command, args.robot, args.config) == ("rov", "rov2", "/etc/lrsensor/rov2.json5")
    assert args.imu.startswith("serial:")
