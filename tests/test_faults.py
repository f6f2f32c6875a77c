"""Faults with real processes on loopback: nothing lost, nothing let in.

- the base station is SIGKILLed mid-dive and restarted with the same ``--state``: every cloud of two ROV
  processes is held at the end, nothing it had acknowledged is lost;
- the router is down for 10 s during a ROV replay: every cloud is delivered afterwards;
- hundreds of garbage payloads on a robot's key: the base keeps answering and counts every one;
- the secure profile end to end: ``lrsensor base/rov --config`` over mutual TLS with access control, a
  spoofed cloud under another robot's key is never counted, a session without certificate cannot connect.
"""

from __future__ import annotations

import contextlib
import json
import signal
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from procs import Proc, lrsensor_cmd, router_cmd  # noqa: E402
from waiting import wait_until  # noqa: E402

from lrsensor.frames import Pose  # noqa: E402
from services.errors import WireError  # noqa: E402
from services.simsource import record_sim_dive  # noqa: E402
from services.testnet import free_port  # noqa: E402
from services.wire import CloudMsg  # noqa: E402

pytestmark = pytest.mark.slow

N_FRAMES = 40
WAIT_S = 30.0  # how long a test waits for a service or a state unless it says otherwise


@pytest.fixture(scope="module")
def dive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_sim_dive(tmp_path_factory.mktemp("faults") / "dive", "rov1", n_frames=N_FRAMES, seed=3)


def client_conf(port: int, timeout_ms: int = 30000) -> Any:
    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": timeout_ms},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    return zenoh.Config.from_json5(json.dumps(conf))


def get_status(session: Any, fleet: str, timeout_s: float = 3.0) -> dict[str, Any] | None:
    for reply in session.get(f"lrs/{fleet}/base/status", timeout=timeout_s):
        if reply.ok is not None:
            data: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return data
    return None


def robot_status(session: Any, fleet: str, robot: str) -> dict[str, Any]:
    st = get_status(session, fleet)
    return (st or {}).get("robots", {}).get(robot, {})


def rov_args(fleet: str, robot: str, dive: Path, rate: float, outbox: Path, *net: str) -> list[str]:
    return lrsensor_cmd(
        "rov", "--fleet", fleet, "--robot", robot, *net,
        "--source", str(dive), "--imu", f"csv:{dive / 'imu.csv'}", "--calib", str(dive / "calib.json"),
        "--rate", str(rate), "--ack-timeout-s", "90", "--outbox", str(outbox),
    )  # fmt: skip


def base_args(fleet: str, state: Path, *net: str, map_mode: str = "off") -> list[str]:
    return lrsensor_cmd(
        "base", "--fleet", fleet, *net, "--state", str(state), "--map", map_mode, "--status-every-s", "0"
    )


def resent_count(output: str) -> int:
    """The ``N re-sent`` of the ROV's outbox summary line."""
    return int(output.split(" re-sent")[0].rsplit(" ", 1)[-1])


def assert_delivered(rov: Proc, robot: str, timeout_s: float = 120.0) -> None:
    assert rov.wait(timeout_s) == 0, rov.output()
    out = rov.output()
    assert f"rov {robot}: frames {N_FRAMES}, published {N_FRAMES}" in out, out
    assert "delivery confirmed" in out, out


def test_base_sigkill_mid_dive_loses_nothing(dive: Path, tmp_path: Path, procs: list[Proc]) -> None:
    fleet, port, state = "fk", free_port(), tmp_path / "state"
    listen = ("--listen", f"tcp/127.0.0.1:{port}")
    base = Proc(base_args(fleet, state, *listen, map_mode="auto"), tmp_path / "base.log")
    procs.append(base)
    robots = ("rov1", "rov2")
    with zenoh.open(client_conf(port)) as s:
        assert wait_until(lambda: get_status(s, fleet) is not None, WAIT_S), base.output()
    rovs = {}
    for r in robots:
        rovs[r] = Proc(
            rov_args(fleet, r, dive, 5.0, tmp_path / f"outbox-{r}", "--connect", f"tcp/127.0.0.1:{port}"),
            tmp_path / f"{r}.log",
        )
        procs.append(rovs[r])
    with zenoh.open(client_conf(port)) as s:
        assert wait_until(lambda: all(robot_status(s, fleet, r).get("acked", 0) >= 8 for r in robots), 60), (
            base.output()
        )
        before = {r: robot_status(s, fleet, r) for r in robots}
    # mid-dive: the base station (and its in-process router) dies without a chance to save anything
    base.p.send_signal(signal.SIGKILL)
    base.wait(10)
    assert all(rovs[r].p.poll() is None for r in robots), "the ROVs must still be diving"
    time.sleep(2.0)
    base2 = Proc(base_args(fleet, state, *listen, map_mode="auto"), tmp_path / "base.log")
    procs.append(base2)
    with zenoh.open(client_conf(port)) as s:
        assert wait_until(lambda: get_status(s, fleet) is not None, WAIT_S), base2.output()
        after = {r: robot_status(s, fleet, r) for r in robots}
        for r in robots:  # nothing it had acknowledged is lost
            assert after[r]["received"] >= before[r]["acked"] > 0, (before, after)
        for r in robots:
            assert_delivered(rovs[r], r)
            assert resent_count(rovs[r].output()) > 0  # clouds sent while the base was down went again
        final = {r: robot_status(s, fleet, r) for r in robots}
    for r in robots:
        assert (final[r]["received"], final[r]["missed"], final[r]["last_seq"]) == (N_FRAMES, 0, N_FRAMES - 1), final
        assert not list((tmp_path / f"outbox-{r}").glob("*.msg")), "every cloud acknowledged"
    assert base2.stop(signal.SIGTERM) == 0, base2.output()
    saved = json.loads((state / "fleet.json").read_text())
    for r in robots:
        assert saved["robots"][r]["acked"] == [[0, N_FRAMES - 1]]


