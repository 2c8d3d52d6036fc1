"""The run directory contract (DESIGN.md section 5): `<run>/run.yaml` and stage bookkeeping.

`run.yaml` records, per stage, the config sections the stage depends on (and their digest),
its inputs with SHA-256 checksums, its outputs, the cvslam version and when it finished.
Before a stage runs, `RunDir.plan` compares that record with the present config and inputs:

- nothing recorded, or `--force`: run;
- same config and same inputs, outputs present: skip (up to date);
- same config, inputs changed: run (the outputs are stale);
- a different config: refuse with one line naming the first key that differs, unless
  `--force` (outputs made with another config must not be silently mixed or replaced).

`run.yaml` is written atomically (`io/atomic.py`); its name comes from `io/run_layout.py`.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Mapping, Sequence
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


def file_sha256(path: Path) -> str:
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def input_record(path: Path) -> dict[str, Any]:
    if path.is_dir():  # a rosbag2 folder: its files' names and checksums, summed sizes
        files = sorted(p for p in path.rglob("*") if p.is_file())
        listing = "".join(f"{p.relative_to(path)} {file_sha256(p)}\n" for p in files)
        digest = hashlib.sha256(listing.encode()).hexdigest()
        return {
            "path": str(path.resolve()),
            "size": sum(p.stat().st_size for p in files),
            "sha256": digest,
        }
    return {"path": str(path.resolve()), "size": path.stat().st_size, "sha256": file_sha256(path)}


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
        sections = {name: full[name] for name in section_names}
        records = [input_record(p) for p in inputs]
        done = self.load().get("stages", {}).get(stage)
        if force or not done:
            return StagePlan(
                "run", "forced" if force and done else "not run yet", sections, records, full
            )
        diff = first_difference(done.get("config", {}), sections)
        if diff:
            raise CvslamError(
                f"{self.path}: {stage} was run with a different config ({diff}); "
                "use --force to redo it with the new one"
            )
        old_inputs = {(r["path"], r["sha256"]) for r in done.get("inputs", [])}
        new_inputs = {(r["path"], r["sha256"]) for r in records}
        if old_inputs != new_inputs:
            return StagePlan("run", "inputs changed", sections, records, full)
        if done.get("status") != "complete" or not all(p.exists() for p in outputs):
            return StagePlan("run", "previous run incomplete", sections, records, full)
        return StagePlan("skip", "up to date", sections, records, full)

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
