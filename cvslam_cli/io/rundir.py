"""The run directory contract (DESIGN.md section 5): `<run>/run.yaml` and stage bookkeeping.

`run.yaml` records, per stage, the config sections the stage depends on (and their digest),
its inputs with SHA-256 checksums, its outputs, the cvslam version and when it finished.
Before a stage runs, `RunDir.plan` compares that record with the present config and inputs:

- nothing recorded, or `--force`: run;
- same config and same inputs, outputs present: skip (up to date);
- same config, inputs changed: run (the outputs are stale);
- a different config: refuse with one line naming the first key that differs, unless
  `--force` (outputs made with another config must not be silently mixed or replaced).

A run directory moves and is copied as a whole: input paths are recorded relative to it and
inputs are compared by checksum only, so a moved or copied run (with its logs, or with the
logs at the same relative place) is still up to date. The checksum is over the content that
matters: a CSV's timing columns (`TIMING_COLUMNS`: `timeline.csv` `ms`, the `t_*_s` of
`<vehicle>_stats.csv`) are left out, so a stage does not go stale because its predecessor ran
at another speed.

A stage that is going to replace recorded outputs first marks its record "running" with the
new config (`plan`), so an interrupted run, even one with `--force`, never leaves outputs
that a later run calls up to date: the next run with the same config redoes the stage.

One process at a time works on a run directory: `RunDir.session` takes an exclusive lock
(`flock` on `<run>/.lock`; a second process gets one line naming the holder) and copies the
log lines of the session to `<run>/cvslam.log`.

`run.yaml` is written atomically (`io/atomic.py`); its names come from `io/run_layout.py`.
"""

from __future__ import annotations

import collections
import contextlib
import csv
import fcntl
import hashlib
import io
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml

from cvslam_cli import __version__
from cvslam_cli.config import Config, to_dict
from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.io.run_layout import RunLayout
from cvslam_cli.io.textfiles import read_yaml_mapping

# Columns that hold how long something took, not what it computed: the only CSV columns whose
# values differ between two runs of the same inputs and config (fuse `timeline.csv`: `ms`;
# extract `<vehicle>_stats.csv`: the `t_*_s`). Left out of the content checksum.
TIMING_COLUMNS = frozenset(
    ("ms", "t_detect_s", "t_describe_s", "t_match_s", "t_triangulate_s", "t_total_s")
)


def file_sha256(path: Path) -> str:
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _csv_without_timing(text: str) -> str | None:
    """The CSV `text` without its `TIMING_COLUMNS`, or None when it has none."""
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or not TIMING_COLUMNS.intersection(rows[0]):
        return None
    keep = [k for k, name in enumerate(rows[0]) if name not in TIMING_COLUMNS]
    buf = io.StringIO()
    rows = [[r[k] for k in keep if k < len(r)] for r in rows]
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue()


def content_sha256(path: Path) -> str:
    """SHA-256 of what `path` holds that matters: its bytes, except that a CSV's
    `TIMING_COLUMNS` are left out; for a folder (a rosbag2 recording), of its files' names
    and checksums."""
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        listing = "".join(f"{p.relative_to(path)} {file_sha256(p)}\n" for p in files)
        return hashlib.sha256(listing.encode()).hexdigest()
    if path.suffix == ".csv":
        try:
            stripped = _csv_without_timing(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, csv.Error):
            stripped = None
        if stripped is not None:
            return hashlib.sha256(stripped.encode()).hexdigest()
    return file_sha256(path)


def relative_to_run(path: Path, run_dir: Path) -> str:
    """`path` as recorded in `run_dir`'s records: relative to the run directory."""
    return os.path.relpath(path.resolve(), run_dir.resolve())


def input_record(path: Path, run_dir: Path) -> dict[str, Any]:
    """How an input is recorded: its path relative to `run_dir`, size (a folder's: its
    files' summed) and content checksum."""
    size = (
        sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        if path.is_dir()
        else path.stat().st_size
    )
    return {"path": relative_to_run(path, run_dir), "size": size, "sha256": content_sha256(path)}


