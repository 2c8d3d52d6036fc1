"""The command line's habits: -v/-q anywhere, -v saying what each stage chose, `cvslam config
show/check`, configs shipped in the package, eval's progress bar, Ctrl-C with workers."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import click
import pytest
import yaml

from cvslam_cli.cli import CvslamGroup, cli
from cvslam_cli.config import (
    CONFIG_DIR,
    DEFAULT_CONFIG_PATH,
    Config,
    config_problems,
    load_config,
    to_dict,
)
from cvslam_cli.config_show import key_comments
from tests.scenarios import small_uav_scenario
from tests.signals import default_sigint
from tests.synth import write_stereo_log

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def landmark_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 s of two simulated UAVs in landmark mode (features written by the simulator)."""
    tmp = tmp_path_factory.mktemp("habits")
    out = tmp / "sim"
    args = ["-q", "simulate", small_uav_scenario(tmp), "-o", out, "--set", "mode=landmarks"]
    cli.main([*map(str, args), "--duration", "3"], standalone_mode=False)
    return out


def _commands(cmd: click.Command, path: tuple[str, ...] = ()):
    yield path, cmd
    for name, sub in getattr(cmd, "commands", {}).items():
        yield from _commands(sub, (*path, name))


# --------------------------------------------------------------------------- global options


def test_every_command_takes_the_global_options_and_so_does_one_added_later():
    for path, cmd in _commands(cli):
        names = {p.name for p in cmd.params}
        assert {"verbose", "quiet"} <= names, path

    group = CvslamGroup("g")
    sub = click.Group("plain")  # a plain click group from elsewhere, and a command of it
    sub.add_command(click.Command("leaf", callback=lambda: None))
    group.add_command(sub)
    group.add_command(click.Command("late", callback=lambda: None))

    @group.command()
    def decorated() -> None:
        pass

    for path, cmd in _commands(group):
        assert sum(p.name == "verbose" for p in cmd.params) == 1, path


def test_global_options_before_and_after_the_command(cvslam, landmark_run):
    after = cvslam("fuse", landmark_run, "--force", "-v")
    assert after.code == 0, after.err
    before = cvslam("-v", "fuse", landmark_run, "--force")
    assert before.code == 0, before.err
    for res in (after, before):
        assert "debug: fuse: filter NH-infinity, gamma 30 (fuse.hinf.gamma" in res.err
        assert "debug: uav1: 601 IMU samples" in res.err
        assert "debug: fuse runs (" in res.err
    quiet = cvslam("fuse", landmark_run, "--force", "-q")
    assert quiet.code == 0 and quiet.err == ""
    plain = cvslam("fuse", landmark_run)
    assert "up to date" in plain.err and "debug:" not in plain.err
    twice = cvslam("-v", "fuse", landmark_run, "-v")  # counted over the whole line: -vv
    assert "s cvslam.rundir] debug: fuse skipped (up to date)" in twice.err


def test_verbose_says_which_calibration_the_rig_came_from(cvslam, tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=3, size=(160, 120), fx=120.0)
    res = cvslam("extract", synth.path, "-o", tmp_path / "run", "--workers", "1", "-v")
    assert res.code == 0, res.err
    line = next(ln for ln in res.err.splitlines() if "calibration: left from" in ln)
    assert "CameraInfo /uav1/stereo/left/camera_info" in line and "baseline" in line
    assert "debug: extract: adaptive SIFT" in res.err and "1 worker process(es)" in res.err


# --------------------------------------------------------------------------- config show


def test_config_show_key_prints_the_value_its_comment_and_source(cvslam, tmp_path):
    res = cvslam("config", "show", "fuse.hinf")
    assert res.code == 0, res.err
    lines = res.out.splitlines()
    i = lines.index("    gamma: 30.0  # default")
    assert lines[i - 1].startswith("    # ") and "Bound gamma" in "".join(lines[i - 7 : i])
    assert (
        "fuse.hinf.c_w" not in res.out and "  hinf:" in lines and "c_w: 1.0  # default" in res.out
    )
    assert "filter:" not in res.out  # only the keys below the prefix (and its parents)

    mine = tmp_path / "mine.yaml"
    mine.write_text("fuse:\n  hinf:\n    c_v: 1.5\n")
    res = cvslam("config", "show", "fuse.hinf", "--config", mine, "--set", "fuse.hinf.gamma=50")
    assert "    gamma: 50.0  # --set fuse.hinf.gamma=50" in res.out.splitlines()
    assert f"    c_v: 1.5  # file {mine}" in res.out.splitlines()

    res = cvslam("config", "show", "fuse.hinf.gama")
    assert res.code == 1 and "no such key (did you mean fuse.hinf.gamma?)" in res.err


