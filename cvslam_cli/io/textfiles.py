"""Reading text and YAML files the user gives, with one-line errors naming the file.

Every text input (config and scenario files, run.yaml, dataset tables, trajectories, map
CSVs) is read here, so a missing file, a folder, bytes that are not UTF-8 or malformed YAML
read the same everywhere: `<path>: <what was wrong>, expected <what the file should be>`.
`error` is the `CvslamError` subclass the caller reports with (`ConfigError` for config
files, `DatasetError` for an importer's input). Stamp tables are checked for time order with
`check_stamps_increasing`, one message naming the file and the offending line.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cvslam_cli.errors import CvslamError
from cvslam_cli.records.arrays import first_not_increasing


def read_text(path: Path, what: str, error: type[CvslamError] = CvslamError) -> str:
    """The UTF-8 text of the file `path` (`what` it should hold, for the messages)."""
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: not found, expected {what}") from None
    except IsADirectoryError:
        raise error(f"{path}: is not a file, expected {what}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: is not a UTF-8 text file, expected {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or exc}), expected {what}") from None


def read_yaml_mapping(
    path: Path, what: str, error: type[CvslamError] = CvslamError, *, empty_ok: bool = False
) -> dict[str, Any]:
    """A YAML file holding a mapping (an empty file gives {} when `empty_ok`). An OpenCV
    `%YAML:1.0` first line (rejected by PyYAML) is dropped; line numbers count it."""
    text = read_text(path, what, error)
    skipped = 0
    if text.startswith("%YAML:"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
        skipped = 1
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1 + skipped}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or exc
        raise error(f"{path}: not valid YAML{where} ({problem}), expected {what}") from None
    if data is None and empty_ok:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: expected a YAML mapping ({what}), got {type(data).__name__}")
    return data


def data_lines(text: str) -> Iterator[tuple[int, str]]:
    """(1-based line number, stripped line) of the non-blank lines not starting with '#'."""
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield no, s


def finite_floats(fields: list[str]) -> list[float]:
    """The fields as floats; ValueError when one is not a number or not finite."""
    values = [float(f) for f in fields]
    if not all(np.isfinite(values)):
        raise ValueError("not finite")
    return values


def ns_to_seconds_text(stamp_ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond stamp ("1403715273.262142976")."""
    sign = "-" if stamp_ns < 0 else ""
    sec, ns = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{sec}.{ns:09d}"


_NS_PER_S = Decimal(1_000_000_000)


def seconds_text_to_ns(text: str) -> int:
    """Decimal seconds as text ("1403715273.262142976", "1.5e-3") -> integer nanoseconds,
    rounded half to even, without going through a float. ValueError when not finite."""
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"not a number: {text!r}") from None
    if not value.is_finite():
        raise ValueError(f"not a finite number: {text!r}")
    return int((value * _NS_PER_S).to_integral_value(rounding=ROUND_HALF_EVEN))


def check_stamps_increasing(
    path: Path,
    stamps_ns: Sequence[int] | np.ndarray,
    line_nos: Sequence[int],
    error: type[CvslamError] = CvslamError,
) -> None:
    """`error` naming the file and line of the first stamp that is not later than the one
    before; `line_nos[k]` is the line stamp k was read from."""
    k = first_not_increasing(np.asarray(stamps_ns, dtype=np.int64))
    if k is not None:
        raise error(
            f"{path}: line {line_nos[k]}: timestamp {ns_to_seconds_text(int(stamps_ns[k]))} s "
            f"does not increase (previous {ns_to_seconds_text(int(stamps_ns[k - 1]))} s, "
            f"line {line_nos[k - 1]})"
        )