def config_digest(sections: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(sections, sort_keys=True).encode()).hexdigest()[:16]


def first_difference(old: Any, new: Any, prefix: str = "") -> str | None:
    """The first key path whose value differs, formatted `key: old -> new`."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        for key in sorted(set(old) | set(new), key=str):
            path = f"{prefix}.{key}" if prefix else str(key)
            if key not in old or key not in new:
                return f"{path}: {old.get(key, 'absent')!r} -> {new.get(key, 'absent')!r}"
            diff = first_difference(old[key], new[key], path)
            if diff:
                return diff
        return None
    return None if old == new else f"{prefix}: {old!r} -> {new!r}"


def _checksums(records: Sequence[Mapping[str, Any]]) -> collections.Counter[str]:
    """The inputs as compared for up-to-dateness: their checksums, not their paths."""
    return collections.Counter(r["sha256"] for r in records)


def _section(full: Mapping[str, Any], name: str) -> Any:
    """A config section by name, or one key of it by dotted name (`run.dataset`)."""
    node: Any = full
    for part in name.split("."):
        node = node[part]
    return node


@dataclass(frozen=True)
class StagePlan:
    action: Literal["run", "skip"]
    reason: str
    sections: dict[str, Any]
    inputs: list[dict[str, Any]]
    config: dict[str, Any]


class RunDir:
    def __init__(self, path: Path) -> None:
        self.path = path
        if path.exists() and not path.is_dir():
            raise CvslamError(f"{path}: exists and is not a directory")
        self.run_file = RunLayout(path).run_file

    def load(self) -> dict[str, Any]:
        if not self.run_file.exists():
            return {}
        return read_yaml_mapping(self.run_file, "a cvslam run record (run.yaml)", empty_ok=True)

    def plan(
        self,
        stage: str,
        cfg: Config,
        section_names: Sequence[str],
        inputs: Sequence[Path],
        outputs: Sequence[Path],
        force: bool,
    ) -> StagePlan:
        full = to_dict(cfg)
        sections = {name: _section(full, name) for name in section_names}
        records = [input_record(p, self.path) for p in inputs]
        done = self.load().get("stages", {}).get(stage)
        if done and not force:
            diff = first_difference(done.get("config", {}), sections)
            if diff:
                raise CvslamError(
                    f"{self.path}: {stage} was run with a different config ({diff}); "
                    "use --force to redo it with the new one"
                )
        if not done:
            reason = "not run yet"
        elif force:
            reason = "forced"
        elif _checksums(done.get("inputs", [])) != _checksums(records):
            reason = "inputs changed"
        elif done.get("status") != "complete" or not all(p.exists() for p in outputs):
            reason = "previous run incomplete"
        else:
            _log_plan(stage, "skipped", "up to date", records, section_names)
            return StagePlan("skip", "up to date", sections, records, full)
        if done:
            self._invalidate(stage, sections)
        _log_plan(stage, "runs", reason, records, section_names)
        return StagePlan("run", reason, sections, records, full)

    def _invalidate(self, stage: str, sections: dict[str, Any]) -> None:
        """Mark `stage` "running" with the config about to be used, before its outputs are
        replaced: if the run is interrupted, the next one with this config redoes it and one
        with the old config is refused."""
        data = self.load()
        data.setdefault("stages", {})[stage] = {
            "status": "running",
            "config_digest": config_digest(sections),
            "config": sections,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        write_text_atomic(self.run_file, yaml.safe_dump(data, sort_keys=False))

    def record(
        self,
        stage: str,
        plan: StagePlan,
        outputs: Sequence[Path],
        summary: Mapping[str, Any],
        wall_s: float,
    ) -> None:
        data = self.load()
        data["cvslam_version"] = __version__
        data["config"] = plan.config  # the resolved config of the latest stage run
        stages = data.setdefault("stages", {})
        stages[stage] = {
            "status": "complete",
            "config_digest": config_digest(plan.sections),
            "config": plan.sections,
            "inputs": plan.inputs,
            "outputs": [str(p.relative_to(self.path)) for p in outputs],
            "summary": dict(summary),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "wall_s": round(wall_s, 3),
            "cvslam_version": __version__,
        }
        write_text_atomic(self.run_file, yaml.safe_dump(data, sort_keys=False))

    @contextlib.contextmanager
    def session(self, command: str, *, create: bool = False) -> Iterator[None]:
        """Hold the run directory's lock and copy the log to `<run>/cvslam.log` while the
        block runs. Re-entrant within one process (`cvslam run` holds it for every stage).
        `create`: make the directory first (extract); otherwise a directory that does not
        exist is not locked (the stage's own error says what is missing)."""
        if create:
            with contextlib.suppress(OSError):  # the stage's own check says what is wrong
                self.path.mkdir(parents=True, exist_ok=True)
        if not self.path.is_dir() or not os.access(self.path, os.W_OK):
            # nothing can be written there, so nothing to race on: the stage's own check
            # names the folder and the problem
            yield
            return
        with _LOCKS.hold(self.path, RunLayout(self.path).lock_file) as first:
            if not first:
                yield
                return
            with _run_log(RunLayout(self.path).log_file, command):
                yield


class _LockTable:
    """The run directories this process holds, with how many sessions hold each."""

    def __init__(self) -> None:
        self._mutex = threading.Lock()
        self._held: dict[Path, tuple[int, int]] = {}  # resolved dir -> (fd, depth)

    @contextlib.contextmanager
    def hold(self, run_dir: Path, lock_file: Path) -> Iterator[bool]:
        """Yield True for the outermost hold of `run_dir` by this process, False inside it
        or where the lock file cannot be written (nor can anything else there)."""
        key = run_dir.resolve()
        with self._mutex:
            fd, depth = self._held.get(key, (-1, 0))
            if depth == 0:
                fd = _acquire(run_dir, lock_file)
            self._held[key] = (fd, depth + 1)
        try:
            yield depth == 0 and fd >= 0
        finally:
            with self._mutex:
                fd, depth = self._held.pop(key)
                if depth > 1:
                    self._held[key] = (fd, depth - 1)
                elif fd >= 0:
                    os.close(fd)  # releases the flock


_LOCKS = _LockTable()


def _acquire(run_dir: Path, lock_file: Path) -> int:
    """An open descriptor of `lock_file` holding its exclusive flock, with this process's
    id and host written in it; CvslamError naming the holder when another process has it."""
    try:
        fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return -1  # nothing can be written there: the stage's own check names the problem
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise CvslamError(
            f"{run_dir}: another cvslam process ({holder}) is working on this run directory; "
            "wait for it to finish"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
    return fd


def _log_plan(
    stage: str,
    action: str,
    reason: str,
    records: Sequence[Mapping[str, Any]],
    section_names: Sequence[str],
) -> None:
    """-v: whether a stage runs or is skipped, and why."""
    logging.getLogger("cvslam.rundir").debug(
        "%s %s (%s): %d input file(s) by checksum, config sections %s",
        stage,
        action,
        reason,
        len(records),
        ", ".join(section_names),
    )


@contextlib.contextmanager
def _run_log(path: Path, command: str) -> Iterator[None]:
    """Append the `cvslam` logger's lines (at its present level) to `path`, with times,
    between a line naming `command` and one saying how it ended."""
    logger = logging.getLogger("cvslam")
    try:
        handler = logging.FileHandler(path, encoding="utf-8")
    except OSError:  # the stage's own check names what cannot be written
        yield
        return
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    logger.addHandler(handler)
    started = time.perf_counter()
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    handler.stream.write(f"{stamp} START {command} (pid {os.getpid()})\n")
    outcome = "failed"
    try:
        yield
        outcome = "done"
    except CvslamError as exc:
        handler.stream.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')} ERROR {exc}\n")
        raise
    except BaseException as exc:
        outcome = f"stopped ({type(exc).__name__})"
        raise
    finally:
        elapsed = time.perf_counter() - started
        handler.stream.write(
            f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')} END {command}: {outcome} in {elapsed:.1f} s\n"
        )
        logger.removeHandler(handler)
        handler.close()
