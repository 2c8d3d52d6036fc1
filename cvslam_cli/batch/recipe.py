"""Dataset recipes (`datasets/*.yaml`): where a dataset's logs come from and how it is run.

A recipe is one run: one dataset, or one mission of several logs (a cooperative run over all
its vehicles). It says

- `logs`: a list of sources, each one of
  `{file: PATH[, vehicle: NAME]}` (a log: MCAP, rosbag2 folder, .db3, ROS 1 .bag; bound to
  vehicle NAME as `NAME=PATH` on the command line when given),
  `{import: euroc|kitti, path: DIR, vehicle: NAME[, rate_hz: HZ]}` (`cvslam import`),
  `{simulate: SCENARIO[, seed: N][, duration_s: S][, set: [KEY=VALUE, ...]]}` (`cvslam simulate`);
- `config`: config files, `set`: `KEY.PATH=VALUE` overrides (as on the command line);
- `vehicles`: optional `logs.vehicles` settings (name -> kind, topics, rig);
- `ground_truth`: optional `--gt` entries (FILE or VEHICLE=FILE; default the logs' topic);
- `comparisons`, `mosaic`: optional `run.comparisons` / `run.mosaic`.

Paths are relative to the recipe file; `{shared_data}` stands for the real-data folder
(`$CVSLAM_SHARED_DATA`, else `../shared/data` beside the project). `RecipeSteps` turns a
recipe into the cvslam command lines that make it: one per generated source (written under
the generated folder, never into git), then `cvslam run` into `<runs>/<name>`. The recipe's
name (its file name) is the run's `run.dataset`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cvslam_cli.errors import ConfigError
from cvslam_cli.io.textfiles import read_yaml_mapping

RECIPE_FILE = "a dataset recipe (see datasets/README.md)"
_KEYS = {
    *("description", "logs", "config", "set", "vehicles", "ground_truth", "comparisons"),
    "mosaic",
}
_SOURCE_KEYS = {
    "file": {"file", "vehicle"},
    "import": {"import", "path", "vehicle", "rate_hz"},
    "simulate": {"simulate", "seed", "duration_s", "set"},
}
_IMPORT_FORMATS = ("euroc", "kitti")


def shared_data_dir() -> Path:
    """The real-data folder: `$CVSLAM_SHARED_DATA`, else `../shared/data` beside the
    project (the folder holding `datasets/`)."""
    env = os.environ.get("CVSLAM_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent.parent.parent / "shared" / "data"


@dataclass(frozen=True)
class LogSource:
    """One source of logs. `kind`: file, import or simulate; `target`: the file, the
    dataset folder or the scenario; `options`: the other keys of the entry."""

    kind: str
    target: str
    options: Mapping[str, Any]


@dataclass(frozen=True)
class Recipe:
    """A parsed recipe file; paths already resolved against its folder. `name`: its run
    directory's; `dataset`: what it is a run of (both the file's name, except for the
    points of a sweep)."""

    path: Path
    name: str
    dataset: str
    description: str
    logs: tuple[LogSource, ...]
    config_files: tuple[Path, ...]
    overrides: tuple[str, ...]
    ground_truth: tuple[str, ...]

    def with_overrides(self, name: str, extra: Sequence[str]) -> Recipe:
        """The same recipe named `name`, with `extra` overrides after its own (a sweep's
        grid point)."""
        return Recipe(
            self.path,
            name,
            self.dataset,
            self.description,
            self.logs,
            self.config_files,
            (*self.overrides, *extra),
            self.ground_truth,
        )


def _fail(path: Path, key: str, what: str) -> ConfigError:
    return ConfigError(f"{path}: {key}: {what}")


def _strings(path: Path, key: str, value: Any) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise _fail(path, key, f"expected a list of strings, got {value!r}")
    return tuple(value)


def _expand(text: str, base: Path) -> str:
    """`text` with `{shared_data}` replaced; a relative path made relative to `base`."""
    text = text.replace("{shared_data}", str(shared_data_dir()))
    p = Path(text)
    return os.path.normpath(p if p.is_absolute() else base / p)


def _source(path: Path, k: int, entry: Any) -> LogSource:
    where = f"logs[{k}]"
    if not isinstance(entry, dict):
        raise _fail(path, where, "expected a mapping with one of file, import, simulate")
    kinds = [kind for kind in _SOURCE_KEYS if kind in entry]
    if len(kinds) != 1:
        raise _fail(path, where, "expected exactly one of file, import, simulate")
    kind = kinds[0]
    unknown = sorted(set(entry) - _SOURCE_KEYS[kind])
    if unknown:
        allowed = ", ".join(sorted(_SOURCE_KEYS[kind]))
        raise _fail(path, f"{where}.{unknown[0]}", f"unknown key (a {kind} entry has {allowed})")
    base = path.absolute().parent
    options = {key: v for key, v in entry.items() if key != kind}
    if kind == "import":
        if entry["import"] not in _IMPORT_FORMATS:
            raise _fail(path, f"{where}.import", f"expected one of {_IMPORT_FORMATS}")
        for key in ("path", "vehicle"):
            if not isinstance(entry.get(key), str):
                raise _fail(path, f"{where}.{key}", "expected a string")
        options["path"] = _expand(entry["path"], base)
        return LogSource(kind, entry["import"], options)
    if not isinstance(entry[kind], str):
        raise _fail(path, f"{where}.{kind}", "expected a string")
    if kind == "file":
        if "vehicle" in options and not isinstance(options["vehicle"], str):
            raise _fail(path, f"{where}.vehicle", "expected a string")
        return LogSource(kind, _expand(entry["file"], base), options)
    if "seed" in options and not isinstance(options["seed"], int):
        raise _fail(path, f"{where}.seed", "expected an integer")
    options["set"] = _strings(path, f"{where}.set", options.get("set"))
    scenario = entry["simulate"]
    target = _expand(scenario, base) if scenario.endswith((".yaml", ".yml")) else scenario
    return LogSource(kind, target, options)


def load_recipe(path: Path) -> Recipe:
    """Read and check a recipe file; ConfigError naming the file and key otherwise."""
    raw = read_yaml_mapping(path, RECIPE_FILE, ConfigError)
    unknown = sorted(set(raw) - _KEYS)
    if unknown:
        raise _fail(path, unknown[0], f"unknown key (expected {', '.join(sorted(_KEYS))})")
    entries = raw.get("logs")
    if not isinstance(entries, list) or not entries:
        raise _fail(path, "logs", "expected a non-empty list of log sources")
    logs = tuple(_source(path, k, e) for k, e in enumerate(entries))
    overrides = list(_strings(path, "set", raw.get("set")))
    if raw.get("vehicles") is not None:
        if not isinstance(raw["vehicles"], dict):
            raise _fail(path, "vehicles", "expected a mapping of vehicle name -> settings")
        overrides.append(f"logs.vehicles={json.dumps(raw['vehicles'])}")
    if raw.get("comparisons") is not None:
        comparisons = _strings(path, "comparisons", raw["comparisons"])
        overrides.append(f"run.comparisons={json.dumps(list(comparisons))}")
    if raw.get("mosaic") is not None:
        if not isinstance(raw["mosaic"], bool):
            raise _fail(path, "mosaic", "expected true or false")
        overrides.append(f"run.mosaic={json.dumps(raw['mosaic'])}")
    return Recipe(
        path=path,
        name=path.stem,
        dataset=path.stem,
        description=str(raw.get("description", "")).strip(),
        logs=logs,
        config_files=tuple(
            Path(_expand(c, path.absolute().parent))
            for c in _strings(path, "config", raw.get("config"))
        ),
        overrides=tuple(overrides),
        ground_truth=tuple(
            _gt_entry(g, path.absolute().parent)
            for g in _strings(path, "ground_truth", raw.get("ground_truth"))
        ),
    )


def _gt_entry(entry: str, base: Path) -> str:
    """A `--gt` entry with its file resolved: `VEHICLE=FILE` keeps the vehicle."""
    vehicle, sep, file = entry.partition("=")
    if sep and "/" not in vehicle:
        return f"{vehicle}={_expand(file, base)}"
    return _expand(entry, base)


@dataclass(frozen=True)
class SourceStep:
    """A cvslam command line that makes logs (`import`, `simulate`) and the logs it makes:
    `log` (a file) or, for the simulator, the folder `out` of one log per vehicle."""

    argv: tuple[str, ...]
    out: Path
    makes_folder: bool

    def logs(self) -> list[Path]:
        return sorted(self.out.glob("*.mcap")) if self.makes_folder else [self.out]


@dataclass(frozen=True)
class RecipeSteps:
    """The cvslam command lines that make a recipe's run: `sources`, then `run_argv()`
    (`cvslam run` on every log, made or given, into `run_dir`)."""

    recipe: Recipe
    run_dir: Path
    generated_dir: Path
    sources: tuple[SourceStep, ...]
    inputs: tuple[SourceStep | Path, ...]  # in the recipe's order
    workers: int

    def run_argv(self) -> list[str]:
        """`cvslam run` over the logs (the simulators' listed once they exist)."""
        logs = [
            str(p) for i in self.inputs for p in (i.logs() if isinstance(i, SourceStep) else [i])
        ]
        argv = ["run", *logs, "-o", str(self.run_dir), "--workers", str(self.workers)]
        for c in self.recipe.config_files:
            argv += ["--config", str(c)]
        for s in (*self.recipe.overrides, f"run.dataset={json.dumps(self.recipe.dataset)}"):
            argv += ["--set", s]
        for g in self.recipe.ground_truth:
            argv += ["--gt", g]
        return argv


def recipe_steps(
    recipe: Recipe, runs_dir: Path, generated_dir: Path, *, workers: int = 1
) -> RecipeSteps:
    """The steps of `recipe` with its run in `runs_dir/<name>` and its generated logs in
    `generated_dir/<dataset>/` (shared by the points of a sweep); `workers`: processes per
    stage."""
    gen = generated_dir / recipe.dataset
    sources: list[SourceStep] = []
    inputs: list[SourceStep | Path] = []
    for k, src in enumerate(recipe.logs):
        if src.kind == "file":  # bound to a vehicle: NAME=PATH, as on the command line
            vehicle = src.options.get("vehicle")
            inputs.append(Path(f"{vehicle}={src.target}" if vehicle else src.target))
            continue
        if src.kind == "import":
            out = gen / f"{src.options['vehicle']}.mcap"
            argv = ["import", src.target, src.options["path"], "-o", str(out)]
            argv += ["--vehicle", src.options["vehicle"]]
            if "rate_hz" in src.options:
                argv += ["--rate-hz", str(src.options["rate_hz"])]
            step = SourceStep(tuple(argv), out, makes_folder=False)
        else:
            out = gen / (f"sim{k}" if k else "sim")
            argv = ["simulate", src.target, "-o", str(out), "--workers", str(workers)]
            if "seed" in src.options:
                argv += ["--seed", str(src.options["seed"])]
            if "duration_s" in src.options:
                argv += ["--duration", str(src.options["duration_s"])]
            for s in src.options["set"]:
                argv += ["--set", s]
            step = SourceStep(tuple(argv), out, makes_folder=True)
        sources.append(step)
        inputs.append(step)
    return RecipeSteps(recipe, runs_dir / recipe.name, gen, tuple(sources), tuple(inputs), workers)
