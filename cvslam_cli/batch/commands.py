"""The commands over many runs: `cvslam batch`, `cvslam summary`, `cvslam sweep` (thin click
commands over `runner.py`, `summary.py`, `sweep.py`; registered in `cli.py`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import click

from cvslam_cli.batch.execute import RecipeResult
from cvslam_cli.batch.recipe import Recipe, load_recipe
from cvslam_cli.batch.runner import plan_batch, run_batch
from cvslam_cli.batch.sweep import sweep_recipes
from cvslam_cli.errors import CvslamError

log = logging.getLogger("cvslam")

_RECIPES = click.argument(
    "recipes", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path)
)


def _folder_option(name: str, default: str, help_text: str) -> Callable[..., Any]:
    return click.option(
        name,
        f"{name[2:]}_dir",
        default=Path(default),
        show_default=True,
        type=click.Path(file_okay=False, path_type=Path),
        metavar="DIR",
        help=help_text,
    )


def _cluster_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Where the runs go: `--scheduler ADDRESS`, `--local-workers N` or `--serial`; where
    their files go: `--runs DIR`, `--generated DIR`; `--stage-workers N`."""
    for option in reversed(
        [
            click.option(
                "--scheduler",
                metavar="ADDRESS",
                default=None,
                help="Run on the Dask cluster whose scheduler is at ADDRESS (tcp://host:8786; "
                "docs/batch.md).",
            ),
            click.option(
                "--local-workers",
                type=click.IntRange(min=1),
                default=None,
                metavar="N",
                help="Run on a local Dask cluster of N worker processes (default: one per core).",
            ),
            click.option(
                "--serial",
                is_flag=True,
                help="Run the recipes one after another in this process (no Dask).",
            ),
            _folder_option("--runs", "runs", "Run directories go in DIR/<recipe name>."),
            _folder_option(
                "--generated",
                "datasets/generated",
                "Imported and simulated logs go in DIR/<dataset>/ (not in git).",
            ),
            click.option(
                "--stage-workers",
                type=click.IntRange(min=1),
                default=1,
                show_default=True,
                help="Processes per stage of one recipe (extract, simulate); with Dask the "
                "parallelism is across recipes.",
            ),
        ]
    ):
        func = option(func)
    return func


def _summary_option(*names: str) -> Callable[..., Any]:
    """A FILE option naming where a summary goes (`names`: the option's names, then its
    help)."""
    *decls, help_text = names
    return click.option(
        *decls, default=None, type=click.Path(dir_okay=False, path_type=Path), help=help_text
    )


def _check_cluster_choice(scheduler: str | None, local_workers: int | None, serial: bool) -> None:
    if sum((scheduler is not None, local_workers is not None, serial)) > 1:
        raise click.UsageError("give at most one of --scheduler, --local-workers, --serial")


def _report(result: RecipeResult, done: int, total: int) -> None:
    if result.ok:
        log.info("[%d/%d] %s: done in %.1f s (%s)", done, total, result.name, result.wall_s,
                 result.run_dir)  # fmt: skip
    else:
        log.error("[%d/%d] %s failed: %s", done, total, result.name, result.error)


def _run_all(recipes: Sequence[Recipe], opts: dict[str, Any]) -> list[RecipeResult]:
    """Run the recipes with the cluster options."""
    _check_cluster_choice(opts["scheduler"], opts["local_workers"], opts["serial"])
    steps = plan_batch(
        recipes, opts["runs_dir"], opts["generated_dir"], workers=opts["stage_workers"]
    )
    results = run_batch(
        steps,
        serial=opts["serial"],
        scheduler=opts["scheduler"],
        local_workers=opts["local_workers"],
        report=_report,
    )
    return results


def _fail_if_any_failed(results: Sequence[RecipeResult]) -> None:
    """CvslamError naming the recipes that failed (each was reported as it ended)."""
    failed = [r for r in results if not r.ok]
    if failed:
        raise CvslamError(
            f"{len(failed)} of {len(results)} recipe(s) failed: "
            + ", ".join(f"{r.name} (log: {r.run_dir}/cvslam.log)" for r in failed)
        )


@click.command()
@_RECIPES
@_cluster_options
@_summary_option(
    "--summary", "summary_out", "Also write the summary of the runs (FILE.csv, FILE.html)."
)
def batch(recipes: tuple[Path, ...], summary_out: Path | None, **opts: Any) -> None:
    """Run every RECIPE (datasets/*.yaml): make its logs, then every stage, on a Dask cluster
    (default: a local one sized to the machine) or --serial.

    Each recipe's run goes to RUNS/<name>; what is up to date is skipped. A recipe that
    fails is reported and the others finish; the exit status is 1 if any failed.
    """
    results = _run_all([load_recipe(r) for r in recipes], opts)
    if summary_out is not None:
        _summary([Path(r.run_dir) for r in results if r.ok], summary_out)
    _fail_if_any_failed(results)


