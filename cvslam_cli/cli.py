"""The `cvslam` command line: thin click commands over the stage modules.

The one error boundary (DESIGN.md section 6, convention 2): a `CvslamError` prints one line
naming the file, topic or key at fault and exits 1; usage errors exit 2; anything else is a
bug and keeps its traceback.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import click

from cvslam_cli import __version__
from cvslam_cli.batch.commands import COMMANDS as BATCH_COMMANDS
from cvslam_cli.config import Config, dump_config, load_config, with_origin
from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.io.run_layout import EvalFolder, FuseFolder, RunLayout, resolved_config_beside

log = logging.getLogger("cvslam")


class _OneLineFormatter(logging.Formatter):
    """`cvslam: [level: ]message`; `detailed` (-vv): also the seconds since start and the
    logger (which stage said it)."""

    def __init__(self, detailed: bool = False) -> None:
        super().__init__()
        self.detailed = detailed

    def format(self, record: logging.LogRecord) -> str:
        prefix = "" if record.levelno == logging.INFO else f"{record.levelname.lower()}: "
        if self.detailed:
            prefix = f"[{record.relativeCreated / 1000:8.3f} s {record.name}] {prefix}"
        return f"cvslam: {prefix}{record.getMessage()}"


class _TerminalHandler(logging.StreamHandler):
    """The handler writing the one-line messages to stderr."""


def _setup_logging(verbose: int, quiet: bool) -> None:
    """The `cvslam` logger's level and terminal handler: INFO; -v DEBUG; -vv DEBUG with
    the seconds since start and the logger's name on each line; -q WARNING."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    handler = _TerminalHandler(sys.stderr)
    handler.setFormatter(_OneLineFormatter(detailed=verbose >= 2 and not quiet))
    # replace the terminal handler of an earlier call, keep others (a run's log file)
    log.handlers[:] = [h for h in log.handlers if not isinstance(h, _TerminalHandler)]
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False


def _with_config_layers(
    func: Callable[..., Any], receive: Callable[[Sequence[Path], Sequence[str], list], dict]
) -> Callable[..., Any]:
    """Add `--config FILE` (repeatable), `--calib` and `--set key.path=value` (repeatable);
    the command receives `receive(config files, overrides, calib layers)` as keywords."""

    @_config_params
    @functools.wraps(func)
    def wrapper(
        *args: Any,
        config_files: Sequence[Path],
        overrides: Sequence[str],
        calibs: Sequence[str],
        **kwargs: Any,
    ) -> Any:
        layers = [_calib_layer(c) for c in calibs]
        return func(*args, **receive(config_files, overrides, layers), **kwargs)

    return wrapper


