"""The HTML report: self-contained (every image a data URI), the tables, and a render check
in headless Chromium (skipped where Chromium is not installed)."""

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

from cvslam_cli.evaluation.report import FigureEntry, render_report

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
