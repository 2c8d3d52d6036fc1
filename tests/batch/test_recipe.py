"""Recipes (`datasets/*.yaml`) and sweep grids: parsing, checks, the command lines made."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cvslam_cli.batch.recipe import load_recipe, recipe_steps
from cvslam_cli.batch.runner import plan_batch
from cvslam_cli.batch.sweep import grid_axes, sweep_recipes
from cvslam_cli.config import load_config
from cvslam_cli.errors import ConfigError, CvslamError
from cvslam_cli.sim.scenario import resolve_scenario_path

REPO = Path(__file__).resolve().parent.parent.parent
SHIPPED = sorted((REPO / "datasets").glob("*.yaml"))


def test_the_shipped_recipes_cover_the_data_at_hand():
    names = {p.stem for p in SHIPPED}
    assert names == {
        "kitti_clip_a", "kitti_clip_b", "euroc_v101_micro", "uav2_paper_seed1",
        "uav2_paper_seed2", "uav2_paper_seed3", "ugv2_yard", "uav4_team", "mixed_yard",
    }  # fmt: skip


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_recipe_is_valid(path, tmp_path, monkeypatch):
    monkeypatch.setenv("CVSLAM_SHARED_DATA", "/data")
    recipe = load_recipe(path)
    assert recipe.description
    load_config(recipe.config_files, recipe.overrides)  # its config and overrides are valid
    steps = recipe_steps(recipe, tmp_path / "runs", tmp_path / "gen")
    for src in recipe.logs:
        if src.kind == "import":
            assert src.options["path"].startswith("/data/")
        if src.kind == "simulate":
            assert resolve_scenario_path(Path(src.target)).is_file()
    for step in steps.sources:  # generated logs go under the generated folder, never in git
        assert step.out.is_relative_to(tmp_path / "gen" / recipe.name)
    argv = steps.run_argv()
    assert argv[0] == "run" and argv[argv.index("-o") + 1] == str(tmp_path / "runs" / path.stem)
    assert f'run.dataset="{path.stem}"' in argv


def _write(tmp_path: Path, data: object, name: str = "r.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    "data, expected",
    [
        ({"logs": []}, "logs: expected a non-empty list"),
        ({"logs": [{"file": "a.mcap"}], "colour": 1}, "colour: unknown key"),
        ({"logs": [{"file": "a.mcap", "import": "kitti"}]}, "logs[0]: expected exactly one of"),
        ({"logs": [{"import": "tum", "path": "x", "vehicle": "v"}]}, "logs[0].import: expected"),
        ({"logs": [{"import": "kitti", "path": "x"}]}, "logs[0].vehicle: expected a string"),
        ({"logs": [{"simulate": "uav2_paper", "seed": "one"}]}, "logs[0].seed: expected an int"),
        ({"logs": [{"simulate": "uav2_paper", "speed": 2}]}, "logs[0].speed: unknown key"),
        ({"logs": [{"file": "a.mcap"}], "mosaic": "yes"}, "mosaic: expected true or false"),
        ({"logs": [{"file": "a.mcap", "vehicle": 3}]}, "logs[0].vehicle: expected a string"),
        ({"logs": [{"file": "a.mcap"}], "set": [3]}, "set: expected a list of strings"),
    ],
)
def test_a_bad_recipe_is_one_line_naming_the_file_and_key(tmp_path, data, expected):
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as exc:
        load_recipe(path)
    assert str(exc.value).startswith(f"{path}: ") and expected in str(exc.value)
    assert "\n" not in str(exc.value)


def test_paths_are_relative_to_the_recipe_and_options_become_overrides(tmp_path):
    path = _write(
        tmp_path,
        {
            "description": "two bags of one mission",
            "logs": [{"file": "bags/a.mcap"}, {"file": "/abs/b.mcap", "vehicle": "tb3"}],
            "config": ["cfg.yaml"],
            "vehicles": {"tb3": {"kind": "ugv"}},
            "comparisons": ["single"],
            "mosaic": False,
            "ground_truth": ["tb3=gt/tb3.tum"],
        },
    )
    recipe = load_recipe(path)
    argv = recipe_steps(recipe, tmp_path / "runs", tmp_path / "gen").run_argv()
    assert argv[1:3] == [str(tmp_path / "bags" / "a.mcap"), "tb3=/abs/b.mcap"]
    assert ["--config", str(tmp_path / "cfg.yaml")] == argv[argv.index("--config") :][:2]
    assert f"tb3={tmp_path / 'gt' / 'tb3.tum'}" in argv
    cfg = load_config((), recipe.overrides)
    assert cfg.run.comparisons == ("single",) and cfg.run.mosaic is False
    assert cfg.logs.vehicles["tb3"].kind == "ugv"


def test_sweep_points_are_named_by_their_overrides_and_share_the_logs(tmp_path):
    recipe = load_recipe(_write(tmp_path, {"logs": [{"simulate": "uav2_paper"}]}, "m.yaml"))
    points = sweep_recipes(recipe, ["fuse.filter=hinf,ekf", "eval.align=none,se3"])
    assert [p.name for p in points] == [
        "m__fuse.filter=hinf__eval.align=none", "m__fuse.filter=hinf__eval.align=se3",
        "m__fuse.filter=ekf__eval.align=none", "m__fuse.filter=ekf__eval.align=se3",
    ]  # fmt: skip
    assert points[3].overrides[-2:] == ("fuse.filter=ekf", "eval.align=se3")
    steps = plan_batch(points, tmp_path / "runs", tmp_path / "gen", workers=1)
    assert {s.generated_dir for s in steps} == {tmp_path / "gen" / "m"}
    assert len({s.run_dir for s in steps}) == 4
    for bad, expected in [
        ("fuse.filter", "expected KEY.PATH=V1,V2"),
        ("fuse.filter=a,,b", "expected KEY.PATH=V1,V2"),
    ]:
        with pytest.raises(ConfigError, match=expected):
            grid_axes([bad])
    with pytest.raises(ConfigError, match="given twice"):
        grid_axes(["a.b=1", "a.b=2"])


def test_two_recipes_of_one_name_are_refused(tmp_path):
    (tmp_path / "x").mkdir()
    a = load_recipe(_write(tmp_path, {"logs": [{"file": "a.mcap"}]}, "same.yaml"))
    b = load_recipe(_write(tmp_path / "x", {"logs": [{"file": "a.mcap"}]}, "same.yaml"))
    with pytest.raises(CvslamError, match="a recipe named 'same' is given twice"):
        plan_batch([a, b], tmp_path / "runs", tmp_path / "gen", workers=1)


def test_tune_params_parse_and_bad_ones_name_the_option():
    from cvslam_cli.batch.tune import Param, parse_param

    assert parse_param("fuse.hinf.gamma=2:20:log") == Param("fuse.hinf.gamma", 2.0, 20.0, "log")
    assert parse_param("a.b=1:5:int").scale == "int" and parse_param("a.b=0:1").scale == "linear"
    for bad in ("a.b", "a.b=1", "a.b=5:1", "a.b=0:1:log", "a.b=1:2:cubic", "a.b=x:2", "=1:2"):
        with pytest.raises(ConfigError, match=r"--param "):
            parse_param(bad)
