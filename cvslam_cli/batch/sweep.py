"""`cvslam sweep RECIPE --grid KEY=V1,V2,...`: a parameter study as a batch of runs.

Every point of the grid (the product of the `--grid` axes) is the recipe with that point's
overrides after its own, run in its own run directory named by them
(`<recipe>__<key>=<value>__...`); the logs are made once and shared. The summary of all
points (`batch/summary.py`) is the study's result.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Sequence

from cvslam_cli.batch.recipe import Recipe
from cvslam_cli.errors import ConfigError

_UNSAFE = re.compile(r"[^A-Za-z0-9._=+-]")


def grid_axes(grid: Sequence[str]) -> list[tuple[str, list[str]]]:
    """`KEY=V1,V2,...` per axis -> (key, values); ConfigError naming a malformed one."""
    axes: list[tuple[str, list[str]]] = []
    for text in grid:
        key, sep, values = text.partition("=")
        items = [v.strip() for v in values.split(",")] if sep else []
        if not key.strip() or not items or not all(items):
            raise ConfigError(f"--grid {text}: expected KEY.PATH=V1,V2,...")
        if any(key.strip() == k for k, _ in axes):
            raise ConfigError(f"--grid {text}: {key.strip()} is given twice")
        axes.append((key.strip(), items))
    if not axes:
        raise ConfigError("cvslam sweep: give at least one --grid KEY.PATH=V1,V2,...")
    return axes


def point_name(base: str, point: Sequence[tuple[str, str]]) -> str:
    """The run directory name of a grid point, safe as a file name."""
    return "__".join([base, *(_UNSAFE.sub("_", f"{k}={v}") for k, v in point)])


def sweep_recipes(recipe: Recipe, grid: Sequence[str]) -> list[Recipe]:
    """One recipe per grid point, in grid order (the last axis varying fastest)."""
    axes = grid_axes(grid)
    points = itertools.product(*([(k, v) for v in values] for k, values in axes))
    out = []
    for point in points:
        overrides = [f"{k}={v}" for k, v in point]
        out.append(recipe.with_overrides(point_name(recipe.name, point), overrides))
    return out