def test_router_outage_of_10_s_during_a_replay(dive: Path, tmp_path: Path, procs: list[Proc]) -> None:
    fleet, port = "fo", free_port()
    router = Proc(router_cmd(port), tmp_path / "router.log")
    procs.append(router)
    assert wait_until(lambda: "router up" in router.output(), WAIT_S), router.output()
    connect = ("--mode", "client", "--connect", f"tcp/127.0.0.1:{port}")
    base = Proc(base_args(fleet, tmp_path / "state", *connect), tmp_path / "base.log")
    procs.append(base)
    with zenoh.open(client_conf(port)) as s:
        assert wait_until(lambda: get_status(s, fleet) is not None, WAIT_S), base.output()
    rov = Proc(
        rov_args(fleet, "rov1", dive, 2.5, tmp_path / "outbox", "--connect", f"tcp/127.0.0.1:{port}"),
        tmp_path / "rov1.log",
    )
    procs.append(rov)
    with zenoh.open(client_conf(port)) as s:
        assert wait_until(lambda: robot_status(s, fleet, "rov1").get("received", 0) >= 5, 60), rov.output()
    router.p.send_signal(signal.SIGKILL)
    router.wait(10)
    t_down = time.monotonic()
    time.sleep(10.0)
    assert rov.p.poll() is None, "the replay must still be running when the router comes back"
    router2 = Proc(router_cmd(port), tmp_path / "router.log")
    procs.append(router2)
    assert wait_until(lambda: router2.output().count("router up") == 2, WAIT_S), router2.output()
    assert time.monotonic() - t_down >= 10.0
    assert_delivered(rov, "rov1")
    assert resent_count(rov.output()) > 0, rov.output()  # the outage cost deliveries; the outbox made them up
    with zenoh.open(client_conf(port)) as s:
        st = robot_status(s, fleet, "rov1")
    assert (st["received"], st["missed"]) == (N_FRAMES, 0), st
    assert base.p.poll() is None, base.output()
    assert base.stop(signal.SIGTERM) == 0
    router2.stop(signal.SIGTERM)


def _garbage(rng: np.random.Generator, valid: bytes, i: int) -> bytes:
    kind = i % 6
    if kind == 0:
        return rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
    if kind == 1:
        return valid[: int(rng.integers(1, len(valid) - 1))]  # truncated
    obj = msgpack.unpackb(valid, raw=False)
    if kind == 2:
        obj["v"] = 99  # wrong version
    elif kind == 3:
        obj["points"] = np.full(obj["n"] * 3, np.nan, "<f4").tobytes()  # non-finite
    elif kind == 4:
        obj["robot"] = "rov2"  # another robot's cloud under rov1's key
    else:
        obj["n"] = obj["n"] + 7  # inconsistent size
    return bytes(msgpack.packb(obj, use_bin_type=True))


