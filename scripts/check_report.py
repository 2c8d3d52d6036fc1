#!/usr/bin/env python3
"""Check that an evaluation report renders in headless Chromium: every image decoded, nothing
wider than the window (a table or figure that escapes its box would cut columns off), and a
screenshot that is not blank.

    python scripts/check_report.py RUN/eval/report.html [--screenshot OUT.png]

Uses the system Chromium (`chromium`, `chromium-browser` or `google-chrome` on PATH, or
$CHROMIUM; on Debian/Ubuntu: `apt-get install chromium`). Exit 0 when the page loaded all
its images, fits the window's width and the screenshot has content, 1 otherwise (with the
reason), 2 when no Chromium is found. `tests/evaluation/test_report.py` runs it (skipped
without Chromium); the same file checks the page's structure without a browser.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

WINDOW = "1280,2400"  # width, height of the headless window [px]


def find_chromium() -> str | None:
    env = os.environ.get("CHROMIUM")
    if env:
        return env
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _run(chromium: str, args: list[str], profile: str) -> subprocess.CompletedProcess[str]:
    base = [
        chromium,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        f"--user-data-dir={profile}",
        "--virtual-time-budget=10000",
    ]
    return subprocess.run(base + args, capture_output=True, text=True, timeout=120, check=False)


def check(report: Path, screenshot: Path) -> tuple[bool, str]:
    """(ok, message) for the report at `report`; writes the screenshot."""
    chromium = find_chromium()
    if chromium is None:
        return False, "no Chromium found (install chromium or set $CHROMIUM)"
    url = report.resolve().as_uri()
    with tempfile.TemporaryDirectory() as profile:
        dom = _run(chromium, [f"--window-size={WINDOW}", "--dump-dom", url], profile)
        m_loaded = re.search(r'data-images-loaded="(\d+)"', dom.stdout)
        m_total = re.search(r'data-images-total="(\d+)"', dom.stdout)
        if not (m_loaded and m_total):
            return False, f"the page's load script did not run (chromium rc {dom.returncode})"
        loaded, total = int(m_loaded.group(1)), int(m_total.group(1))
        if total == 0 or loaded != total:
            return False, f"{loaded} of {total} images loaded"
        if re.search(r'data-page-overflow="1"', dom.stdout):
            return False, f"the page is wider than the window ({WINDOW}): something overflows"
        shot = _run(
            chromium,
            [f"--screenshot={screenshot.resolve()}", f"--window-size={WINDOW}", url],
            profile,
        )
    if not screenshot.exists() or screenshot.stat().st_size == 0:
        return False, f"no screenshot written (chromium rc {shot.returncode})"
    import cv2  # the project's dependency; only needed here

    img = cv2.imread(str(screenshot), cv2.IMREAD_GRAYSCALE)
    if img is None or float(img.std()) < 5.0:
        return False, "the screenshot is blank"
    return True, f"{loaded} of {total} images loaded; screenshot {screenshot}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path)
    ap.add_argument("--screenshot", type=Path, default=None)
    args = ap.parse_args(argv)
    if find_chromium() is None:
        print("check_report: no Chromium found (install chromium or set $CHROMIUM)")
        return 2
    shot = args.screenshot or args.report.with_name(args.report.stem + "_screenshot.png")
    ok, msg = check(args.report, shot)
    print(f"check_report: {'ok' if ok else 'FAILED'}: {args.report}: {msg}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
