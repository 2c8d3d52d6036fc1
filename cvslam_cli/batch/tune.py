"""`cvslam tune RECIPE... --param KEY=LOW:HIGH[:log|:int]`: an Optuna search for the config
values that minimise the ATE on a set of recipes.

Each trial is a set of values (Optuna's TPE sampler, seeded) run on every recipe, each run in
its own directory `<recipe>__trial<NNN>` (the logs are made once and shared); its objective is
the mean `ate_rmse_m` of the chosen estimate (default: the cooperative NH-infinity run) over
every recipe and vehicle, read from the runs' `eval/metrics.csv`. A trial in which a recipe
fails (a diverging filter, say) is recorded as failed and the search goes on. The trials
(values, objective, state) go to `<out>_trials.csv`, the complete trials' runs to the
summary `<out>.csv` / `.html`.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cvslam_cli.batch.execute import RecipeResult
from cvslam_cli.batch.recipe import Recipe
from cvslam_cli.batch.runner import Report, RunMany, plan_batch
from cvslam_cli.errors import ConfigError, CvslamError
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.io.run_layout import RunLayout


@dataclass(frozen=True)
class Param:
    """One searched config key: values in [low, high], on a log scale or integers."""

    key: str
    low: float
    high: float
    scale: str  # "linear", "log" or "int"

    def suggest(self, trial: Any) -> float | int:
        if self.scale == "int":
            return int(trial.suggest_int(self.key, int(self.low), int(self.high)))
        return float(trial.suggest_float(self.key, self.low, self.high, log=self.scale == "log"))


def parse_param(text: str) -> Param:
    """`KEY.PATH=LOW:HIGH[:log|:int]`; ConfigError naming a malformed one."""
    key, sep, spec = text.partition("=")
    parts = spec.split(":") if sep else []
    scale = parts.pop() if len(parts) == 3 else "linear"
    try:
        low, high = (float(x) for x in parts)
    except ValueError:
        low = high = math.nan
    if not key.strip() or len(parts) != 2 or scale not in ("linear", "log", "int"):
        raise ConfigError(f"--param {text}: expected KEY.PATH=LOW:HIGH[:log|:int]")
    if not (math.isfinite(low) and math.isfinite(high) and low < high) or (
        scale == "log" and low <= 0
    ):
        raise ConfigError(f"--param {text}: need finite LOW < HIGH (and LOW > 0 for :log)")
    return Param(key.strip(), low, high, scale)


def objective(results: Sequence[RecipeResult], estimate: str) -> float:
    """The mean ATE RMSE of `estimate` over the runs' vehicles (NaN when no row has it)."""
    import pandas as pd

    values = []
    for r in results:
        metrics = pd.read_csv(RunLayout(Path(r.run_dir)).eval.metrics_csv)
        values += list(metrics.loc[metrics["estimate"] == estimate, "ate_rmse_m"])
    return float(sum(values) / len(values)) if values else math.nan


@dataclass(frozen=True)
class TuneResult:
    best: dict[str, float | int] | None
    best_value: float
    trials_csv: Path
    run_dirs: list[Path]


def tune(
    recipes: Sequence[Recipe],
    params: Sequence[Param],
    *,
    trials: int,
    estimate: str,
    seed: int,
    runs_dir: Path,
    generated_dir: Path,
    workers: int,
    run_many: RunMany,
    report: Report,
    out: Path,
) -> TuneResult:
    """Run the search (module docstring); `run_many` runs one trial's recipes."""
    try:
        import optuna
    except ImportError:
        raise CvslamError("cvslam tune needs Optuna: pip install optuna") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize", sampler=optuna.samplers.TPESampler(seed=seed))
    rows: list[dict[str, Any]] = []
    run_dirs: list[Path] = []
    for number in range(trials):
        trial = study.ask()
        values = {p.key: p.suggest(trial) for p in params}
        overrides = [f"{k}={v!r}" for k, v in values.items()]
        points = [r.with_overrides(f"{r.name}__trial{number:03d}", overrides) for r in recipes]
        results = run_many(plan_batch(points, runs_dir, generated_dir, workers=workers), report)
        failed = [r for r in results if not r.ok]
        value = math.nan if failed else objective(results, estimate)
        if failed or math.isnan(value):
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            state = (
                "failed: " + "; ".join(r.error for r in failed) if failed else "no such estimate"
            )
        else:
            study.tell(trial, value)
            state = "complete"
            run_dirs += [Path(r.run_dir) for r in results]
        rows.append({"trial": number, **values, "mean_ate_rmse_m": value, "state": state})
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    trials_csv = out.with_name(out.name + "_trials.csv")
    write_text_atomic(trials_csv, buf.getvalue())
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not done:
        return TuneResult(None, math.nan, trials_csv, run_dirs)
    return TuneResult(dict(study.best_params), float(study.best_value), trials_csv, run_dirs)
