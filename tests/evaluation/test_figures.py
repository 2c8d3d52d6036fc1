"""Report figures: sizes, plotted data, bands, RMSE labels, events, NaN, colours, saving."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from cvslam_cli.evaluation import figures as figs
from cvslam_cli.evaluation.figures import Series
from cvslam_cli.geometry.rotations import interpolate_positions

T0_NS = 1_700_000_000_000_000_000


def pixels(fig: Figure) -> tuple[int, int]:
    """(height, width) in pixels that `png_bytes` must render."""
    w, h = fig.get_size_inches() * figs.DPI
    return round(h), round(w)


def rendered(fig: Figure) -> np.ndarray:
    """Render through png_bytes; check the size; the image."""
    expected = pixels(fig)
    img = cv2.imdecode(np.frombuffer(figs.png_bytes(fig), np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape[:2] == expected
    return img


def patch_x(patch) -> tuple[float, float]:
    """Data x range of an axvspan (Polygon or Rectangle, whatever matplotlib made)."""
    x = patch.get_patch_transform().transform(patch.get_path().vertices)[:, 0]
    return float(x.min()), float(x.max())


def line_colour(line) -> str:
    return to_hex(line.get_color())


# --------------------------------------------------------------------------- data


def truth_series(vehicle: str = "uav1") -> Series:
    """Truth on 0.5 s stamps, linear in time (so interpolation is exact)."""
    t = np.arange(0.0, 10.01, 0.5)
    p = np.column_stack([2.0 * t, -1.0 * t + 5.0, np.full_like(t, -100.0)])
    return Series(vehicle, "ground truth", t, p)


def estimate_series(vehicle: str = "uav1", label: str = "cooperative NH-inf") -> Series:
    """Estimate on stamps 0.25, 1.25, ... (between the truth's), truth + 0.1 m north except
    at the first two stamps (+1.0 m north), sigma 0.1 m (NaN at the last stamp)."""
    t = np.arange(0.25, 9.3, 1.0)
    p = np.column_stack([2.0 * t, -1.0 * t + 5.0, np.full_like(t, -100.0)])
    p[:, 0] += 0.1
    p[:2, 0] += 0.9
    sigma = np.full((len(t), 3), 0.1)
    sigma[-1] = np.nan
    return Series(vehicle, label, t, p, sigma)


def timeline_frame() -> pd.DataFrame:
    rows = []
    for v, offset_s in (("uav1", 0.0), ("uav2", 2.0)):
        for i in range(6):
            rows.append(
                {
                    "stamp_ns": T0_NS + int((offset_s + i) * 1e9),
                    "vehicle": v,
                    "type1": i,
                    "type2": 2 * i if v == "uav2" else 0,
                    "type3": 10 - i,
                    "sigma_landmark_m": np.nan if i in (0, 3) else 1.0 / (i + 1),
                }
            )
    return pd.DataFrame(rows)


def events_frame() -> pd.DataFrame:
    return pd.DataFrame(
        {
            "stamp_ns": [T0_NS + 2_500_000_000, T0_NS + 4_000_000_000, T0_NS + 3_000_000_000],
            "end_stamp_ns": [T0_NS + 4_500_000_000, T0_NS + 4_200_000_000, T0_NS + 3_000_000_000],
            "event": ["cross_vehicle", "loop_closure", "joint_initialisation"],
            "vehicle": ["uav2", "uav1", "uav2"],
        }
    )


# --------------------------------------------------------------------------- Series


def test_series_checks_shapes_and_stamps() -> None:
    with pytest.raises(ValueError, match="p_m"):
        Series("uav1", "x", np.arange(3.0), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="increasing"):
        Series("uav1", "x", np.array([0.0, 1.0, 1.0]), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="sigma_m"):
        Series("uav1", "x", np.arange(3.0), np.zeros((3, 3)), np.zeros((2, 3)))


def test_positions_at_interpolates_without_extrapolating() -> None:
    truth = truth_series()
    got = interpolate_positions(truth.t_s, truth.p_m, np.array([-0.1, 0.25, 10.0, 10.1]))
    np.testing.assert_allclose(got[1], [0.5, 4.75, -100.0])
    np.testing.assert_allclose(got[2], truth.p_m[-1])
    assert np.isnan(got[[0, 3]]).all()


# --------------------------------------------------------------------------- Fig. 10


def test_position_components_plots_inputs_and_band() -> None:
    truth, est = truth_series(), estimate_series()
    dr = Series("uav1", "dead reckoning", truth.t_s, truth.p_m * 1.1)
    fig = figs.position_components(truth, est, dr)
    assert len(fig.axes) == 3
    for ax, k, sign in zip(fig.axes, (0, 1, 2), (1.0, 1.0, -1.0), strict=True):
        truth_line, dr_line, est_line = ax.lines
        np.testing.assert_array_equal(truth_line.get_xdata(), truth.t_s)
        np.testing.assert_array_equal(truth_line.get_ydata(), sign * truth.p_m[:, k])
        np.testing.assert_array_equal(dr_line.get_xdata(), dr.t_s)
        np.testing.assert_array_equal(dr_line.get_ydata(), sign * dr.p_m[:, k])
        np.testing.assert_array_equal(est_line.get_xdata(), est.t_s)
        np.testing.assert_array_equal(est_line.get_ydata(), sign * est.p_m[:, k])
        # the band: at every stamp with a sigma, exactly estimate -+ 3 sigma
        verts = np.concatenate([p.vertices for p in ax.collections[0].get_paths()])
        for t, y, s in zip(est.t_s, sign * est.p_m[:, k], est.sigma_m[:, k], strict=True):
            at = verts[np.isclose(verts[:, 0], t), 1]
            if np.isnan(s):
                assert at.size == 0
            else:
                np.testing.assert_allclose([at.min(), at.max()], [y - 3 * s, y + 3 * s])
    # north: truth outside the band at the first 2 of the 9 stamps with a sigma; east and
    # height inside everywhere (truth interpolated at the estimate's stamps)
    notes = [ax.get_title(loc="right") for ax in fig.axes]
    assert notes == ["truth inside ±3σ: 78%", "truth inside ±3σ: 100%", "truth inside ±3σ: 100%"]
    assert "height" in fig.axes[2].get_ylabel() and "north" in fig.axes[0].get_ylabel()
    rendered(fig)


def test_position_components_without_dead_reckoning_or_sigma() -> None:
    truth, est = truth_series(), estimate_series()
    bare = Series(est.vehicle, est.label, est.t_s, est.p_m)
    fig = figs.position_components(truth, bare, None)
    for ax in fig.axes:
        assert len(ax.lines) == 2 and not ax.collections
        assert ax.get_title(loc="right") == ""
    with pytest.raises(ValueError, match="different vehicles"):
        figs.position_components(truth_series("uav2"), est)


# --------------------------------------------------------------------------- Fig. 11


def test_top_view_paths_landmarks_and_aspect() -> None:
    truths = [truth_series("uav1"), truth_series("uav2")]
    tracks = [estimate_series("uav1"), estimate_series("uav2")]
    lm = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]])
    observers = ["uav1", "uav2;uav1", "uav2", "uav1"]
    fig = figs.top_view(tracks, truths, lm, observers)
    (ax,) = fig.axes
    colours = figs.vehicle_colours(["uav1", "uav2"])
    assert len(ax.lines) == 4
    for line, s, ls in zip(ax.lines, [*truths, *tracks], ["--", "--", "-", "-"], strict=True):
        np.testing.assert_array_equal(line.get_xdata(), s.p_m[:, 1])  # east right
        np.testing.assert_array_equal(line.get_ydata(), s.p_m[:, 0])  # north up
        assert line.get_linestyle() == ls and line_colour(line) == colours[s.vehicle]
    by_label = {c.get_label(): c for c in ax.collections}
    np.testing.assert_array_equal(
        by_label["landmarks seen by uav1 only"].get_offsets(), [[2.0, 1.0], [8.0, 7.0]]
    )
    np.testing.assert_array_equal(
        by_label["landmarks seen by several vehicles"].get_offsets(), [[4.0, 3.0]]
    )
    assert to_hex(by_label["landmarks seen by uav2 only"].get_facecolor()[0]) == colours["uav2"]
    assert to_hex(by_label["landmarks seen by several vehicles"].get_facecolor()[0]) == (
        figs.SHARED_LANDMARK_COLOUR
    )
    np.testing.assert_array_equal(
        by_label["start"].get_offsets(), [[t.p_m[0, 1], t.p_m[0, 0]] for t in tracks]
    )
    assert ax.get_aspect() == 1.0
    assert ax.get_xlabel().startswith("east") and ax.get_ylabel().startswith("north")
    rendered(fig)


def test_top_view_dead_reckoning_dotted_and_checks_lengths() -> None:
    truth = truth_series()
    dr = Series("uav1", "dead reckoning", truth.t_s, truth.p_m)
    fig = figs.top_view([dr], [], np.zeros((0, 2)), [])
    assert fig.axes[0].lines[0].get_linestyle() == ":"
    with pytest.raises(ValueError, match="observer"):
        figs.top_view([dr], [], np.zeros((2, 2)), ["uav1"])


# --------------------------------------------------------------------------- Fig. 12


def test_landmark_uncertainty_lines_nan_and_events() -> None:
    timeline = timeline_frame().iloc[::-1]  # stamp order restored per vehicle
    fig = figs.landmark_uncertainty(timeline, events_frame(), T0_NS)
    (ax,) = fig.axes
    tl = timeline_frame()
    vehicle_lines = ax.lines[:2]
    assert [line.get_label() for line in vehicle_lines] == ["uav2", "uav1"]  # first appearance
    for line in vehicle_lines:
        rows = tl[tl["vehicle"] == line.get_label()]
        np.testing.assert_allclose(line.get_xdata(), (rows["stamp_ns"] - T0_NS) / 1e9)
        np.testing.assert_array_equal(line.get_ydata(), rows["sigma_landmark_m"])  # NaN kept
    # one loop closure line at 4.0 s (uav1's colour), one cross-vehicle span 2.5-4.5 s
    colours = figs.vehicle_colours(["uav1", "uav2"])
    (loop,) = ax.lines[2:]
    np.testing.assert_allclose(loop.get_xdata(), [4.0, 4.0])
    assert line_colour(loop) == colours["uav1"] and loop.get_label() == "loop closure (uav1)"
    (span,) = ax.patches
    np.testing.assert_allclose(patch_x(span), (2.5, 4.5))
    assert to_hex(span.get_facecolor()) == colours["uav2"]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "uav2 re-observes another vehicle's landmarks" in labels
    rendered(fig)


def test_landmark_uncertainty_labels_each_kind_once_and_needs_columns() -> None:
    ev = events_frame()
    twice = pd.concat(
        [ev, ev.assign(stamp_ns=ev["stamp_ns"] + 1, end_stamp_ns=ev["end_stamp_ns"] + 1)]
    )
    fig = figs.landmark_uncertainty(timeline_frame(), twice, T0_NS)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert len(labels) == len(set(labels)) == 4
    with pytest.raises(ValueError, match="sigma_landmark_m"):
        figs.landmark_uncertainty(timeline_frame().drop(columns="sigma_landmark_m"), ev, T0_NS)


# --------------------------------------------------------------------------- Figs. 13, 17


def test_error_over_time_errors_and_rmse_labels() -> None:
    truth = truth_series()
    est = estimate_series()
    single = Series("uav1", "single NH-inf", est.t_s, est.p_m + np.array([0.0, 0.3, 0.4]))
    fig = figs.error_over_time(truth, [est, single], "uav1: single vs cooperative")
    (ax,) = fig.axes
    err_est = np.full(len(est.t_s), 0.1)
    err_est[:2] = 1.0
    err_single = np.hypot(err_est, 0.5)
    for line, s, err in zip(ax.lines, (est, single), (err_est, err_single), strict=True):
        np.testing.assert_array_equal(line.get_xdata(), s.t_s)
        np.testing.assert_allclose(line.get_ydata(), err, atol=1e-12)
        rmse = np.sqrt(np.mean(err**2))
        assert line.get_label() == f"{s.label}: RMSE {rmse:.3f} m"
        assert line_colour(line) == figs.run_colour(s.label)
    assert ax.get_yscale() == "linear" and ax.get_title() == "uav1: single vs cooperative"
    rendered(fig)


def test_error_over_time_outside_truth_is_nan_and_log_for_dead_reckoning() -> None:
    truth = truth_series()  # 0 .. 10 s
    t = np.array([9.0, 10.0, 11.0, 12.0])
    late = Series(
        "uav1", "cooperative NH-inf", t, np.column_stack([2 * t + 1, 5 - t, -100 + 0 * t])
    )
    dr = Series("uav1", "dead reckoning", t, late.p_m + np.array([100.0, 0.0, 0.0]))
    fig = figs.error_over_time(truth, [late, dr], "x")
    (ax,) = fig.axes
    np.testing.assert_allclose(ax.lines[0].get_ydata(), [1.0, 1.0, np.nan, np.nan])
    assert ax.lines[0].get_label() == "cooperative NH-inf: RMSE 1.000 m"
    assert ax.lines[1].get_label() == "dead reckoning: RMSE 101.000 m"
    assert ax.get_yscale() == "log"
    with pytest.raises(ValueError, match="other vehicles"):
        figs.error_over_time(truth, [estimate_series("uav2")], "x")


# --------------------------------------------------------------------------- feature types


def test_feature_counts_one_axis_per_vehicle() -> None:
    tl = timeline_frame()
    fig = figs.feature_counts(tl, T0_NS)
    assert len(fig.axes) == 2
    assert pixels(fig) == (
        round((figs.FEATURES_EXTRA_IN + 2 * figs.FEATURES_ROW_IN) * figs.DPI),
        round(figs.FEATURES_WIDTH_IN * figs.DPI),
    )
    colours = figs.vehicle_colours(["uav1", "uav2"])
    for ax, v in zip(fig.axes, ("uav1", "uav2"), strict=True):
        rows = tl[tl["vehicle"] == v]
        assert ax.get_title() == v and to_hex(ax.title.get_color()) == colours[v]
        assert len(ax.lines) == 3
        for line, column in zip(ax.lines, ("type1", "type2", "type3"), strict=True):
            np.testing.assert_allclose(line.get_xdata(), (rows["stamp_ns"] - T0_NS) / 1e9)
            np.testing.assert_array_equal(line.get_ydata(), rows[column])
    rendered(fig)


# --------------------------------------------------------------------------- NEES


def test_nees_band_log_axis_and_share_in_band() -> None:
    t = np.arange(5.0)
    nees = {"uav1": np.array([1.0, 2.0, 50.0, np.nan, 3.0]), "uav2": np.array([0.1, 2, 2, 2, 2.0])}
    fig = figs.nees_over_time(t, nees, (0.5, 9.0), 3)
    (ax,) = fig.axes
    assert ax.get_yscale() == "log"
    band = ax.patches[0].get_patch_transform().transform(ax.patches[0].get_path().vertices)
    np.testing.assert_allclose([band[:, 1].min(), band[:, 1].max()], [0.5, 9.0])
    assert [line.get_label() for line in ax.lines[:2]] == [
        "uav1 (75% in band)",
        "uav2 (80% in band)",
    ]
    np.testing.assert_array_equal(ax.lines[0].get_ydata(), nees["uav1"])
    np.testing.assert_array_equal(ax.lines[2].get_ydata(), [3.0, 3.0])  # expected value dof
    rendered(fig)
    with pytest.raises(ValueError, match="shape"):
        figs.nees_over_time(t, {"uav1": np.ones(4)}, (0.5, 9.0), 3)
    with pytest.raises(ValueError, match="band"):
        figs.nees_over_time(t, nees, (9.0, 0.5), 3)


def test_nees_lines_start_at_the_first_informative_value() -> None:
    """A filter started at the truth: NEES 1e-27, 1e-9 ... then ordinary values. With
    `informative_from` the line starts at the first value reaching it (later small ones
    stay), the label says how many were left out and the share in band counts them all; a
    series that never reaches it is drawn whole."""
    t = np.arange(8.0)
    start = np.array([1e-27, 1e-9, np.nan, 2.0, 0.001, 3.0, 1.0, 4.0])
    never = np.full(8, 1e-3)
    fig = figs.nees_over_time(
        t, {"uav1": start, "uav2": never}, (0.5, 9.0), 3, informative_from=0.024
    )
    (ax,) = fig.axes
    np.testing.assert_array_equal(ax.lines[0].get_xdata(), t[3:])
    np.testing.assert_array_equal(ax.lines[0].get_ydata(), start[3:])  # 0.001 later: kept
    assert ax.lines[0].get_label() == "uav1 (57% in band; 3 first poses < 0.024 not drawn)"
    np.testing.assert_array_equal(ax.lines[1].get_ydata(), never)
    assert ax.lines[1].get_label() == "uav2 (0% in band)"
    fig.canvas.draw()
    assert ax.get_ylim()[0] > 1e-5  # the axis no longer reaches down to 1e-27
    rendered(fig)
    assert figs.first_informative(start, None) == 0
    assert figs.first_informative(start, 2.5) == 5


def test_feature_counts_of_chosen_types() -> None:
    tl = timeline_frame()
    fig = figs.feature_counts(tl, T0_NS, types=("type1", "type3"))
    labels = [line.get_label() for line in fig.axes[0].lines]
    assert len(labels) == 2 and labels[0].startswith("type 1") and labels[1].startswith("type 3")
    with pytest.raises(ValueError, match="feature types"):
        figs.feature_counts(tl, T0_NS, types=("type4",))


# --------------------------------------------------------------------------- Figs. 19-21


def test_mosaics_scale_bar_is_a_round_length_in_pixels_of_the_gsd() -> None:
    grey = np.full((40, 300), 128, np.uint8)
    fig = figs.mosaics({"uav1": grey, "all": grey}, merged="all", gsd_m={"uav1": 0.5})
    bar_ax, plain_ax = fig.axes
    (bar,) = [a for a in bar_ax.artists if isinstance(a, AnchoredSizeBar)]
    assert not plain_ax.artists  # no GSD given: no bar
    # 300 px x 0.5 m = 150 m wide: a 20 m bar (largest 1/2/5 x 10^k <= a quarter), 40 px
    (rect,) = bar.size_bar.get_children()  # in data units: pixels
    assert rect.get_width() == pytest.approx(40.0)
    assert bar.txt_label.get_text() == "20 m"
    rendered(fig)
    with pytest.raises(ValueError, match="metres per pixel"):
        figs.mosaics({"uav1": grey}, merged="all", gsd_m={"uav1": 0.0})


def test_mosaics_convert_colours_and_keep_transparency() -> None:
    grey = np.full((40, 60), 128, np.uint8)
    bgr = np.zeros((40, 60, 3), np.uint8)
    bgr[..., 0] = 255  # blue in BGR
    bgra = np.zeros((60, 60, 4), np.uint8)
    bgra[:, 30:] = (0, 0, 255, 255)  # right half opaque red, left half no-data
    fig = figs.mosaics({"uav1": grey, "uav2": bgr, "all": bgra}, merged="all")
    assert len(fig.axes) == 3
    assert [ax.get_title() for ax in fig.axes][2].startswith("all vehicles (merged)")
    arrays = [np.asarray(ax.images[0].get_array()) for ax in fig.axes]
    np.testing.assert_array_equal(arrays[0], grey)
    np.testing.assert_array_equal(arrays[1][0, 0], [0, 0, 255])  # now RGB: blue
    np.testing.assert_array_equal(arrays[2][0, 59], [255, 0, 0, 255])  # RGBA: red
    np.testing.assert_array_equal(arrays[2][..., 3], bgra[..., 3])
    fig.canvas.draw()  # lays the figure out: where the merged mosaic lands
    box = fig.axes[2].images[0].get_window_extent()
    h = pixels(fig)[0]
    row = int(h - (box.y0 + box.y1) / 2)
    img = rendered(fig)
    left = img[row, int(box.x0 + 0.25 * box.width)]
    right = img[row, int(box.x0 + 0.75 * box.width)]
    np.testing.assert_array_equal(left[:3], [255, 255, 255])  # transparent: white figure
    np.testing.assert_array_equal(right[:3], [0, 0, 255])  # BGR red as read by cv2


def test_mosaics_reject_other_images() -> None:
    with pytest.raises(ValueError, match="uint8"):
        figs.mosaics({"uav1": np.zeros((4, 4), np.float32)}, merged="all")


# --------------------------------------------------------------------------- headline


def test_headline_bars_groups_runs_per_vehicle() -> None:
    table = pd.DataFrame(
        {
            "cooperative NH-inf": [1.19, 1.43],
            "single NH-inf": [np.nan, 2.5],
            "dead reckoning": [84.0, 55.1],
        },
        index=["uav1", "uav2"],
    )
    fig = figs.headline_bars(table)
    (ax,) = fig.axes
    bars = [c for c in ax.containers if hasattr(c, "patches")]
    assert len(bars) == 3
    for container, run in zip(bars, table.columns, strict=True):
        heights = [p.get_height() for p in container.patches]
        np.testing.assert_allclose(heights, np.nan_to_num(table[run].to_numpy()))
        assert all(to_hex(p.get_facecolor()) == figs.run_colour(run) for p in container.patches)
    texts = sorted(t.get_text() for t in ax.texts if t.get_text())
    assert texts == sorted(["1.19", "1.43", "2.50", "84.00", "55.10"])  # no label for NaN
    assert [t.get_text() for t in ax.get_xticklabels()] == ["uav1", "uav2"]
    rendered(fig)


# --------------------------------------------------------------------------- colours


def test_vehicle_colours_consistent_across_figures() -> None:
    colours = figs.vehicle_colours(["uav1", "uav2"])
    assert colours == {"uav1": "#1f77b4", "uav2": "#ff7f0e"}  # tab10, as the overlays
    tl, ev = timeline_frame(), events_frame()
    no_lm = (np.zeros((0, 2)), [])
    est2, truth2 = estimate_series("uav2"), truth_series("uav2")
    nees = {"uav1": np.ones(2), "uav2": np.ones(2)}
    seen = {
        "position": figs.position_components(truth2, est2).axes[0].lines[-1],
        "top": figs.top_view([est2], [], *no_lm).axes[0].lines[0],
        "sigma": figs.landmark_uncertainty(tl, ev, T0_NS).axes[0].lines[1],  # uav2
        "nees": figs.nees_over_time(np.arange(2.0), nees, (0.5, 2.0), 1).axes[0].lines[1],
        "features": figs.feature_counts(tl, T0_NS).axes[1].title,
    }
    got = {k: to_hex(a.get_color()) for k, a in seen.items()}
    # uav2 alone in a figure: the default gives it tab10[0]; with others, by name order
    assert got["position"] == got["top"] == colours["uav1"]
    assert got["sigma"] == got["nees"] == got["features"] == colours["uav2"]
    # the fleet's mapping keeps uav2 orange whatever the figure shows
    fleet = figs.vehicle_colours(["uav1", "uav2"])
    line = figs.position_components(truth2, est2, colours=fleet).axes[0].lines[-1]
    assert line_colour(line) == colours["uav2"]
    line = figs.top_view([est2], [], *no_lm, colours=fleet).axes[0].lines[0]
    assert line_colour(line) == colours["uav2"]
    with pytest.raises(ValueError, match="no colour"):
        figs.top_view([estimate_series("uav3")], [], *no_lm, colours=fleet)


def test_run_colours_fixed_for_known_labels() -> None:
    assert figs.run_colour("dead reckoning") == figs.DEAD_RECKONING_COLOUR
    assert figs.run_colour("a", ["a", "b"]) != figs.run_colour("b", ["a", "b"])
    assert figs.run_colour("b", ["cooperative NH-inf", "a", "b"]) == figs.run_colour(
        "b", ["a", "b"]
    )


# --------------------------------------------------------------------------- saving


def test_png_bytes_are_deterministic_and_close() -> None:
    def build() -> Figure:
        return figs.error_over_time(truth_series(), [estimate_series()], "x")

    fig = build()
    a = figs.png_bytes(fig)
    assert not fig.axes  # closed (cleared)
    assert a == figs.png_bytes(build())
    assert a.startswith(b"\x89PNG")


def test_nees_with_stamps_per_vehicle() -> None:
    t = {"uav1": np.arange(3.0), "uav2": np.arange(8.0, 10.0)}
    nees = {"uav1": np.array([1.0, 2.0, 3.0]), "uav2": np.array([20.0, 2.0])}
    fig = figs.nees_over_time(t, nees, (0.5, 9.0), 3)
    lines = fig.axes[0].lines
    for line, v in zip(lines[:2], ("uav1", "uav2"), strict=True):
        np.testing.assert_array_equal(line.get_xdata(), t[v])
        np.testing.assert_array_equal(line.get_ydata(), nees[v])
    assert lines[1].get_label() == "uav2 (50% in band)"
