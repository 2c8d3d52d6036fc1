"""Config loading: defaults file, validation messages, overrides, vehicle merging."""

from __future__ import annotations

import dataclasses
import re

import pytest
import yaml

from cvslam_cli.config import DEFAULT_CONFIG_PATH, Config, dump_config, load_config, to_dict
from cvslam_cli.errors import ConfigError


def _leaf_paths(d, prefix=""):
    for k, v in d.items():
        path = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict) and v:
            yield from _leaf_paths(v, path)
        else:
            yield path


def test_default_yaml_equals_dataclass_defaults():
    assert load_config([DEFAULT_CONFIG_PATH]) == Config()
    on_disk = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    assert sorted(_leaf_paths(on_disk)) == sorted(_leaf_paths(to_dict(Config())))


def test_default_yaml_documents_every_key():
    lines = DEFAULT_CONFIG_PATH.read_text().splitlines()
    key_re = re.compile(r"^(\s*)([A-Za-z_]+):")
    for i, line in enumerate(lines):
        m = key_re.match(line)
        if not m:
            continue
        # a comment on the line before, or the key belongs to a group whose earlier sibling
        # carries the comment (width/height, fx..cy, the right camera's keys)
        window = lines[max(0, i - 10) : i]
        assert any(w.strip().startswith("#") for w in window), f"undocumented: {line}"


def test_resolved_config_round_trips_through_yaml(tmp_path):
    cfg = load_config(overrides=["logs.stereo_pair_tolerance_ms=4.5", "logs.vehicles.tb3.kind=ugv"])
    path = tmp_path / "resolved.yaml"
    path.write_text(dump_config(cfg))
    assert load_config([path]) == cfg


