"""Damaged variants of a small MCAP log, and what reading each one must give.

`variants(data, n, seed)` makes `n` seeded mutations of a log's bytes (truncations, bit flips,
zeroed or random-filled ranges, a range cut out); `read_variant` reads one through
`McapLogSource` + `LogSet` (what every stage reads through) and classifies the outcome:

- "error": a `CvslamError` (one line for the user);
- "warned": read, with at least one warning from the reader;
- "intact": read with no warning (allowed only when the bytes are unchanged);
- "altered": some record read differs from every record of the original (never allowed);
- "silent loss": fewer records than the original and no warning (never allowed);
- "traceback": any other exception (never allowed); "hang": past the time limit (never).

Used by `tests/io/test_mcap_fuzz.py` (40 variants in `make test`) and `make fuzz` (more).
"""

from __future__ import annotations

import contextlib
import hashlib
import signal
import traceback
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cvslam_cli.config import load_config
from cvslam_cli.errors import CvslamError
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.records.log import ImuSample, PoseRecord, StereoFrame

BAD_OUTCOMES = ("altered", "silent loss", "traceback", "hang")


@dataclass(frozen=True)
class Variant:
    kind: str
    detail: str
    data: bytes


def variants(data: bytes, n: int, seed: int) -> Iterator[Variant]:
    """`n` damaged copies of `data`, cycling through the kinds of damage, seeded."""
    rng = np.random.default_rng(seed)
    kinds = ("truncate", "flip", "zero", "random", "cut")
    size = len(data)
    for i in range(n):
        kind = kinds[i % len(kinds)]
        buf = bytearray(data)
        if kind == "truncate":
            at = int(rng.integers(0, size))
            buf = buf[:at]
            detail = f"first {at} bytes"
        elif kind == "flip":
            offsets = rng.integers(0, size, int(rng.integers(1, 9)))
            for off in offsets:
                buf[off] ^= 1 << int(rng.integers(0, 8))
            detail = f"bits flipped at {sorted(int(o) for o in offsets)}"
        else:
            at = int(rng.integers(0, size))
            length = int(min(rng.integers(1, 4096), size - at))
            if kind == "zero":
                buf[at : at + length] = bytes(length)
            elif kind == "random":
                buf[at : at + length] = rng.integers(0, 256, length, dtype=np.uint8).tobytes()
            else:
                del buf[at : at + length]
            detail = f"{length} bytes at {at}"
        yield Variant(kind, detail, bytes(buf))


def record_keys(path: Path) -> tuple[list[str], list[str]]:
    """(content key of every record read from the log at `path`, reader warnings)."""
    src = McapLogSource(path)
    logs = LogSet([src], load_config().logs, strict=False)
    keys = []
    for rec in logs.records():
        if isinstance(rec, StereoFrame):
            h = hashlib.sha1(rec.left.image.tobytes() + rec.right.image.tobytes()).hexdigest()
            keys.append(f"frame {rec.stamp_ns} {rec.right.stamp_ns} {h}")
        elif isinstance(rec, ImuSample):
            keys.append(f"imu {rec.stamp_ns} {rec.gyro_rad_s.tobytes().hex()}")
            keys[-1] += rec.accel_m_s2.tobytes().hex()
        elif isinstance(rec, PoseRecord):
            keys.append(f"pose {rec.stamp_ns} {np.asarray(rec.p_m).tobytes().hex()}")
    if logs.vehicles:
        rig = logs.rig(next(iter(logs.vehicles)))
        keys.append(f"rig {rig.left.K.tobytes().hex()} {rig.baseline_m!r}")
    return keys, list(src.warnings)


@contextlib.contextmanager
def _time_limit(seconds: int) -> Iterator[None]:
    def fire(signum: int, frame: object) -> None:
        raise TimeoutError

    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def read_variant(path: Path, reference: list[str], *, damaged: bool, limit_s: int = 20) -> str:
    """The outcome of reading the variant at `path` (see the module docstring)."""
    try:
        with _time_limit(limit_s):
            keys, warnings = record_keys(path)
    except TimeoutError:
        return "hang"
    except CvslamError as exc:
        text = str(exc)
        return "error" if "\n" not in text and text.strip() else "traceback"
    except Exception:
        return "traceback: " + traceback.format_exc().splitlines()[-1]
    if set(keys) - set(reference):
        return "altered"
    if warnings:
        return "warned"
    if not damaged:
        return "intact"
    return "silent loss" if Counter(keys) != Counter(reference) else "silent damage"


@dataclass
class FuzzResult:
    outcomes: Counter[str] = field(default_factory=Counter)
    bad: list[str] = field(default_factory=list)


def fuzz(log: Path, work: Path, n: int, seed: int) -> FuzzResult:
    """Read `n` damaged variants of `log` (written under `work`) and tally their outcomes;
    `bad` lists each variant whose outcome is not allowed."""
    reference, _ = record_keys(log)
    data = log.read_bytes()
    result = FuzzResult()
    path = work / "variant.mcap"
    for i, v in enumerate(variants(data, n, seed)):
        path.write_bytes(v.data)
        outcome = read_variant(path, reference, damaged=v.data != data)
        result.outcomes[outcome.split(":")[0]] += 1
        if outcome.split(":")[0] in BAD_OUTCOMES or outcome == "silent damage":
            result.bad.append(f"variant {i} ({v.kind}, {v.detail}): {outcome}")
    return result
