"""Many recipes at once: serially in this process, or as tasks on a Dask cluster
(`cvslam_cli/cluster.py`), each recipe one task (`execute.run_recipe`).

A recipe that fails (a corrupt log, a bad key, a worker that died) is reported as soon as it
ends and the others go on; the results come back in the recipes' order. Tasks run the same
command lines as the serial run, so their outputs are the same files, byte for byte (up to
the timing columns and times that `io/rundir.py` lists).
"""

from __future__ import annotations

import contextlib
import functools
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from cvslam_cli.batch.execute import RecipeResult, make_sources, run_recipe
from cvslam_cli.batch.recipe import Recipe, RecipeSteps, recipe_steps
from cvslam_cli.cluster import cluster
from cvslam_cli.errors import CvslamError

Report = Callable[[RecipeResult, int, int], None]  # (result, finished so far, total)


def plan_batch(
    recipes: Sequence[Recipe], runs_dir: Path, generated_dir: Path, *, workers: int
) -> list[RecipeSteps]:
    """The steps of every recipe, with absolute paths (workers may run elsewhere); one run
    directory per recipe name."""
    seen: dict[str, Path] = {}
    for r in recipes:
        if r.name in seen:
            raise CvslamError(
                f"{r.path}: a recipe named {r.name!r} is given twice ({seen[r.name]}); "
                "recipes need distinct names (their run directories)"
            )
        seen[r.name] = r.path
    runs, gen = runs_dir.absolute(), generated_dir.absolute()
    return [recipe_steps(r, runs, gen, workers=workers) for r in recipes]


RunMany = Callable[[Sequence[RecipeSteps], Report], list[RecipeResult]]


@contextlib.contextmanager
def executor(serial: bool, scheduler: str | None, local_workers: int | None) -> Iterator[RunMany]:
    """A function running a list of recipes (several times, e.g. the trials of a search):
    serially in this process, or on one Dask cluster kept for the block."""
    if serial:
        yield _run_serially
        return
    with cluster(scheduler, local_workers) as client:
        yield functools.partial(_run_on_cluster, client)


def run_batch(
    steps: Sequence[RecipeSteps],
    *,
    serial: bool,
    scheduler: str | None,
    local_workers: int | None,
    report: Report,
) -> list[RecipeResult]:
    """Run every recipe; `report` is called as each one ends."""
    with executor(serial, scheduler, local_workers) as run_many:
        return run_many(steps, report)


def _run_serially(steps: Sequence[RecipeSteps], report: Report) -> list[RecipeResult]:
    results = []
    for s in steps:
        results.append(run_recipe(s))
        report(results[-1], len(results), len(steps))
    return results


def _run_on_cluster(
    client: Any, steps: Sequence[RecipeSteps], report: Report
) -> list[RecipeResult]:
    from distributed import as_completed

    results: dict[int, RecipeResult] = {}
    token = uuid.uuid4().hex[:8]
    index = {}
    made: dict[Path, str] = {}  # generated folder -> "" or why it could not be made
    for k, s in enumerate(steps):
        shared = sum(x.generated_dir == s.generated_dir for x in steps) > 1
        if shared and s.generated_dir not in made:
            # logs shared by several recipes (a sweep's points) are made once, first
            try:
                make_sources(s)
                made[s.generated_dir] = ""
            except CvslamError as exc:
                made[s.generated_dir] = str(exc)
        if made.get(s.generated_dir):
            results[k] = RecipeResult(s.recipe.name, str(s.run_dir), made[s.generated_dir], 0)
            report(results[k], len(results), len(steps))
            continue
        future = client.submit(run_recipe, s, key=f"cvslam-{s.recipe.name}-{token}", pure=False)
        index[future] = k
    for future in as_completed(index):
        k = index[future]
        try:
            result = future.result()
        except Exception as exc:  # the worker died or the task could not run
            s = steps[k]
            error = f"task failed: {type(exc).__name__}: {exc}"
            result = RecipeResult(s.recipe.name, str(s.run_dir), error, 0.0)
        results[k] = result
        report(result, len(results), len(steps))
    return [results[k] for k in range(len(steps))]