def test_vehicle_entries_merge_over_defaults(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text(
        "logs:\n  vehicle_defaults:\n    topics:\n      imu: /{vehicle}/imu0\n"
        "  vehicles:\n    a: {kind: ugv}\n    b: {topics: {odom: /wheels}}\n"
    )
    cfg = load_config([f])
    assert cfg.logs.vehicles["a"].kind == "ugv"
    assert cfg.logs.vehicles["a"].topics.imu == "/{vehicle}/imu0"
    assert cfg.logs.vehicles["b"].topics.odom == "/wheels"
    assert cfg.logs.vehicles["b"].topics.imu == "/{vehicle}/imu0"
    assert dataclasses.is_dataclass(cfg.logs.vehicles["b"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.logs.gap_factor = 2.0  # type: ignore[misc]


def test_later_sources_override_earlier(tmp_path):
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text("logs: {gap_factor: 4.0, reorder_window_ms: 10}\n")
    b.write_text("logs: {gap_factor: 5.0}\n")
    cfg = load_config([a, b], ["logs.reorder_window_ms=20"])
    assert (cfg.logs.gap_factor, cfg.logs.reorder_window_ms) == (5.0, 20.0)


@pytest.mark.parametrize(
    "text, message",
    [
        ("logs: {colour: red}\n", "c.yaml: logs.colour: unknown key"),
        (
            "logs: {gap_factor: fast}\n",
            "c.yaml: logs.gap_factor: expected a number > 1.0, got 'fast'",
        ),
        ("logs: {gap_factor: 0.5}\n", "c.yaml: logs.gap_factor: expected a number > 1.0, got 0.5"),
        (
            "logs: {stereo_pair_tolerance_ms: -1}\n",
            "c.yaml: logs.stereo_pair_tolerance_ms: expected a number >= 0.0, got -1",
        ),
        (
            "logs: {vehicles: {a: {kind: boat}}}\n",
            "c.yaml: logs.vehicles.a.kind: expected one of 'uav', 'ugv', got 'boat'",
        ),
        (
            "logs: {vehicles: {a: {rig: {left: {width: 1.5}}}}}\n",
            "c.yaml: logs.vehicles.a.rig.left.width: expected an integer >= 0, got 1.5",
        ),
        (
            "logs: {vehicle_defaults: {rig: {left: {distortion: [1, x]}}}}\n",
            "c.yaml: logs.vehicle_defaults.rig.left.distortion[1]: expected a number, got 'x'",
        ),
        ("logs: {tf_static_topic: true}\n", "c.yaml: logs.tf_static_topic: expected a string"),
        (
            "fuse: {association: {pixel_sigma_px: -1}}\n",
            "c.yaml: fuse.association.pixel_sigma_px: expected 'auto' or a number > 0.0, got -1",
        ),
        (
            "fuse: {association: {pixel_sigma_px: measured}}\n",
            "c.yaml: fuse.association.pixel_sigma_px: expected 'auto' or a number > 0.0, got "
            "'measured'",
        ),
        (
            "fuse: {association: {octave_bearing_variance: [1, 0]}}\n",
            "c.yaml: fuse.association.octave_bearing_variance: expected 'auto' or a list of "
            "numbers > 0.0, got [1, 0]",
        ),
        ("- just\n- a list\n", "c.yaml: expected a YAML mapping (a config file), got list"),
        ("logs: {a: [1, 2\n", "c.yaml: not valid YAML"),
    ],
)
def test_bad_config_file_gives_one_line_naming_file_and_key(tmp_path, text, message):
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config([f])
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_bad_overrides_name_the_option():
    with pytest.raises(ConfigError, match=r"^--set logs.gap_factor=x: logs.gap_factor: expected"):
        load_config(overrides=["logs.gap_factor=x"])
    with pytest.raises(ConfigError, match=r"expected key\.path=value"):
        load_config(overrides=["logs.gap_factor"])
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(overrides=["nothing.here=1"])
    with pytest.raises(ConfigError, match=r"file\.yaml: not found, expected a config file"):
        load_config(["/no/such/file.yaml"])


def test_numbers_in_exponent_notation_are_numbers(tmp_path):
    # PyYAML resolves YAML 1.1, where 1e-9 (no decimal point) is a string
    f = tmp_path / "c.yaml"
    f.write_text("fuse: {hinf: {gamma: 3E+1}}\n")
    cfg = load_config([f], ["fuse.association.iterate_sigma_ratio=1e-9"])
    assert cfg.fuse.association.iterate_sigma_ratio == 1e-9
    assert cfg.fuse.hinf.gamma == 30.0
    # still checked as numbers, and shown as written
    with pytest.raises(
        ConfigError, match=r"fuse\.hinf\.gamma: expected a number > 0\.0, got '-1e3'"
    ):
        load_config(overrides=["fuse.hinf.gamma=-1e3"])
    with pytest.raises(ConfigError, match=r"got '1e-9x'"):
        load_config(overrides=["fuse.hinf.gamma=1e-9x"])
    with pytest.raises(ConfigError, match=r"expected an integer >= 0, got '1e3'"):
        load_config(overrides=["logs.vehicle_defaults.rig.left.width=1e3"])


# -- values checked where they enter (issue 16) ------------------------------------------------


@pytest.mark.parametrize(
    "override",
    [
        "logs.stereo_pair_tolerance_ms=.inf",
        "logs.reorder_window_ms=-.inf",
        "extract.stereo.pixel_sigma_px=.inf",
        "extract.stereo.z_min_m=.inf",
        "fuse.hinf.gamma=.nan",
    ],
)
def test_infinite_and_nan_values_are_refused_naming_the_key(override):
    key = override.split("=")[0]
    with pytest.raises(
        ConfigError, match=rf"--set {re.escape(override)}: {key}: expected a finite"
    ):
        load_config(overrides=[override])


def test_min_above_max_is_refused_naming_both_keys_and_the_source(tmp_path):
    with pytest.raises(
        ConfigError,
        match=r"--set extract.adaptive.layers_min=9: extract.adaptive.layers_min = 9 is above "
        r"extract.adaptive.layers_max = 6",
    ):
        load_config(overrides=["extract.adaptive.layers_min=9"])
    f = tmp_path / "c.yaml"
    f.write_text("extract: {adaptive: {features_max: 100}}\n")
    with pytest.raises(ConfigError, match=rf"{f}: extract.adaptive.features_min = 150 is above"):
        load_config([f])
    with pytest.raises(ConfigError, match=r"contrast_min = 0\.5 is above"):
        load_config(overrides=["extract.adaptive.contrast_min=0.5"])
    # a pair moved together, in either order, is fine: only the resolved config is checked
    cfg = load_config(overrides=["extract.adaptive.layers_max=9", "extract.adaptive.layers_min=8"])
    assert (cfg.extract.adaptive.layers_min, cfg.extract.adaptive.layers_max) == (8, 9)


@pytest.mark.parametrize(
    ("name", "why"),
    [
        ("team/uav1", "cannot be part of a file name"),
        ("-rf", "cannot be part of a file name"),
        ("a" * 300, "300 bytes long"),
    ],
)
def test_vehicle_names_must_be_safe_file_names(name, why):
    with pytest.raises(ConfigError, match=rf"logs.vehicles.{re.escape(name[:20])}.*{why}"):
        load_config(overrides=[f"logs.vehicles.{name}.kind=uav"])
    assert load_config(overrides=["logs.vehicles.uav-1.kind=uav"]).logs.vehicles["uav-1"]


def test_a_value_of_several_kinds_takes_the_first_that_fits():
    """fuse.association.pixel_sigma_px: 'auto' (the default) or a number;
    fuse.observability_constrained: 'auto' (the default) or true / false."""
    assert load_config().fuse.association.pixel_sigma_px == "auto"
    cfg = load_config(overrides=["fuse.association.pixel_sigma_px=0.5"])
    assert cfg.fuse.association.pixel_sigma_px == 0.5
    assert load_config().fuse.observability_constrained == "auto"
    cfg = load_config(overrides=["fuse.observability_constrained=false"])
    assert cfg.fuse.observability_constrained is False
    cfg = load_config(overrides=["fuse.association.pixel_sigma_px=0.4"])
    assert cfg.fuse.association.pixel_sigma_px == 0.4
    cfg = load_config(overrides=["fuse.association.pixel_sigma_px=1"])
    assert cfg.fuse.association.pixel_sigma_px == 1.0