def test_config_show_is_the_resolved_config_as_yaml(cvslam, tmp_path):
    args = ["--config", "kitti", "--set", "logs.vehicles.tb3.kind=ugv"]
    res = cvslam("config", "show", *args)
    assert res.code == 0, res.err
    assert yaml.safe_load(res.out) == to_dict(
        load_config(["kitti"], ["logs.vehicles.tb3.kind=ugv"])
    )
    assert f"# file {CONFIG_DIR / 'kitti.yaml'}" in res.out
    # a vehicle's keys carry the comments of logs.vehicle_defaults
    tb3 = res.out.split("    tb3:\n", 1)[1]
    assert tb3.splitlines()[0].strip().startswith("# ") and "kind: ugv  # --set" in tb3


def test_default_yaml_has_a_comment_for_every_key_config_show_prints():
    """Each value has its own comment, or is one of the first keys of a section whose
    comment (printed above the section) covers them (`fuse.initial.source`)."""
    comments = key_comments(DEFAULT_CONFIG_PATH.read_text(encoding="utf-8"))

    def uncovered(node, path=""):
        commented_before = False
        for k, v in node.items():
            sub = f"{path}.{k}" if path else k
            commented_before = commented_before or bool(comments.get(sub))
            if isinstance(v, dict) and v:
                yield from uncovered(v, sub)
            elif not comments.get(sub) and (commented_before or not comments.get(path)):
                yield sub

    assert not list(uncovered(to_dict(Config())))
    assert (
        comments["logs.vehicle_defaults.rig.left.height"]
        == comments["logs.vehicle_defaults.rig.left.width"]
    )  # one comment for a group of keys
    assert "logs.vehicle_defaults.rig.left" not in comments  # a section has only its own
    assert comments["logs.vehicle_defaults.rig.right.fx"] == ["Same keys as left."]
    assert "logs" not in comments  # the file's header (then a blank line) is no key's


# --------------------------------------------------------------------------- config check


def test_config_check_names_every_bad_key_and_exits_1(cvslam, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "fuse:\n  hinf:\n    gama: 3\n    c_w: 0.5\n  gamma: 2\n"
        "logs:\n  vehicles:\n    uav1: {kind: boat}\nextrac: {}\n"
    )
    res = cvslam("config", "check", bad)
    assert res.code == 1
    assert res.err.splitlines() == [
        f"cvslam: error: {bad}: fuse.hinf.gama: unknown key (did you mean fuse.hinf.gamma?)",
        f"cvslam: error: {bad}: fuse.hinf.c_w: expected a number >= 1.0, got 0.5",
        f"cvslam: error: {bad}: fuse.gamma: unknown key (did you mean fuse.hinf.gamma?)",
        f"cvslam: error: {bad}: logs.vehicles.uav1.kind: expected one of 'uav', 'ugv', got 'boat'",
        f"cvslam: error: {bad}: extrac: unknown key (did you mean extract?)",
    ]
    assert res.out == ""


def test_config_check_ok_and_the_checks_load_config_makes(cvslam, tmp_path):
    for name in ("default.yaml", "kitti.yaml", "paper.yaml"):
        res = cvslam("config", "check", CONFIG_DIR / name)
        assert res.code == 0 and res.out.strip() == f"{CONFIG_DIR / name}: ok", res.err
    pair = {"extract": {"adaptive": {"layers_min": 5, "layers_max": 3}}}
    (problem,) = config_problems(pair, "x.yaml")
    assert "x.yaml: extract.adaptive.layers_min = 5 is above extract.adaptive.layers_max" in problem
    res = cvslam("config", "check", tmp_path / "none.yaml")
    assert res.code == 1 and "none.yaml: not found" in res.err


# --------------------------------------------------------------------------- package data


def test_configs_are_package_data_and_the_repository_link_points_there():
    assert CONFIG_DIR.parent == REPO / "cvslam_cli"
    assert (CONFIG_DIR / "scenarios" / "uav2_paper.yaml").is_file()
    assert (REPO / "configs").resolve() == CONFIG_DIR.resolve()
    assert load_config(["paper"]) == load_config([REPO / "configs" / "paper.yaml"])
    text = (REPO / "pyproject.toml").read_text()
    assert '"configs/*.yaml"' in text and '"configs/scenarios/*.yaml"' in text


