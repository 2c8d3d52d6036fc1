"""One recipe's run, start to end, in this process: the task `cvslam batch` runs per recipe
(serially, or on a Dask worker).

The steps (`recipe.RecipeSteps`) are cvslam command lines run through the CLI itself, so a
batch run does exactly what typing them would. Their terminal output is captured (a batch
prints one line per recipe); their log lines go to the run's `cvslam.log`. A source step
(import, simulate) is skipped when its outputs are there from the same command line (recorded
in `<generated>/<name>/sources.yaml`); the stages skip themselves when up to date. The whole
recipe holds its run directory's lock. A failure of any kind ends the recipe with a one-line
`RecipeResult.error` (a bug's traceback goes to the run's log), never the caller.
"""

from __future__ import annotations

import contextlib
import io
import logging
import shutil
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import click
import yaml

from cvslam_cli.batch.recipe import RecipeSteps, SourceStep
from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.textfiles import read_yaml_mapping

log = logging.getLogger("cvslam")

SOURCES_RECORD = "sources.yaml"
# one recipe at a time per process: the CLI's logging and redirected output are per process
_ONE_AT_A_TIME = threading.Lock()


@dataclass(frozen=True)
class RecipeResult:
    """How one recipe ended: `error` is one line ("" when it succeeded)."""

    name: str
    run_dir: str
    error: str
    wall_s: float

    @property
    def ok(self) -> bool:
        return not self.error


def _cvslam(argv: list[str]) -> None:
    """Run `cvslam ARGV` in this process, its terminal output discarded; CvslamError with
    the command's one line when it fails."""
    from cvslam_cli.cli import cli

    sink = io.StringIO()
    handlers, level = log.handlers[:], log.level  # the command sets up its own logging
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            cli.main(args=argv, prog_name="cvslam", standalone_mode=False)
    except click.ClickException as exc:
        raise CvslamError(f"cvslam {argv[0]}: {exc.format_message()}") from None
    except click.exceptions.Abort:
        raise KeyboardInterrupt from None
    finally:
        log.handlers[:] = handlers
        log.setLevel(level)


def _sources_done(record: Path) -> dict[str, str]:
    if not record.exists():
        return {}
    return {str(k): str(v) for k, v in read_yaml_mapping(record, "a sources record").items()}


def make_sources(steps: RecipeSteps) -> None:
    """Run the source steps whose outputs are not there from the same command line."""
    record = steps.generated_dir / SOURCES_RECORD
    done = _sources_done(record)
    for step in steps.sources:
        key = str(step.out.name)
        # the generated folder recorded as "{generated}": a moved one is still up to date
        command = " ".join(step.argv).replace(str(steps.generated_dir), "{generated}")
        if done.get(key) == command and _present(step):
            log.info("%s: %s is up to date", steps.recipe.name, step.out)
            continue
        log.info("%s: cvslam %s", steps.recipe.name, " ".join(step.argv))
        done.pop(key, None)
        write_text_atomic(record, yaml.safe_dump(done))  # invalid until remade
        if step.out.is_dir():
            shutil.rmtree(step.out)
        step.out.unlink(missing_ok=True)
        _cvslam(list(step.argv))
        done[key] = command
        write_text_atomic(record, yaml.safe_dump(done))


def _present(step: SourceStep) -> bool:
    return bool(step.logs()) if step.makes_folder else step.out.is_file()


def run_recipe(steps: RecipeSteps) -> RecipeResult:
    """Make the recipe's logs and run every stage on them (skipping what is up to date)."""
    t0 = time.perf_counter()
    name = steps.recipe.name
    with _ONE_AT_A_TIME:
        try:
            with RunDir(steps.run_dir).session(f"batch {steps.recipe.path}", create=True):
                try:
                    make_sources(steps)
                    _cvslam(steps.run_argv())
                except CvslamError:
                    raise
                except Exception:
                    log.error("%s: internal error\n%s", name, traceback.format_exc())
                    raise
        except CvslamError as exc:
            return RecipeResult(name, str(steps.run_dir), str(exc), time.perf_counter() - t0)
        except Exception as exc:
            error = f"internal error {type(exc).__name__}: {exc} (see the run's cvslam.log)"
            return RecipeResult(name, str(steps.run_dir), error, time.perf_counter() - t0)
    return RecipeResult(name, str(steps.run_dir), "", time.perf_counter() - t0)