def test_garbage_on_a_robot_key_is_counted_and_never_stops_the_base(
    dive: Path, tmp_path: Path, procs: list[Proc]
) -> None:
    fleet, port = "fg", free_port()
    base = Proc(base_args(fleet, tmp_path / "state", "--listen", f"tcp/127.0.0.1:{port}"), tmp_path / "base.log")
    procs.append(base)
    rng = np.random.default_rng(11)
    n = 10
    valid = CloudMsg(
        "rov1", 10**6, 1_700_000_000_000_000_000, Pose(0, 0, 1, 0, 0, 0),
        rng.normal(size=(n, 3)).astype(np.float32), np.zeros(n, np.uint8), np.ones(n, np.float32),
    ).to_bytes()  # fmt: skip
    garbage = [_garbage(rng, valid, i) for i in range(300)]
    for g in garbage:  # every one is refused: by the decoder, or as another robot's cloud under rov1's key
        with contextlib.suppress(WireError):
            assert CloudMsg.from_bytes(g).robot != "rov1"
    with zenoh.open(client_conf(port)) as s:
        assert wait_until(lambda: get_status(s, fleet) is not None, WAIT_S), base.output()
        rov = Proc(
            rov_args(fleet, "rov1", dive, 8.0, tmp_path / "outbox", "--connect", f"tcp/127.0.0.1:{port}"),
            tmp_path / "rov1.log",
        )
        procs.append(rov)
        assert wait_until(lambda: robot_status(s, fleet, "rov1").get("received", 0) >= 1, 60), rov.output()
        pub = s.declare_publisher(f"lrs/{fleet}/rov1/cloud", congestion_control=zenoh.CongestionControl.BLOCK)
        stray = s.declare_publisher(f"lrs/{fleet}/base/cloud", congestion_control=zenoh.CongestionControl.BLOCK)
        answered = 0
        for i, g in enumerate(garbage):
            pub.put(g)
            if i % 30 == 0:
                stray.put(b"\x00garbage")
                assert get_status(s, fleet) is not None, "the base must keep answering during the flood"
                answered += 1
        pub.put(b"\x01" * (17 * 1024 * 1024))  # oversized
        assert wait_until(lambda: robot_status(s, fleet, "rov1").get("rejected", 0) == 301, 60), get_status(s, fleet)
        assert_delivered(rov, "rov1")
        st = get_status(s, fleet)
    assert st is not None
    r1 = st["robots"]["rov1"]
    assert (r1["received"], r1["missed"], r1["rejected"]) == (N_FRAMES, 0, 301), r1
    assert st["robots"]["?"]["rejected"] == 10  # payloads on a key that names no robot: counted too
    assert sum(r1["rejected_reasons"].values()) >= 1
    assert answered == 10
    assert base.p.poll() is None
    assert base.stop(signal.SIGTERM) == 0


def test_secure_profile_with_processes(dive: Path, tmp_path: Path, procs: list[Proc]) -> None:
    pytest.importorskip("cryptography")
    from services.certs import generate_fleet

    fleet, port = "fs", free_port()
    sec = generate_fleet(tmp_path / "secure", fleet, ["rov1", "rov2"], listen=[f"tls/127.0.0.1:{port}"])
    base = Proc(
        lrsensor_cmd("base", "--fleet", fleet, "--config", str(sec.configs["base"]), "--state", str(tmp_path / "state"),
                 "--map", "off", "--status-every-s", "0"),
        tmp_path / "base.log",
    )  # fmt: skip
    procs.append(base)
    op_conf = zenoh.Config.from_file(str(sec.configs["operator"]))
    assert wait_until(lambda: "running" in base.output(), WAIT_S), base.output()
    with zenoh.open(op_conf) as op:
        assert wait_until(lambda: get_status(op, fleet) is not None, WAIT_S), base.output()
        rov = Proc(
            rov_args(fleet, "rov1", dive, 10.0, tmp_path / "outbox", "--config", str(sec.configs["rov1"])),
            tmp_path / "rov1.log",
        )
        procs.append(rov)
        assert_delivered(rov, "rov1")
        # rov1's certificate, another robot's key: the router drops it (the base never counts rov2)
        with zenoh.open(zenoh.Config.from_file(str(sec.configs["rov1"]))) as spoof:
            own = spoof.declare_publisher(f"lrs/{fleet}/rov1/status")
            assert wait_until(lambda: own.matching_status.matching, WAIT_S), "rov1's link is up"
            rng = np.random.default_rng(1)
            for seq in range(20):
                fake = CloudMsg(
                    "rov2", seq, 1_700_000_000_000_000_000, Pose(0, 0, 1, 0, 0, 0),
                    rng.normal(size=(5, 3)).astype(np.float32), np.zeros(5, np.uint8), np.ones(5, np.float32),
                )  # fmt: skip
                spoof.put(f"lrs/{fleet}/rov2/cloud", fake.to_bytes())
                time.sleep(0.01)
            time.sleep(1.0)
        st = get_status(op, fleet)
        assert st is not None
        assert (st["robots"]["rov1"]["received"], st["robots"]["rov1"]["missed"]) == (N_FRAMES, 0)
        assert "rov2" not in st["robots"], st["robots"]
        assert st["robots"]["rov1"]["rejected"] == 0
    # no certificate: the TLS endpoint refuses the session
    plain = {
        "mode": "client",
        "connect": {"endpoints": [f"tls/127.0.0.1:{port}"], "timeout_ms": 0},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": {"root_ca_certificate": str(sec.ca_cert)}}},
    }
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh.Config.from_json5(json.dumps(plain)))
    assert base.stop(signal.SIGTERM) == 0, base.output()