# --------------------------------------------------------------------------- eval progress


def _on_a_terminal(args: list[str]) -> tuple[int, str]:
    """Run `python -m cvslam_cli ARGS` with stderr on a pseudo-terminal: (exit code, what
    the terminal showed)."""
    master, slave = pty.openpty()
    # a new pseudo-terminal is 0 columns wide: progress bars would have no room
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    proc = subprocess.Popen(
        [sys.executable, "-m", "cvslam_cli", *args], stdout=subprocess.DEVNULL, stderr=slave
    )
    os.close(slave)
    shown = b""
    while True:
        ready, _, _ = select.select([master], [], [], 60)
        if not ready:
            break
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        shown += chunk
    os.close(master)
    return proc.wait(timeout=60), shown.decode(errors="replace")


def test_eval_shows_progress_on_a_terminal_and_debug_lines_with_v(cvslam, landmark_run):
    code, shown = _on_a_terminal(["eval", str(landmark_run), "--force"])
    assert code == 0, shown
    assert "eval metrics" in shown and "estimate" in shown and "eval figures" in shown
    res = cvslam("eval", landmark_run, "--force", "-v")  # not a terminal: no bar, debug lines
    assert res.code == 0 and "eval metrics" not in res.err
    assert "debug: eval: cooperative NH-inf, uav1:" in res.err and "ATE RMSE" in res.err


# --------------------------------------------------------------------------- Ctrl-C


@pytest.fixture(scope="module")
def long_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """600 stereo pairs: ~5 s of work for 2 workers on an idle machine (15 ms per frame)."""
    path = tmp_path_factory.mktemp("ctrl_c") / "a.mcap"
    return write_stereo_log(path, n_frames=600, size=(320, 240), fx=200.0).path


@pytest.mark.parametrize("delay_s", [0.0, 2.0])  # as the workers start; as they work
def test_ctrl_c_with_workers_exits_130_with_one_line(tmp_path, long_log, delay_s):
    args = ["extract", long_log, "-o", tmp_path / "r", "--workers", "2", "-v"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "cvslam_cli", *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a shell gives a command
        preexec_fn=default_sigint,
    )
    seen = []
    while not seen or "worker process(es)" not in seen[-1]:  # the pool is about to start
        seen.append(proc.stderr.readline())
        assert seen[-1], "".join(seen)
    time.sleep(delay_s)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C does: the whole foreground group
    _, err = proc.communicate(timeout=120)
    err = "".join(seen) + err
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines()[-1] == "cvslam: interrupted" and err.count("interrupted") == 1
    assert not (tmp_path / "r" / "features" / "uav1.npz").exists()


def test_ctrl_c_while_the_command_line_loads_is_one_line(monkeypatch, capsys):
    import importlib.abc

    from cvslam_cli.__main__ import main

    class CtrlC(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name == "cvslam_cli.cli":
                raise KeyboardInterrupt  # as if Ctrl-C came while it imports
            return None

    monkeypatch.delitem(sys.modules, "cvslam_cli.cli")
    monkeypatch.setattr(sys, "meta_path", [CtrlC(), *sys.meta_path])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 130 and capsys.readouterr().err == "cvslam: interrupted\n"
    assert 'cvslam = "cvslam_cli.__main__:main"' in (REPO / "pyproject.toml").read_text()


# --------------------------------------------------------------------------- completion


def test_shell_completion_as_documented():
    from click.shell_completion import ShellComplete

    complete = ShellComplete(cli, {}, "cvslam", "_CVSLAM_COMPLETE")
    assert "config" in [c.value for c in complete.get_completions([], "con")]
    keys = [c.value for c in complete.get_completions(["config", "show"], "fuse.hinf.g")]
    assert keys == ["fuse.hinf.gamma", "fuse.hinf.gamma_margin"]
    options = [c.value for c in complete.get_completions(["fuse", "run1"], "--verb")]
    assert options == ["--verbose"]
    proc = subprocess.run(
        [sys.executable, "-m", "cvslam_cli"],
        env={**os.environ, "_CVSLAM_COMPLETE": "bash_source"},
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0 and "_cvslam_completion()" in proc.stdout
    assert "_CVSLAM_COMPLETE=bash_source cvslam" in (REPO / "docs" / "cli.md").read_text()