def _summary(run_dirs: Sequence[Path], out: Path) -> None:
    from cvslam_cli.batch.summary import write_summary  # pandas, matplotlib: only when used

    if not run_dirs:
        return
    files = write_summary(run_dirs, out)
    log.info("summary of %d run(s), %d rows: %s, %s", len(run_dirs), files.rows, files.csv,
             files.html)  # fmt: skip


@click.command()
@click.argument(
    "run_dirs", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path)
)
@click.option(
    "-o",
    "--output",
    default=Path("runs/summary"),
    show_default=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write OUTPUT.csv and OUTPUT.html.",
)
def summary(run_dirs: tuple[Path, ...], output: Path) -> None:
    """One table across RUN_DIR... (run, dataset, vehicle, estimate, ATE/RPE/drift/NEES,
    time, real-time factor) as CSV, and an HTML page comparing them with links to each
    run's report."""
    _summary(list(run_dirs), output)


@click.command()
@click.argument("recipe", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--grid",
    "grid",
    multiple=True,
    required=True,
    metavar="KEY.PATH=V1,V2,...",
    help="One axis of the grid: a config key and its values (repeatable; the grid is the "
    "product of the axes).",
)
@_cluster_options
@_summary_option(
    "-o", "--output", "The summary (OUTPUT.csv, OUTPUT.html); default RUNS/<recipe>_sweep."
)
def sweep(recipe: Path, grid: tuple[str, ...], output: Path | None, **opts: Any) -> None:
    """Run RECIPE at every point of the --grid (each point a run directory named by its
    overrides, RUNS/<recipe>__KEY=V...) and write their summary."""
    base = load_recipe(recipe)
    results = _run_all(sweep_recipes(base, grid), opts)
    out = output or opts["runs_dir"] / f"{base.name}_sweep"
    _summary([Path(r.run_dir) for r in results if r.ok], out)
    _fail_if_any_failed(results)


@click.command()
@_RECIPES
@click.option(
    "--param",
    "params",
    multiple=True,
    required=True,
    metavar="KEY.PATH=LOW:HIGH[:log|:int]",
    help="A config key to search and its range (repeatable).",
)
@click.option("--trials", type=click.IntRange(min=1), default=20, show_default=True)
@click.option(
    "--estimate",
    default="cooperative NH-inf",
    show_default=True,
    help="The estimate whose mean ATE RMSE (over recipes and vehicles) is minimised.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="The sampler's seed.")
@_cluster_options
@_summary_option(
    "-o",
    "--output",
    "OUTPUT_trials.csv (values, objective) and the summary OUTPUT.csv/.html; default RUNS/tune.",
)
def tune(
    recipes: tuple[Path, ...],
    params: tuple[str, ...],
    trials: int,
    estimate: str,
    seed: int,
    output: Path | None,
    **opts: Any,
) -> None:
    """Search config values minimising the ATE on RECIPE... (Optuna, TPE): each trial runs
    every recipe with its values (RUNS/<recipe>__trialNNN) on the cluster or --serial."""
    from cvslam_cli.batch.runner import executor
    from cvslam_cli.batch.tune import parse_param
    from cvslam_cli.batch.tune import tune as search

    _check_cluster_choice(opts["scheduler"], opts["local_workers"], opts["serial"])
    loaded = [load_recipe(r) for r in recipes]
    parsed = [parse_param(p) for p in params]
    out = output or opts["runs_dir"] / "tune"
    with executor(opts["serial"], opts["scheduler"], opts["local_workers"]) as run_many:
        result = search(
            loaded,
            parsed,
            trials=trials,
            estimate=estimate,
            seed=seed,
            runs_dir=opts["runs_dir"],
            generated_dir=opts["generated_dir"],
            workers=opts["stage_workers"],
            run_many=run_many,
            report=_report,
            out=out,
        )
    _summary(result.run_dirs, out)
    log.info("trials: %s", result.trials_csv)
    if result.best is None:
        raise CvslamError(f"cvslam tune: every trial failed (see {result.trials_csv})")
    best = ", ".join(f"{k}={v:.6g}" for k, v in result.best.items())
    click.echo(f"best: {best} (mean ATE RMSE of {estimate}: {result.best_value:.4f} m)")


COMMANDS = (batch, summary, sweep, tune)
