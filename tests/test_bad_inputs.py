"""Bad inputs of issue 16: each one clear line naming the file, topic or option and what was
wrong (exit 1), found before the work where it can be, nothing that looks finished left."""

from __future__ import annotations

import os
import shutil
import stat

import pytest

from cvslam_cli.io.atomic import OutputError, atomic_dir, check_writable, write_text_atomic


@pytest.fixture
def run(small_image_run, tmp_path):
    """A copy of the session's small extracted and fused run."""
    dst = tmp_path / "run"
    shutil.copytree(small_image_run, dst)
    return dst


def _one_line(res, *needles):
    assert res.code == 1, res.err
    assert "Traceback" not in res.err
    last = res.err.strip().splitlines()[-1]
    assert last.startswith("cvslam: error: ")
    for n in needles:
        assert str(n) in last, last
    return last


# -- feature files, logs and trajectories given to the stages ------------------------------


@pytest.mark.parametrize("cut", ["half", "empty"])
def test_damaged_feature_file_is_named(run, cvslam, cut):
    f = run / "features" / "uav1.npz"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2] if cut == "half" else b"")
    _one_line(cvslam("-q", "fuse", run, "--force"), f, "not a readable feature file")


def test_missing_log_given_to_fuse_and_mosaic(run, cvslam, tmp_path):
    missing = tmp_path / "nope.mcap"
    _one_line(cvslam("-q", "fuse", run, "--force", "--log", missing), missing, "file not found")
    _one_line(cvslam("-q", "mosaic", run, "--log", missing), missing, "file not found")


def test_binary_ground_truth_file(run, cvslam, tmp_path):
    gt = tmp_path / "uav1.tum"
    gt.write_bytes(bytes(range(256)) * 8)
    _one_line(cvslam("-q", "eval", run, "--gt", gt), gt, "not a UTF-8 text file")


@pytest.mark.parametrize("gsd", ["inf", "-inf", "nan", "0"])
def test_mosaic_gsd_must_be_finite_and_positive(run, cvslam, gsd):
    _one_line(cvslam("-q", "mosaic", run, "--gsd", gsd), "--gsd", "finite")
    assert not (run / "mosaic").exists()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--duration", "inf"], "--duration: expected a finite"),
        (["--duration", "nan"], "--duration: expected a finite"),
        (["--seed", "-1"], "--seed: expected an integer >= 0"),
    ],
)
def test_simulate_duration_and_seed(cvslam, tmp_path, args, needle):
    from tests.scenarios import small_uav_scenario

    sc = small_uav_scenario(tmp_path)
    _one_line(cvslam("-q", "simulate", sc, "-o", tmp_path / "out", *args), needle)
    assert not (tmp_path / "out").exists()


# -- outputs ----------------------------------------------------------------------------------


def test_output_under_a_regular_file(run, cvslam, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    logs = sorted(run.glob("*.mcap"))
    _one_line(cvslam("-q", "extract", *logs, "-o", afile / "run"), afile, "is a file, not a folder")
    from tests.scenarios import small_uav_scenario

    sc = small_uav_scenario(tmp_path)
    _one_line(cvslam("-q", "simulate", sc, "-o", afile / "sim"), "is a file, not a folder")
    assert afile.read_text() == "x"


def test_over_long_vehicle_name_is_found_before_the_work(tmp_path, cvslam):
    from tests.synth import write_stereo_log

    name = "v" * 250  # fits a topic, not a file name with its suffixes
    log = write_stereo_log(tmp_path / "a.mcap", vehicle=name, n_frames=3).path
    res = cvslam("-q", "extract", log, "-o", tmp_path / "run")
    _one_line(res, "File name too long")
    assert not list((tmp_path / "run").glob("features/*.npz"))


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder_is_found_before_the_work(run, cvslam):
    features = run / "features"
    os.chmod(features, stat.S_IRUSR | stat.S_IXUSR)
    try:
        _one_line(
            cvslam("-q", "extract", *sorted(run.glob("*.mcap")), "-o", run, "--force"),
            "Permission denied",
        )
    finally:
        os.chmod(features, stat.S_IRWXU)


def test_check_writable_tries_the_partial_and_leaves_nothing(tmp_path):
    target = tmp_path / "a" / "b" / "x.csv"
    check_writable([target])
    assert not list(tmp_path.iterdir())  # the folders it made are gone again
    with pytest.raises(OutputError, match="too long"):
        check_writable([tmp_path / ("n" * 300)])


def test_writes_never_replace_what_is_not_a_regular_file(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "elsewhere.txt")
    for path, kind in ((fifo, "a pipe"), (link, "a symbolic link"), (tmp_path, "a folder")):
        with pytest.raises(OutputError, match=f"is {kind}, not a regular file"):
            write_text_atomic(path, "x")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and link.is_symlink()
    assert not (tmp_path / "elsewhere.txt").exists()
    with pytest.raises(OutputError, match="a pipe"), atomic_dir(fifo):
        pass
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not list(tmp_path.glob("*.partial"))


def test_import_refuses_to_overwrite_without_force(tmp_path, cvslam):
    out = tmp_path / "existing.mcap"
    out.write_bytes(b"precious")
    res = cvslam("-q", "import", "kitti", tmp_path / "no_such_sequence", "-o", out)
    _one_line(res, out, "already exists (use --force to replace it)")
    assert out.read_bytes() == b"precious"
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    res = cvslam("-q", "import", "kitti", tmp_path / "no_such_sequence", "-o", fifo, "--force")
    _one_line(res, fifo, "is a pipe, not a regular file")
    # with --force and a regular file the import itself runs (and here finds no sequence)
    res = cvslam("-q", "import", "kitti", tmp_path / "no_such_sequence", "-o", out, "--force")
    _one_line(res, "no_such_sequence", "not found")


def test_extract_of_a_log_whose_images_never_pair_exits_1(tmp_path, cvslam):
    from tests.synth import write_stereo_log

    log = write_stereo_log(tmp_path / "a.mcap", n_frames=5, right_offset_ns=30_000_000).path
    res = cvslam("-q", "extract", log, "-o", tmp_path / "run")
    _one_line(res, "vehicle uav1: no stereo pairs", "stereo_pair_tolerance_ms = 2 ms", "5 left")
    assert not list((tmp_path / "run").glob("features/*"))


def test_read_only_file_system_is_found_before_the_work(run, cvslam, monkeypatch):
    """(As root a read-only folder is writable; a read-only file system is not: simulated.)"""
    import errno

    import cvslam_cli.features.stage as extract_stage

    real_open = os.open

    def read_only(path, flags, *args):
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *args)

    def no_work(*args, **kwargs):
        raise AssertionError("the work started before the outputs were checked")

    monkeypatch.setattr(os, "open", read_only)
    monkeypatch.setattr(extract_stage, "_extract", no_work)
    logs = sorted(run.glob("*.mcap"))
    res = cvslam("-q", "extract", *logs, "-o", run, "--force")
    _one_line(res, run / "features", "Read-only file system")
