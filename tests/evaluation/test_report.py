"""The HTML report: self-contained (every image a data URI), the tables (the metrics cut per
family, every table in a sideways-scrolling box), the config folded away, checked without
a browser by parsing the page, and a render check in headless Chromium (skipped where
Chromium is not installed)."""

from __future__ import annotations

import base64
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from cvslam_cli.evaluation.report import (
    METRIC_GROUPS,
    OTHER_METRICS,
    FigureEntry,
    metric_groups,
    render_report,
)

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
from check_report import find_chromium  # noqa: E402


class _Collect(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.srcs: list[str] = []
        self.external: list[str] = []
        self.cells: list[str] = []
        self._in_cell = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.srcs.append(a.get("src", ""))
        if tag in ("link", "script") and (a.get("href") or a.get("src")):
            self.external.append(a.get("href") or a.get("src"))
        self._in_cell = tag in ("td", "th")

    def handle_data(self, data):
        if self._in_cell:
            self.cells.append(data.strip())

    def handle_endtag(self, tag):
        self._in_cell = False


def _report(tmp_path: Path) -> tuple[str, list[np.ndarray]]:
    imgs = []
    figures = []
    for k in range(3):
        img = np.full((120, 200, 3), 255, np.uint8)
        cv2.circle(img, (60 + 40 * k, 60), 30, (40 * k, 100, 200), -1)
        path = tmp_path / f"f{k}.png"
        cv2.imwrite(str(path), img)
        imgs.append(img)
        figures.append(FigureEntry(path, f"Figure {k}", f"caption <{k}> & more"))
    headline = pd.DataFrame(
        {"cooperative NH-inf": [1.234, 1.9], "single NH-inf": [2.0, float("nan")]},
        index=pd.Index(["uav1", "uav2"], name="ATE RMSE [m]"),
    )
    html = render_report(
        title="cvslam evaluation: demo",
        subtitle="2 vehicles",
        headline=headline,
        headline_note="no alignment",
        figures=figures,
        metrics=headline,
        config_yaml="eval:\n  align: none\n",
        provenance={"ground truth": "the logs' ground-truth topic", "input a<b>": "sha256 0"},
    )
    return html, imgs


def test_report_is_self_contained_with_tables_and_escaped_text(tmp_path):
    html, imgs = _report(tmp_path)
    p = _Collect()
    p.feed(html)
    assert not p.external  # no external file, script or style
    assert len(p.srcs) == len(imgs)
    for src, img in zip(p.srcs, imgs, strict=True):
        assert src.startswith("data:image/png;base64,")
        png = base64.b64decode(src.split(",", 1)[1])
        back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert np.array_equal(back, img)
    assert "1.234" in p.cells and "uav2" in p.cells
    assert "caption &lt;1&gt; &amp; more" in html and "input a&lt;b&gt;" in html
    assert re.search(r"<td>&ndash;</td>", html)  # NaN shown as a dash


class _Structure(HTMLParser):
    """The page's tables (with the boxes around them and the heading before them), details
    elements and their text."""

    def __init__(self) -> None:
        super().__init__()
        self.stack: list[tuple[str, dict]] = []
        self.tables: list[dict] = []  # {"in_scroll": bool, "heading": str, "head": [...], "rows"}
        self.details: list[dict] = []  # {"summary": str, "pre": str, "open": bool}
        self.heading = ""
        self._text: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.stack.append((tag, a))
        if tag == "table":
            scroll = any(
                t == "div" and "table-scroll" in (x.get("class") or "") for t, x in self.stack
            )
            self.tables.append(
                {"in_scroll": scroll, "heading": self.heading, "head": [], "rows": []}
            )
        elif tag == "tr" and self.tables:
            self.tables[-1]["rows"].append([])
        elif tag == "details":
            self.details.append({"summary": "", "pre": "", "open": "open" in a})
        if tag in ("h2", "h3", "th", "td", "summary", "pre"):
            self._text = []

    def handle_data(self, data):
        if self._text is not None:
            self._text.append(data)

    def handle_endtag(self, tag):
        text = "".join(self._text or [])
        if tag in ("h2", "h3"):
            self.heading = text
        elif tag in ("th", "td") and self.tables:
            in_head = any(t == "thead" for t, _ in self.stack)
            (self.tables[-1]["head"] if in_head else self.tables[-1]["rows"][-1]).append(text)
        elif (
            tag in ("summary", "pre")
            and self.details
            and any(t == "details" for t, _ in self.stack)
        ):
            self.details[-1][tag] = text
        if tag in ("h2", "h3", "th", "td", "summary", "pre"):
            self._text = None
        while self.stack:
            if self.stack.pop()[0] == tag:
                break


def _wide_metrics() -> pd.DataFrame:
    """Metrics of two estimates of two vehicles with many columns of every family (and one
    of none), as a run with many RPE distances has."""
    rng = np.random.default_rng(2)
    columns = ["poses", "distance_m", "ate_rmse_m", "ate_max_m", "final_error_m"]
    columns += [f"rpe_{d}m_drift_pct" for d in range(5, 100, 5)]
    columns += ["nees_mean", "nees_in_band", "custom_score"]
    index = pd.MultiIndex.from_product(
        [["uav1", "uav2"], ["cooperative NH-inf", "refined"]], names=["vehicle", "estimate"]
    )
    return pd.DataFrame(rng.uniform(0, 10, (4, len(columns))), index=index, columns=columns)


def test_metrics_split_per_family_every_table_scrolls_and_the_config_is_folded():
    metrics = _wide_metrics()
    html = render_report(
        title="t", subtitle="s", headline=metrics[["ate_rmse_m"]].unstack(), headline_note="",
        figures=[], metrics=metrics, config_yaml="eval:\n  align: none\nrun:\n  mosaic: true\n",
        provenance={"ground truth": "x"},
    )  # fmt: skip
    page = _Structure()
    page.feed(html)
    assert page.tables and all(t["in_scroll"] for t in page.tables)  # none wider than its box
    parts = {t["heading"]: t for t in page.tables if t["heading"] in dict(METRIC_GROUPS)}
    parts.update({t["heading"]: t for t in page.tables if t["heading"] == OTHER_METRICS})
    assert list(parts) == [*dict(METRIC_GROUPS), OTHER_METRICS]  # in order, all present
    shown = []
    for t in parts.values():
        assert t["head"][:2] == ["vehicle", "estimate"]  # every part says whose row it is
        assert [r[:2] for r in t["rows"] if r] == [list(i) for i in metrics.index]
        shown += t["head"][2:]
    assert sorted(shown) == sorted(metrics.columns)  # each column once
    assert parts[OTHER_METRICS]["head"][2:] == ["custom_score"]
    assert all(len(t["head"]) <= 2 + 19 for t in parts.values())  # RPE: 19 distances
    # a cell has the value of its row and column
    rpe = parts["Relative pose error (RPE)"]
    col = rpe["head"].index("rpe_50m_drift_pct")
    assert rpe["rows"][2][col] == f"{metrics['rpe_50m_drift_pct'].iloc[1]:.3f}"
    # the config: one folded details element holding the YAML, its size in the summary
    (details,) = page.details
    assert not details["open"] and "4 lines of YAML" in details["summary"]
    assert details["pre"] == "eval:\n  align: none\nrun:\n  mosaic: true\n"


def test_metric_groups_keep_every_column_once():
    metrics = _wide_metrics()
    groups = metric_groups(metrics)
    assert [t for t, _ in groups] == [*dict(METRIC_GROUPS), OTHER_METRICS]
    cols = [c for _, f in groups for c in f.columns]
    assert sorted(cols) == sorted(metrics.columns) and len(cols) == len(set(cols))
    assert all(f.index.equals(metrics.index) for _, f in groups)
    # families without columns are left out; no "Other" part when nothing is left
    assert [t for t, _ in metric_groups(metrics[["ate_rmse_m", "nees_mean"]])] == [
        "Absolute trajectory error (ATE)",
        "Consistency: position NEES",
    ]


def test_report_renders_in_headless_chromium(tmp_path):
    if find_chromium() is None:
        pytest.skip("Chromium not installed (apt-get install chromium) or $CHROMIUM unset")
    html, imgs = _report(tmp_path)
    page = tmp_path / "report.html"
    page.write_text(html, encoding="utf-8")
    shot = tmp_path / "shot.png"
    res = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "check_report.py"), str(page), "--screenshot",
         str(shot)],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"{len(imgs)} of {len(imgs)} images loaded" in res.stdout
    assert cv2.imread(str(shot)).std() > 5
    # a broken image is caught
    page.write_text(html.replace(";base64,", ";base64,AAAA", 1), encoding="utf-8")
    res = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "check_report.py"), str(page)],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    assert res.returncode == 1 and f"{len(imgs) - 1} of {len(imgs)} images loaded" in res.stdout
    # many metric columns: the page still fits the window; the same tables outside their
    # scrolling boxes make it wider, which the check reports
    wide = render_report(
        title="t", subtitle="s", headline=_wide_metrics()[["ate_rmse_m"]], headline_note="",
        figures=[FigureEntry(tmp_path / "f0.png", "f", "c")], metrics=_wide_metrics(),
        config_yaml="a: 1\n", provenance={},
    )  # fmt: skip
    for page_html, ok in ((wide, True), (wide.replace('class="table-scroll"', ""), False)):
        page.write_text(page_html, encoding="utf-8")
        res = subprocess.run(
            [sys.executable, str(REPO / "scripts" / "check_report.py"), str(page)],
            capture_output=True, text=True, timeout=180, check=False,
        )  # fmt: skip
        assert (res.returncode == 0) == ok, res.stdout + res.stderr
        assert ok or "wider than the window" in res.stdout
