"""Fuzz run over every decoder: N random and mutated inputs each, rejections counted by reason.

    python benchmarks/fuzz_decoders.py [--n 2000] [--seed 1]

Decoders: wire messages (cloud schema 1, cloud of either schema with the compact schema 2, calib, status),
calibration JSON, OpenROV serial telemetry lines, CSV IMU
logs. Inputs: arbitrary bytes, arbitrary msgpack/JSON values, valid payloads with random edits (truncation,
byte flips, insertions, deletions, duplications) and valid maps with fields replaced or removed. A decoder
passes when every input is either accepted or rejected with its own error type; anything else is listed as
UNEXPECTED with the input (hex) that caused it. Prints a markdown table per decoder.
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import re
import sys
import tempfile
import time
import traceback
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.errors import CalibrationFileError
from lrsensor.frames import Pose
from services.errors import ImuError, WireError
from services.imu import CsvImu, OpenRovParser
from services.wire import CalibMsg, CloudMsg, StatusMsg, StripeMsg, calibration_fingerprint, decode_cloud


def _valid_cloud(rng: np.random.Generator, n: int) -> CloudMsg:
    return CloudMsg(
        robot="rov1",
        seq=int(rng.integers(0, 10**6)),
        t_ns=1_700_000_000_000_000_000,
        pose=Pose(1.0, -2.0, 3.0, 0.1, -0.05, 1.2),
        points_body=rng.normal(size=(n, 3)).astype(np.float32),
        laser=rng.integers(0, 2, size=n).astype(np.uint8),
        quality=rng.random(n).astype(np.float32),
        uv=None if n % 2 else rng.random((n, 2)).astype(np.float32),
    )


def _valid_stripe(rng: np.random.Generator, n: int) -> StripeMsg:
    """A compact cloud of two lasers' stripes with a gap and a row jump (several runs)."""
    laser = np.repeat(np.arange(2, dtype=np.uint8), n // 2 + 1)[:n]
    column = (np.arange(n) % (n // 2 + 1) + np.where(np.arange(n) % 7 == 3, 5, 0)).astype(np.uint16)
    row = (rng.normal(540, 3, n) * 4096).astype(np.int32)
    return StripeMsg(
        robot="rov1",
        seq=int(rng.integers(0, 10**6)),
        t_ns=1_700_000_000_000_000_000,
        pose=Pose(1.0, -2.0, 3.0, 0.1, -0.05, 1.2),
        calib_id=calibration_fingerprint(Calibration.paper(0.1)),
        laser=laser,
        column=column,
        row_fx=row,
        quality_u8=rng.integers(0, 256, n).astype(np.uint8),
    )


def _rand_value(r: random.Random, depth: int = 0) -> Any:
    kind = r.randrange(9 if depth < 3 else 7)
    if kind == 0:
        return None
    if kind == 1:
        return r.random() < 0.5
    if kind == 2:
        return r.choice([0, 1, -1, 2**31, -(2**63), 2**64 - 1, r.randrange(-1000, 10**6)])
    if kind == 3:
        return r.choice([0.0, -0.0, float("nan"), float("inf"), float("-inf"), 1e308, r.uniform(-1e3, 1e3)])
    if kind == 4:
        return "".join(r.choice("abcxyz/*$#?.\u00e9\U0001f600") for _ in range(r.randrange(12)))
    if kind == 5:
        return r.randbytes(r.randrange(64))
    if kind == 6:
        return r.choice(["cloud", "calib", "status", "rov1", "base", ""])
    if kind == 7:
        return [_rand_value(r, depth + 1) for _ in range(r.randrange(5))]
    return {str(_rand_value(r, depth + 1))[:8]: _rand_value(r, depth + 1) for _ in range(r.randrange(5))}


def _mutate(r: random.Random, data: bytes) -> bytes:
    out = bytearray(data)
    for _ in range(r.randrange(1, 5)):
        op = r.randrange(5)
        i = r.randrange(len(out)) if out else 0
        if op == 0:
            del out[i:]
        elif op == 1 and out:
            out[i] ^= r.randrange(1, 256)
        elif op == 2:
            out[i:i] = r.randbytes(r.randrange(1, 9))
        elif op == 3:
            del out[i : i + r.randrange(1, 9)]
        else:
            out[i:i] = out[i : i + r.randrange(1, 17)]
    return bytes(out)


def _swap_fields(r: random.Random, data: bytes) -> bytes:
    obj = msgpack.unpackb(data, raw=False)
    for _ in range(r.randrange(1, 4)):
        key = r.choice(sorted(obj)) if obj else "x"
        action = r.randrange(3)
        if action == 0:
            obj[key] = _rand_value(r)
        elif action == 1:
            obj.pop(key, None)
        else:
            obj[str(_rand_value(r))[:6]] = _rand_value(r)
    try:
        return bytes(msgpack.packb(obj, use_bin_type=True))
    except (OverflowError, ValueError, TypeError):
        return data


def _pack_any(r: random.Random) -> bytes:
    try:
        return bytes(msgpack.packb(_rand_value(r), use_bin_type=True))
    except (OverflowError, ValueError, TypeError):
        return b"\xc1"


_NUM = re.compile(r"-?\d+(\.\d+)?(e[+-]?\d+)?")
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")


def reason_of(err: BaseException) -> str:
    """A short, input-independent reason: numbers and quoted values blanked, the where-prefix dropped."""
    text = str(err).split("\n")[0]
    text = re.sub(r"^(cloud|calib|status)( of| from)? [\w.\-]+(#\d+)?: ", r"\1: ", text)
    text = text.split(": ", 1)[-1] if text.count(": ") >= 1 and len(text) > 90 else text
    text = re.sub(r"0x[0-9a-fA-F]+", "0x..", text)
    text = re.sub(r"(/[^\s:]+)+/", "", text)  # folders of file paths
    text = re.sub(r"codec can't decode bytes? .*", "codec can't decode (not UTF-8)", text)
    text = _QUOTED.sub("'…'", _NUM.sub("N", text))
    return text[:110]


def run_decoder(
    name: str,
    inputs: Callable[[random.Random], tuple[str, bytes]],
    decode: Callable[[bytes], Any],
    expected: tuple[type[BaseException], ...],
    n: int,
    seed: int,
) -> dict[str, Any]:
    r = random.Random(seed)
    accepted = 0
    reasons: Counter[str] = Counter()
    by_gen: Counter[str] = Counter()
    unexpected: list[str] = []
    t0 = time.perf_counter()
    for _ in range(n):
        gen, data = inputs(r)
        by_gen[gen] += 1
        try:
            decode(data)
            accepted += 1
        except expected as err:
            reasons[reason_of(err)] += 1
        except Exception as err:  # this is what the fuzz run looks for
            unexpected.append(f"{type(err).__name__}: {err} <- {data[:64].hex()}")
            if len(unexpected) <= 3:
                traceback.print_exc()
    dt = time.perf_counter() - t0
    return {
        "name": name,
        "n": n,
        "accepted": accepted,
        "rejected": sum(reasons.values()),
        "unexpected": unexpected,
        "reasons": reasons,
        "by_gen": by_gen,
        "us_per_input": 1e6 * dt / max(n, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="inputs per decoder")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "fuzz.md"))
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)  # the decoders log each rejection; the table counts them instead

    rng = np.random.default_rng(args.seed)
    valid = {
        "cloud": [_valid_cloud(rng, n).to_bytes() for n in (0, 1, 7, 300)],
        "stripe": [_valid_stripe(rng, n).to_bytes() for n in (0, 1, 7, 300)],
        "calib": [CalibMsg("rov1", Calibration.paper(0.1)).to_bytes()],
        "status": [StatusMsg("rov1", 1_700_000_000_000_000_000, "running", 10, 9, 1, 0, 8).to_bytes()],
    }

    def wire_inputs(kind: str) -> Callable[[random.Random], tuple[str, bytes]]:
        def gen(r: random.Random) -> tuple[str, bytes]:
            g = r.randrange(5)
            base = r.choice(valid[kind])
            if g == 0:
                return "random bytes", r.randbytes(r.randrange(256))
            if g == 1:
                return "random msgpack", _pack_any(r)
            if g == 2:
                return "mutated", _mutate(r, base)
            if g == 3:
                return "fields swapped", _swap_fields(r, base)
            return "valid", base

        return gen

    calib_text = Calibration.paper(0.1).to_json().encode()

    def calib_inputs(r: random.Random) -> tuple[str, bytes]:
        g = r.randrange(4)
        if g == 0:
            return "random bytes", r.randbytes(r.randrange(256))
        if g == 1:
            try:
                return "random json", json.dumps(_rand_value(r)).encode()
            except (TypeError, ValueError):
                return "random json", b"[]"
        if g == 2:
            return "mutated", _mutate(r, calib_text)
        return "valid", calib_text

    good_line = b"hdgd:90.5;deep:1.25;pitc:-3.0;roll:2.0;temp:18.2"
    tokens = [b"hdgd:", b"deep:", b"pitc:", b"roll:", b";", b":", b"nan", b"inf", b"1e400", b"-3.5", b"\xff", b"\x00"]

    def serial_inputs(r: random.Random) -> tuple[str, bytes]:
        g = r.randrange(4)
        if g == 0:
            return "random bytes", r.randbytes(r.randrange(200)) + b"\n"
        if g == 1:
            return "token soup", b"".join(r.choice(tokens) for _ in range(r.randrange(12))) + b"\n"
        if g == 2:
            return "mutated", _mutate(r, good_line) + b"\n"
        return "valid", good_line + b"\n"

    class _RejectedError(Exception):
        pass

    def serial_decode(data: bytes) -> Any:
        p = OpenRovParser()
        p.feed(good_line + b"\n")  # all four fields known: a good line emits a reading
        before = p.rejected
        out = p.feed(data)
        if p.rejected > before:
            raise _RejectedError(next(iter(p.reasons)))
        return out

    tmp = Path(tempfile.mkdtemp(prefix="fuzz-csv-"))
    header = b"t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\n"
    good_csv = header + b"".join(f"{1_000_000_000 + i * 1000},1,2,3,4,5,6\n".encode() for i in range(20))

    def csv_inputs(r: random.Random) -> tuple[str, bytes]:
        g = r.randrange(3)
        if g == 0:
            return "random bytes", (header if r.random() < 0.5 else b"") + r.randbytes(r.randrange(200))
        if g == 1:
            return "mutated", _mutate(r, good_csv)
        return "valid", good_csv

    def csv_decode(data: bytes) -> Any:
        path = tmp / "imu.csv"
        path.write_bytes(data)
        imu = CsvImu(path)
        if imu.rejected:
            raise _RejectedError(f"{imu.rejected} rows rejected (log accepted)")
        return imu

    runs = [
        run_decoder("CloudMsg.from_bytes", wire_inputs("cloud"), CloudMsg.from_bytes, (WireError,), args.n, args.seed),
        run_decoder("decode_cloud (schema 2)", wire_inputs("stripe"), decode_cloud, (WireError,), args.n, args.seed),
        run_decoder("CalibMsg.from_bytes", wire_inputs("calib"), CalibMsg.from_bytes, (WireError,), args.n, args.seed),
        run_decoder(
            "StatusMsg.from_bytes", wire_inputs("status"), StatusMsg.from_bytes, (WireError,), args.n, args.seed
        ),
        run_decoder(
            "Calibration.from_json",
            calib_inputs,
            lambda d: Calibration.from_json(d, "fuzz"),
            (CalibrationFileError,),
            args.n,
            args.seed,
        ),
        run_decoder("OpenRovParser.feed", serial_inputs, serial_decode, (_RejectedError,), args.n, args.seed),
        run_decoder("CsvImu", csv_inputs, csv_decode, (ImuError, _RejectedError), max(1, args.n // 4), args.seed),
    ]

    lines = [f"# Decoder fuzz run (seed {args.seed}, {args.n} inputs per decoder, CSV {max(1, args.n // 4)})", ""]
    lines += [
        "| decoder | inputs | accepted | rejected | unexpected | µs/input |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for run in runs:
        lines.append(
            f"| {run['name']} | {run['n']} | {run['accepted']} | {run['rejected']} | {len(run['unexpected'])} "
            f"| {run['us_per_input']:.0f} |"
        )
    for run in runs:
        lines += ["", f"## {run['name']}: rejections by reason (top 12)", "", "| count | reason |", "| ---: | --- |"]
        for reason, count in run["reasons"].most_common(12):
            lines.append(f"| {count} | {reason.replace('|', '/')} |")
        if run["unexpected"]:
            lines += ["", "UNEXPECTED:"] + [f"- {u}" for u in run["unexpected"][:10]]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    bad = sum(len(r["unexpected"]) for r in runs)
    print(f"{bad} unexpected exceptions; table written to {out}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