def config_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Add `--config FILE` (repeatable), `--calib` and `--set key.path=value` (repeatable);
    the command receives the resolved `cfg: Config`."""
    return _with_config_layers(
        func, lambda files, overrides, layers: {"cfg": load_config(files, overrides, layers)}
    )


def config_source_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """The options of `config_options`; the command receives the config's `sources` (name,
    mapping), lowest precedence first (`config.config_sources`), instead of the config."""
    from cvslam_cli.config import config_sources

    return _with_config_layers(
        func,
        lambda files, overrides, layers: {"sources": config_sources(files, overrides, layers)},
    )


def _config_params(func: Callable[..., Any]) -> Callable[..., Any]:
    """`--config`, `--set`, `--calib`: the command receives config_files, overrides, calibs."""
    for option in reversed(
        [
            click.option(
                "--config",
                "config_files",
                multiple=True,
                metavar="FILE",
                type=click.Path(dir_okay=False, path_type=Path),
                help="YAML config file, or the name of a shipped one (kitti, paper) "
                "(repeatable; later files override earlier ones).",
            ),
            click.option(
                "--set",
                "overrides",
                multiple=True,
                metavar="KEY.PATH=VALUE",
                help="Override one config key, e.g. --set logs.stereo_pair_tolerance_ms=5 "
                "(repeatable).",
            ),
            click.option(
                "--calib",
                "calibs",
                multiple=True,
                metavar="[VEHICLE=]FILE",
                help="Kalibr camchain(-imucam).yaml: the stereo rig of every vehicle, or of "
                "VEHICLE (with its image topics); applied after --config, before --set "
                "(repeatable).",
            ),
        ]
    ):
        func = option(func)
    return func


def _calib_layer(spec: str) -> tuple[str, dict[str, Any]]:
    """The config layer of `--calib [VEHICLE=]FILE` (a Kalibr calibration)."""
    from cvslam_cli.io.importers.kalibr import kalibr_config

    name, sep, rest = spec.partition("=")
    vehicle, path = (name, Path(rest)) if sep and not Path(spec).exists() else (None, Path(spec))
    return f"--calib {spec}", kalibr_config(path, vehicle)


_FORCE_STAGE = click.option(
    "--force", is_flag=True, help="Redo the stage even if up to date or made with another config."
)
_RUN_DIR_OUTPUT = click.option(
    "-o",
    "--output",
    "run_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Run directory.",
)


_ORIGIN_OPTION = click.option(
    "--origin",
    metavar="LAT,LON,ALT,HEADING",
    default=None,
    help="The nav origin on the Earth (WGS 84 degrees, ellipsoidal metres, heading of the nav "
    "x axis in degrees clockwise from true north), as geo.origin: mosaics in UTM instead of "
    "the local nav east/north.",
)


def _log_option(what: str) -> Callable[..., Any]:
    """`--log FILE` (repeatable): the logs a stage reads `what` from."""
    return click.option(
        "--log",
        "log_paths",
        multiple=True,
        type=click.Path(path_type=Path),
        help=f"Log with {what} (repeatable; NAME=PATH: the log of vehicle NAME); default: the "
        "logs the features came from.",
    )


def bound_logs(logs: Sequence[Path], cfg: Config) -> tuple[list[Path], Config]:
    """(plain log paths, `cfg` with the `NAME=PATH` arguments bound as logs.vehicles.NAME.log)."""
    from cvslam_cli.io.log_open import split_log_args
    from cvslam_cli.io.logs import bind_logs

    paths, bound = split_log_args(logs)
    return paths, dataclasses.replace(cfg, logs=bind_logs(cfg.logs, bound))


def run_session(run_dir: Path, command: str, *, create: bool = False) -> Any:
    """The run directory held by this process while `command` works on it: one process at a
    time, the log copied to RUN_DIR/cvslam.log (`io/rundir.py`)."""
    from cvslam_cli.io.rundir import RunDir

    return RunDir(run_dir).session(command, create=create)


def write_resolved_config(cfg: Config, path: Path) -> Path:
    """Write the resolved config to `path` (a name from `io/run_layout.py`)."""
    write_text_atomic(path, dump_config(cfg))
    return path


# ----------------------------------------------------------------------------- global options

_VERBOSITY = "cvslam.verbosity"  # key in the root context's meta: the counts of -v and -q


def _on_global_option(ctx: click.Context, param: click.Parameter, value: Any) -> None:
    """Add one command's -v count (or -q) to the whole command line's and set up the logging:
    `cvslam -v fuse RUN -v` is -vv."""
    seen = ctx.find_root().meta.setdefault(_VERBOSITY, {"verbose": 0, "quiet": False})
    if param.name == "verbose":
        seen["verbose"] += value
    else:
        seen["quiet"] = seen["quiet"] or bool(value)
    _setup_logging(seen["verbose"], seen["quiet"])


def _global_options() -> list[click.Option]:
    """Fresh -v/-q options (one set per command): `-v` debug lines saying what each stage
    chose and why, `-vv` with times and logger names; `-q` only warnings and errors."""
    common: dict[str, Any] = {"expose_value": False, "callback": _on_global_option}
    return [
        click.Option(
            ["-v", "--verbose"],
            count=True,
            help="More output: -v what each stage chose and why, -vv with times and the "
            "logger of each line (anywhere on the command line).",
            **common,
        ),
        click.Option(["-q", "--quiet"], is_flag=True, help="Only warnings and errors.", **common),
    ]


def _add_global_options(cmd: click.Command) -> None:
    """Give `cmd` (and the commands of a plain click group it is) the global options."""
    if not any(p.name == "verbose" for p in cmd.params):
        cmd.params.extend(_global_options())
    if isinstance(cmd, click.Group) and not isinstance(cmd, CvslamGroup):
        for sub in cmd.commands.values():
            _add_global_options(sub)


class CvslamGroup(click.Group):
    """A click group whose every command takes the global options (-v, -q) wherever they
    are on the command line: they are added to each command as it is added to the group
    (`@cli.command()`, `@cli.group()`, `cli.add_command(...)`), so a new command has them
    without doing anything. Subgroups made with `@group.group()` are CvslamGroups too."""

    group_class = type

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _add_global_options(self)

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        _add_global_options(cmd)
        super().add_command(cmd, name)


@click.group(cls=CvslamGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="cvslam")
def cli() -> None:
    """Cooperative stereo visual SLAM from ROS 2 and ROS 1 bags (no ROS install needed).

    -v / -q are accepted before or after any command.
    """


# ----------------------------------------------------------------------------- info


@cli.command()
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path, dir_okay=True))
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@config_options
def info(logs: tuple[Path, ...], as_json: bool, cfg: Config) -> None:
    """Summarise LOG... per vehicle: topics, rates, stereo pairs, calibration, problems.

    A LOG is an .mcap file, a rosbag2 folder, a .db3 or a ROS 1 .bag; NAME=LOG reads LOG as
    vehicle NAME's (its topic names as they are). Exits 1 when a problem that would stop later
    stages is found, or no vehicle is (after printing the report).
    """
    from cvslam_cli.info import first_error, inspect_logs, render_text
    from cvslam_cli.io.log_open import open_log
    from cvslam_cli.io.logs import all_log_paths

    paths, cfg = bound_logs(logs, cfg)
    report = inspect_logs([open_log(p) for p in all_log_paths(paths, cfg.logs)], cfg)
    click.echo(json.dumps(report, indent=2) if as_json else render_text(report))
    err = first_error(report)
    if err:
        raise CvslamError(err)


# ----------------------------------------------------------------------------- import


@cli.group(name="import")
def import_() -> None:
    """Convert a dataset folder (EuRoC, KITTI) into a cvslam MCAP log, or a Kalibr
    calibration into a rig config."""


def _import_common(func: Callable[..., Any]) -> Callable[..., Any]:
    func = click.option(
        "-o",
        "--output",
        required=True,
        type=click.Path(dir_okay=False, path_type=Path),
        help="MCAP file to write.",
    )(func)
    func = click.option(
        "--vehicle",
        default="uav1",
        show_default=True,
        help="Vehicle name used in topic names (/<vehicle>/...).",
    )(func)
    func = click.option("--force", is_flag=True, help="Replace an existing output file.")(func)
    return config_options(func)


def _import_target(output: Path, force: bool) -> Path:
    """`output`, checked before the import: an existing file is replaced only with `--force`
    (and never anything that is not a regular file); its folder must be writable."""
    from cvslam_cli.io.atomic import check_writable

    if (output.exists() or output.is_symlink()) and not force:
        raise CvslamError(f"{output}: already exists (use --force to replace it)")
    check_writable([output])
    return output


def _report_import(summary: Any, cfg: Config) -> None:
    cfg_path = write_resolved_config(cfg, resolved_config_beside(summary.out_path))
    log.info(
        "wrote %s: vehicle %s, %d stereo pairs, %d IMU samples, %d ground-truth poses, "
        "%.3f s, baseline %.4f m (config: %s)",
        summary.out_path,
        summary.vehicle,
        summary.stereo_pairs,
        summary.imu_samples,
        summary.ground_truth_poses,
        summary.duration_s,
        summary.baseline_m,
        cfg_path,
    )
    for note in summary.notes:
        log.info("note: %s", note)


@import_.command(name="euroc")
@click.argument("mav0_dir", type=click.Path(path_type=Path))
@_import_common
def import_euroc_cmd(mav0_dir: Path, output: Path, vehicle: str, force: bool, cfg: Config) -> None:
    """Import an EuRoC MAV (ASL folder layout) MAV0_DIR into an MCAP log."""
    from cvslam_cli.io.importers.euroc import import_euroc

    output = _import_target(output, force)
    _report_import(
        import_euroc(mav0_dir, output, vehicle, progress=log.isEnabledFor(logging.INFO)), cfg
    )


@import_.command(name="kitti")
@click.argument("seq_dir", type=click.Path(path_type=Path))
@click.option(
    "--rate-hz",
    default=10.0,
    show_default=True,
    type=click.FloatRange(min=0.001),
    help="Frame rate used when the folder has no times.txt.",
)
@_import_common
def import_kitti_cmd(
    seq_dir: Path, rate_hz: float, output: Path, vehicle: str, force: bool, cfg: Config
) -> None:
    """Import a KITTI odometry sequence folder SEQ_DIR into an MCAP log."""
    from cvslam_cli.io.importers.kitti import import_kitti

    output = _import_target(output, force)
    _report_import(
        import_kitti(
            seq_dir, output, vehicle, rate_hz=rate_hz, progress=log.isEnabledFor(logging.INFO)
        ),
        cfg,
    )


@import_.command(name="kalibr")
@click.argument("camchain", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Config file to write (use it with --config).",
)
@click.option(
    "--vehicle",
    default=None,
    help="Write the rig (and Kalibr's image topics) for this vehicle only "
    "(logs.vehicles.VEHICLE); default: every vehicle's rig (logs.vehicle_defaults.rig).",
)
def import_kalibr_cmd(camchain: Path, output: Path, vehicle: str | None) -> None:
    """Turn a Kalibr CAMCHAIN (camchain-imucam.yaml) into a cvslam rig config: cam0/cam1 as
    the left/right camera, T_body_cam = inv(T_cam_imu), radtan as plumb_bob, the time shift as
    rig.camera_time_offset_ns."""
    from cvslam_cli.io.importers.kalibr import kalibr_config_text

    write_text_atomic(output, kalibr_config_text(camchain, vehicle))
    log.info("wrote %s (use it with --config %s)", output, output)


# ----------------------------------------------------------------------------- config


@cli.group("config")
def config_group() -> None:
    """The configuration: every key with its value, comment and source; check a file."""


def _complete_config_key(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[str]:
    """Shell completion of a config key path (docs/cli.md)."""
    from cvslam_cli.config import schema_keys

    return [k for k in schema_keys() if k.startswith(incomplete)]


@config_group.command("show")
@click.argument("key", required=False, shell_complete=_complete_config_key)
@config_source_options
def config_show(key: str | None, sources: Sequence[tuple[str, dict[str, Any]]]) -> None:
    """Print the resolved config (defaults, then --config files, --calib, --set) as YAML,
    each key with its comment from configs/default.yaml and each value with its source
    (default, file PATH, --set ...). KEY: only the keys at or below this dotted prefix,
    e.g. `fuse.hinf`. The output loads as the same config (--config)."""
    from cvslam_cli.config import (
        DEFAULT_CONFIG_PATH,
        config_from_sources,
        nearest_key,
        to_dict,
        value_sources,
    )
    from cvslam_cli.config_show import key_comments, key_paths, render_config

    data = to_dict(config_from_sources(sources))
    if key is not None and key not in key_paths(data):
        near = nearest_key(key, key_paths(data))
        raise CvslamError(
            f"config show {key}: no such key"
            + (f" (did you mean {near}?)" if near else " (see `cvslam config show`)")
        )
    comments = key_comments(DEFAULT_CONFIG_PATH.read_text(encoding="utf-8"))
    click.echo(render_config(data, comments, value_sources(sources), key), nl=False)


@config_group.command("check")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
def config_check(file: Path) -> None:
    """Check the config FILE: one line per problem (an unknown key with the nearest valid
    one, a wrong type or range), exit 1; "ok" and exit 0 when it has none."""
    from cvslam_cli.config import CONFIG_FILE, config_problems, resolve_config_path
    from cvslam_cli.errors import ConfigError
    from cvslam_cli.io.textfiles import read_yaml_mapping

    path = resolve_config_path(file)
    problems = config_problems(
        read_yaml_mapping(path, CONFIG_FILE, ConfigError, empty_ok=True), str(path)
    )
    for problem in problems:
        click.echo(f"cvslam: error: {problem}", err=True)
    if problems:
        click.get_current_context().exit(1)
    click.echo(f"{path}: ok")


# ----------------------------------------------------------------------------- simulate


@cli.command()
@click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output directory (one MCAP log per vehicle, truth/, scenario.yaml).",
)
@click.option("--seed", type=int, default=None, help="Random seed (default: the scenario's).")
@click.option(
    "--duration",
    "duration_s",
    type=float,
    default=None,
    metavar="S",
    help="Stretch the mission to S seconds (same paths, speeds scaled).",
)
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY.PATH=VALUE",
    help="Override one scenario key, e.g. --set mode=landmarks (repeatable).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=2,
    show_default=True,
    help="Processes rendering images in parallel.",
)
@click.option("--force", is_flag=True, help="Replace an existing output directory.")
def simulate(
    scenario: Path,
    output: Path,
    seed: int | None,
    duration_s: float | None,
    overrides: tuple[str, ...],
    workers: int,
    force: bool,
) -> None:
    """Simulate SCENARIO (YAML, see configs/scenarios/) into OUTPUT: logs and ground truth.

    Same scenario and seed give byte-identical output.
    """
    from cvslam_cli.sim.scenario import load_scenario, resolve_scenario_path
    from cvslam_cli.sim.stage import run

    path = resolve_scenario_path(scenario)
    sc = load_scenario(path, overrides, seed=seed, duration_s=duration_s)
    summary = run(
        sc,
        output,
        source=str(path),
        force=force,
        workers=workers,
        progress=log.isEnabledFor(logging.INFO),
    )
    for name, v in summary.vehicles.items():
        extra = (
            f"{v.observations} landmark observations"
            if sc.mode == "landmarks"
            else f"{v.stereo_frames} stereo pairs"
        )
        motion = (
            f"{v.imu_samples} IMU samples"
            if v.imu_samples
            else f"{v.odometry_samples} odometry samples"
        )
        log.info(
            "%s: %s, %s, %d ground-truth poses, %.0f m travelled",
            name,
            extra,
            motion,
            v.ground_truth_poses,
            v.distance_m,
        )
    log.info(
        "wrote %s (scenario %s, seed %d, %.1f s simulated) in %.1f s",
        summary.out_dir,
        sc.name,
        sc.seed,
        sc.duration_s,
        summary.wall_time_s,
    )


# ----------------------------------------------------------------------------- extract


@cli.command()
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@_RUN_DIR_OUTPUT
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=2,
    show_default=True,
    help="Processes working on frames in parallel.",
)
@click.option(
    "--scheduler",
    metavar="ADDRESS",
    default=None,
    help="Spread the frames over the Dask cluster at ADDRESS (tcp://host:8786) instead of "
    "--workers local processes; same output (docs/batch.md).",
)
@_FORCE_STAGE
@config_options
def extract(
    logs: tuple[Path, ...],
    run_dir: Path,
    workers: int,
    scheduler: str | None,
    force: bool,
    cfg: Config,
) -> None:
    """Adaptive SIFT + stereo-constrained matching on every stereo frame of LOG...
    (NAME=LOG: the log of vehicle NAME).

    Writes RUN_DIR/features/<vehicle>.npz (docs/feature_format.md) and
    <vehicle>_stats.csv, and records the stage in RUN_DIR/run.yaml.
    """
    paths, cfg = bound_logs(logs, cfg)
    do_extract(cfg, paths, run_dir, workers=workers, force=force, scheduler=scheduler)


def do_extract(
    cfg: Config,
    logs: Sequence[Path],
    run_dir: Path,
    *,
    workers: int,
    force: bool,
    scheduler: str | None = None,
) -> None:
    from cvslam_cli.features.stage import run

    with run_session(run_dir, "extract", create=True):
        summary = run(
            cfg,
            list(logs),
            run_dir,
            workers=workers,
            force=force,
            progress=log.isEnabledFor(logging.INFO),
            scheduler=scheduler,
        )
        layout = RunLayout(run_dir)
        write_resolved_config(cfg, layout.extract_config)
    for name, v in summary.vehicles.items():
        log.info(
            "%s: %d stereo frames (%d empty, %d/%d images unpaired), %.0f keypoints and "
            "%.0f matches per frame, %.1f candidates per keypoint",
            name,
            v.frames,
            v.empty_frames,
            v.unpaired_left,
            v.unpaired_right,
            v.keypoints_per_frame,
            v.matches_per_frame,
            v.candidates_per_keypoint,
        )
    if not summary.skipped:
        log.info("wrote %s", layout.features_dir)


# ----------------------------------------------------------------------------- fuse


@cli.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--filter",
    "filter_kind",
    type=click.Choice(["hinf", "ekf"]),
    default=None,
    help="Filter (default: fuse.filter, hinf). Outputs go to RUN_DIR/fuse (hinf) or "
    "RUN_DIR/fuse_ekf.",
)
@click.option(
    "--single",
    is_flag=True,
    help="Each vehicle in its own filter (for comparison with the cooperative default); "
    "outputs in RUN_DIR/fuse_single (fuse_ekf_single).",
)
@click.option(
    "--prior-map",
    "prior_map",
    metavar="OTHER",
    type=click.Path(path_type=Path),
    default=None,
    help="Start from the map of an earlier run: its run directory (OTHER/fuse/map.npz) or a "
    "map.npz; the same as --set fuse.prior_map=OTHER (docs/fuse_outputs.md, Multi-session).",
)
@_log_option("the motion data")
@_FORCE_STAGE
@config_options
def fuse(
    run_dir: Path,
    filter_kind: str | None,
    single: bool,
    prior_map: Path | None,
    log_paths: tuple[Path, ...],
    force: bool,
    cfg: Config,
) -> None:
    """Cooperative stereo VSLAM: one NH-infinity filter (or EKF) over all vehicles' features.

    Writes trajectories, dead reckoning, pose covariances, the landmark map, timeline,
    events and result.mcap to RUN_DIR/fuse (docs/fuse_outputs.md).
    """
    if prior_map is not None:
        cfg = dataclasses.replace(cfg, fuse=dataclasses.replace(cfg.fuse, prior_map=str(prior_map)))
    paths, cfg = bound_logs(log_paths, cfg)
    do_fuse(cfg, run_dir, filter_kind=filter_kind, single=single, log_paths=paths, force=force)


def _fuse_folder_stage(
    cfg: Config,
    run_dir: Path,
    command: str,
    run: Callable[..., Any],
    log_paths: Sequence[Path],
    force: bool,
    **options: Any,
) -> Any:
    """Run a stage that writes a fuse folder (fuse, refine) in the run's session and record
    its resolved config there; its summary, or None when it was up to date."""
    with run_session(run_dir, command):
        summary = run(
            cfg,
            run_dir,
            log_paths=list(log_paths),
            force=force,
            progress=log.isEnabledFor(logging.INFO),
            **options,
        )
        if summary.skipped:
            return None
        write_resolved_config(cfg, FuseFolder(summary.out_dir).resolved_config)
    return summary


def do_fuse(
    cfg: Config,
    run_dir: Path,
    *,
    filter_kind: str | None,
    single: bool,
    log_paths: Sequence[Path],
    force: bool,
) -> None:
    from cvslam_cli.estimation.stage import run

    summary = _fuse_folder_stage(
        cfg, run_dir, "fuse", run, log_paths, force, filter_kind=filter_kind, single=single
    )
    if summary is None:
        return
    for name, v in summary.vehicles.items():
        errors = (
            f"final position error {v.final_error_m:.2f} m (dead reckoning "
            f"{v.final_error_deadreckoning_m:.2f} m), RMSE {v.rmse_m:.2f} m "
            f"({v.rmse_deadreckoning_m:.2f} m)"
            if v.rmse_m == v.rmse_m  # NaN: the logs have no ground truth
            else "no ground truth to compare with"
        )
        log.info(
            "%s (%s): %d frames, %.0f m; %s, final sigma %.2f m, %d loop closure(s)",
            name,
            v.model,
            v.frames,
            v.distance_m,
            errors,
            v.final_sigma_m,
            v.loop_closures,
        )
        if v.localised_after_s is None:
            log.warning("%s: initial pose unknown and never localised in the map", name)
        elif v.localised_after_s > 0:
            log.info(
                "%s: localised in the map %.2f s after its start on %d inlier landmarks",
                name,
                v.localised_after_s,
                v.localised_inliers,
            )
        if v.lost:
            log.warning(
                "%s: lost %d time(s) -- the map contradicted its pose, or it lost the map -- "
                "and found again in it %d time(s) (fuse/events.csv: lost, relocalisation)",
                name,
                v.lost,
                v.relocalised,
            )
        if v.first_prior_s is not None:
            log.info(
                "%s: %d prior-map landmarks brought into the filter, the first %.2f s after "
                "its start",
                name,
                v.prior_landmarks,
                v.first_prior_s,
            )
    log.info(
        "%s: %d landmarks mapped, %.1fx real time (%.1f s)%s; wrote %s",
        summary.filter,
        summary.landmarks,
        summary.realtime_factor,
        summary.wall_s,
        f", gamma raised in {summary.gamma_raised} updates" if summary.gamma_raised else "",
        summary.out_dir,
    )


@cli.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--gsd",
    "gsd_m",
    type=float,
    default=None,
    help="Metres per mosaic pixel (default: mosaic.gsd_m; 0 there: the images' own ground "
    "resolution).",
)
@click.option(
    "--source",
    type=click.Choice(["fused", "deadreckoning", "groundtruth"]),
    default=None,
    help="Poses to project with (default: mosaic.source, fused). Outputs go to RUN_DIR/mosaic "
    "(fused) or RUN_DIR/mosaic_<source>.",
)
@_ORIGIN_OPTION
@_log_option("the images")
@_FORCE_STAGE
@config_options
def mosaic(
    run_dir: Path,
    gsd_m: float | None,
    source: str | None,
    origin: str | None,
    log_paths: tuple[Path, ...],
    force: bool,
    cfg: Config,
) -> None:
    """Ground mosaics: each vehicle's left images projected on the ground with their poses,
    blended per vehicle and all together.

    Writes <vehicle>.png, all.png (with .pgw world files), their GeoTIFFs (.tif) and
    *_overlay.png to RUN_DIR/mosaic (docs/mosaic.md).
    """
    cfg = with_origin(cfg, origin)
    paths, cfg = bound_logs(log_paths, cfg)
    do_mosaic(cfg, run_dir, source=source, gsd_m=gsd_m, log_paths=paths, force=force)


def do_mosaic(
    cfg: Config,
    run_dir: Path,
    *,
    source: str | None,
    gsd_m: float | None,
    log_paths: Sequence[Path],
    force: bool,
) -> None:
    from cvslam_cli.mosaic.stage import run

    with run_session(run_dir, "mosaic"):
        summary = run(
            cfg,
            run_dir,
            source=source,
            gsd_m=gsd_m,
            log_paths=list(log_paths),
            force=force,
            progress=log.isEnabledFor(logging.INFO),
        )
    if summary.skipped:
        return
    for name, m in summary.mosaics.items():
        truth = ""
        if m.truth is not None:
            truth = (
                "; vs true ground: "
                + (
                    f"shift {m.truth['shift_m']:.2f} m"
                    if m.truth["shift_found"]
                    else "no clear match"
                )
                + f", NCC {m.truth['ncc']:.2f}, "
                f"{100 * m.truth['tiles_matched']:.0f} % of tiles matched, local shift "
                f"{m.truth['tile_shift_median_px']:.1f} px"
            )
        log.info(
            "%s: %d images, %d x %d px, %.0f m^2 covered%s",
            name,
            m.images,
            m.width_px,
            m.height_px,
            m.covered_m2,
            truth,
        )
    log.info(
        "mosaic (%s poses): %.3g m/px, %.1f images/s (%.1f s); wrote %s",
        summary.source,
        summary.gsd_m,
        summary.images_per_s,
        summary.wall_s,
        summary.out_dir,
    )


# ----------------------------------------------------------------------------- refine


@cli.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--source",
    type=click.Choice(["fuse", "fuse_ekf", "fuse_single", "fuse_ekf_single"]),
    default=None,
    help="The fuse folder refined (default: refine.source, fuse). Outputs go to "
    "RUN_DIR/fuse_refined (RUN_DIR/<source>_refined for another source).",
)
@_log_option("the motion data")
@_FORCE_STAGE
@config_options
def refine(
    run_dir: Path, source: str | None, log_paths: tuple[Path, ...], force: bool, cfg: Config
) -> None:
    """Batch solution over a fuse run: one factor graph (bundle adjustment with the IMU,
    odometry or constant-velocity motion between keyframes) solved with GTSAM.

    Writes trajectories, pose covariances, the map and result.mcap to RUN_DIR/fuse_refined
    in the fuse formats (docs/refine.md); mosaic (mosaic.fuse_dir) and eval pick it up.
    """
    paths, cfg = bound_logs(log_paths, cfg)
    do_refine(cfg, run_dir, source=source, log_paths=paths, force=force)


def do_refine(
    cfg: Config, run_dir: Path, *, source: str | None, log_paths: Sequence[Path], force: bool
) -> None:
    from cvslam_cli.refine.stage import run

    summary = _fuse_folder_stage(cfg, run_dir, "refine", run, log_paths, force, source=source)
    if summary is None:
        return
    for name, v in summary.vehicles.items():
        errors = (
            f"position RMSE {v.rmse_source_m:.3f} m ({summary.source}) -> {v.rmse_m:.3f} m"
            if v.rmse_m == v.rmse_m  # NaN: no ground truth
            else "no ground truth to compare with"
        )
        log.info(
            "%s: %d keyframes (%s), %s; gauge: prior on the first keyframe (sigma %.3g m, "
            "%.3g rad)",
            name, v.keyframes, v.model, errors, v.prior_sigma_position_m,
            v.prior_sigma_attitude_rad,
        )  # fmt: skip
        if v.right_cx_px == v.right_cx_px:  # NaN: not estimated
            log.info(
                "%s: right camera's principal point u0 corrected by %+.3f px (+- %.3f)",
                name, v.right_cx_px, v.right_cx_std_px,
            )  # fmt: skip
    log.info(
        "refine: %d landmarks, %d observations (%d outliers), error %.4g -> %.4g in %d "
        "iterations, %.1f s; wrote %s",
        summary.landmarks, summary.observations, summary.outliers, summary.initial_error,
        summary.final_error, summary.iterations, summary.wall_s, summary.out_dir,
    )  # fmt: skip


# ----------------------------------------------------------------------------- eval, run

_GT_HELP = (
    "Ground truth (repeatable): a TUM or KITTI file named <vehicle>.tum/.txt, or "
    "VEHICLE=FILE; default: the logs' ground-truth topic."
)


@cli.command("eval")
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--gt", "gt", multiple=True, metavar="FILE", help=_GT_HELP)
@click.option(
    "--align",
    type=click.Choice(["none", "se3", "sim3"]),
    default=None,
    help="Align each estimate to the truth first (default: eval.align, none).",
)
@_log_option("the ground truth")
@_FORCE_STAGE
@config_options
def eval_cmd(
    run_dir: Path,
    gt: tuple[str, ...],
    align: str | None,
    log_paths: tuple[Path, ...],
    force: bool,
    cfg: Config,
) -> None:
    """Metrics (ATE, RPE, drift, NEES), figures and report.html for every estimate in RUN_DIR.

    Writes RUN_DIR/eval/metrics.json, metrics.csv, headline.csv, figures/*.png and
    report.html (docs/eval.md).
    """
    if align is not None:
        cfg = dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, align=align))
    paths, cfg = bound_logs(log_paths, cfg)
    do_eval(cfg, run_dir, gt=gt, log_paths=paths, force=force)


def do_eval(
    cfg: Config, run_dir: Path, *, gt: Sequence[str], log_paths: Sequence[Path], force: bool
) -> None:
    from cvslam_cli.evaluation.stage import headline_text, run

    with run_session(run_dir, "eval"):
        summary = run(
            cfg,
            run_dir,
            gt=gt,
            log_paths=log_paths,
            force=force,
            progress=log.isEnabledFor(logging.INFO),
        )
    # labelled, so that tables of runs made in parallel (make -j) say which run they are of
    click.echo(f"{run_dir}:\n{headline_text(summary.headline)}")
    log.info("report: %s", EvalFolder(summary.out_dir).report_html)


@cli.command("run")
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@_RUN_DIR_OUTPUT
@click.option("--gt", "gt", multiple=True, metavar="FILE", help=_GT_HELP)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=2,
    show_default=True,
    help="Processes working on frames in parallel (extract).",
)
@_ORIGIN_OPTION
@click.option("--force", is_flag=True, help="Redo every stage.")
@config_options
def run_cmd(
    logs: tuple[Path, ...],
    run_dir: Path,
    gt: tuple[str, ...],
    workers: int,
    origin: str | None,
    force: bool,
    cfg: Config,
) -> None:
    """All stages on LOG... with one config: extract, fuse (cooperative NH-infinity and the
    comparisons in run.comparisons), mosaic, eval. Stages whose config and inputs are
    unchanged are skipped. NAME=LOG: the log of vehicle NAME.
    """
    cfg = with_origin(cfg, origin)
    paths, cfg = bound_logs(logs, cfg)
    with run_session(run_dir, "run", create=True):
        do_run(cfg, paths, run_dir, gt=gt, workers=workers, force=force)


def do_run(
    cfg: Config,
    logs: Sequence[Path],
    run_dir: Path,
    *,
    gt: Sequence[str],
    workers: int,
    force: bool,
) -> None:
    do_extract(cfg, list(logs), run_dir, workers=workers, force=force)
    do_fuse(cfg, run_dir, filter_kind="hinf", single=False, log_paths=(), force=force)
    for comparison in cfg.run.comparisons:
        if comparison == "refined":  # the batch solution over the cooperative run
            do_refine(cfg, run_dir, source="fuse", log_paths=(), force=force)
            continue
        filter_kind = "ekf" if comparison.startswith("ekf") else "hinf"
        single = comparison.endswith("single")
        if single and cfg.fuse.prior_map:
            log.warning("run: %s skipped: it cannot start from fuse.prior_map", comparison)
            continue
        do_fuse(cfg, run_dir, filter_kind=filter_kind, single=single, log_paths=(), force=force)
    if cfg.run.mosaic:
        do_mosaic(cfg, run_dir, source=None, gsd_m=None, log_paths=(), force=force)
    from cvslam_cli.evaluation.stage import has_ground_truth

    if gt or has_ground_truth(cfg, run_dir):
        do_eval(cfg, run_dir, gt=gt, log_paths=(), force=force)
    else:
        log.warning(
            "eval skipped: the logs have no ground truth (give it with --gt FILE to evaluate)"
        )


# ----------------------------------------------------------------------------- export


@cli.command("export")
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--source",
    default="fuse",
    show_default=True,
    help="The fuse folder whose estimates to export (fuse, fuse_ekf, fuse_single, ...).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["tum", "kitti", "euroc"]),
    default="tum",
    show_default=True,
    help="tum: <v>.tum; kitti: <v>.txt (3x4 poses) and <v>_times.txt; euroc: <v>.csv.",
)
@click.option(
    "--frame",
    type=click.Choice(["nav", "enu", "dataset"]),
    default="nav",
    show_default=True,
    help="nav: NED, body frame; enu: z up, body frame; dataset: the dataset's own world "
    "and sensor (KITTI camera 0, EuRoC IMU), as its ground truth.",
)
@click.option(
    "-o",
    "--output",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Output folder (default: RUN_DIR/export/<source>_<frame>).",
)
@_log_option("the dataset frame (--frame dataset)")
@config_options
def export_cmd(
    run_dir: Path,
    source: str,
    fmt: str,
    frame: str,
    out_dir: Path | None,
    log_paths: tuple[Path, ...],
    cfg: Config,
) -> None:
    """Every vehicle's estimate in the frame and format of your tools (docs/export.md):
    with --frame dataset, evo's APE and RPE against the dataset's own ground truth
    (KITTI poses.txt, EuRoC data.csv) are right."""
    from cvslam_cli.io.export import run

    paths, cfg = bound_logs(log_paths, cfg)
    with run_session(run_dir, "export"):
        summary = run(
            cfg, run_dir, source=source, fmt=fmt, frame=frame, out_dir=out_dir, log_paths=paths
        )
    for name, v in summary.vehicles.items():
        log.info(
            "%s: %d poses of the %s in %s -> %s",
            name,
            len(v.table),
            v.sensor,
            v.world,
            ", ".join(map(str, v.files)),
        )


# ----------------------------------------------------------------------------- many runs

for _command in BATCH_COMMANDS:  # batch, summary, sweep (cvslam_cli/batch/commands.py)
    cli.add_command(_command)


# ----------------------------------------------------------------------------- entry


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that the stage unwinds like on Ctrl-C."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise _Terminated


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point with the one error boundary; Ctrl-C exits 130, SIGTERM 143,
    both after the stage has unwound (partial outputs removed, workers shut down)."""
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        rc = cli.main(
            args=list(argv) if argv is not None else None, prog_name="cvslam", standalone_mode=False
        )
    except _Terminated:
        click.echo("cvslam: terminated", err=True)
        sys.exit(143)
    except click.exceptions.Abort as exc:
        if isinstance(exc.__cause__, EOFError):  # click turns every EOFError into Abort:
            raise exc.__cause__ from None  # one not from the terminal is a bug, not Ctrl-D
        click.echo("cvslam: interrupted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except CvslamError as exc:
        click.echo(f"cvslam: error: {exc}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        click.echo("cvslam: interrupted", err=True)
        sys.exit(130)
    finally:
        signal.signal(signal.SIGTERM, previous)
    sys.exit(rc if isinstance(rc, int) else 0)
