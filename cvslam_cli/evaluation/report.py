"""The evaluation report: one self-contained HTML page (every image embedded as a data URI,
no external file, script or font), readable offline and mailable as one file.

Sections: the headline table, the figures (each with its caption), all metrics (one table
per metric family, `METRIC_GROUPS`, so no table is wider than the page however many columns
there are; each table also scrolls sideways inside its own box, `.table-scroll`, where the
window is narrower than it), the config used (YAML, folded away in a `<details>` element)
and the data provenance (inputs with checksums, versions, when). Rows are whatever
estimates the run has (one per estimate and vehicle), so new variants need no change here.
A small inline script counts the images that decoded and writes the result into
`<body data-images-loaded="N" data-images-total="M">`, and whether the page is wider than
the window (`data-page-overflow="1"`: something escaped its box), so a headless browser can
check the page rendered completely (`scripts/check_report.py`).
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

_CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif;
       margin: 2em auto; max-width: 1200px; color: #222; padding: 0 1em; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
.sub { color: #666; margin-top: 0; }
.table-scroll { overflow-x: auto; max-width: 100%; margin: 1em 0; }
table { border-collapse: collapse; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; }
th { background: #f3f3f3; } td:first-child, th:first-child { text-align: left; }
.key { text-align: left; white-space: nowrap; }
figure { margin: 1.5em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #444; font-size: 0.92em; margin-top: 0.3em; }
pre { background: #f7f7f7; padding: 1em; overflow-x: auto; font-size: 0.85em; }
.note { color: #555; font-size: 0.92em; }
details { margin: 1em 0; } summary { cursor: pointer; color: #333; }
"""

_SCRIPT = """
window.addEventListener("load", function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++;
  }
  document.body.setAttribute("data-images-loaded", String(ok));
  document.body.setAttribute("data-images-total", String(imgs.length));
  var root = document.documentElement;
  document.body.setAttribute(
    "data-page-overflow", root.scrollWidth > root.clientWidth + 1 ? "1" : "0");
});
"""


@dataclass(frozen=True)
class FigureEntry:
    """A PNG to embed, with its title and caption."""

    path: Path
    title: str
    caption: str


def _img_tag(path: Path, alt: str) -> str:
    return _png_tag(path.read_bytes(), alt)


def _png_tag(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


# the parts of the metrics table, in the report's order: (title, the columns it holds: a
# name or a prefix ending in "_"); columns in none of them go to a last part, "Other"
METRIC_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Absolute trajectory error (ATE)", ("poses", "distance_m", "ate_")),
    ("Relative pose error (RPE)", ("rpe_",)),
    ("Final drift", ("final_",)),
    ("Consistency: position NEES", ("nees_",)),
)
OTHER_METRICS = "Other"


def _header(name: object) -> str:
    """A column name, allowed to wrap after its underscores (`ate_rmse_m`)."""
    return html.escape(str(name)).replace("_", "_<wbr>")


def _table(frame: pd.DataFrame, float_format: str = "{:.3f}") -> str:
    """The frame as an HTML table in a box that scrolls sideways when the window is narrower
    than it; its index (one or several levels) in the first columns; NaN and missing
    values (pandas' NA, e.g. of a nullable integer column) as a dash."""

    def cell(v: object) -> str:
        if v is pd.NA or (isinstance(v, float) and v != v):
            return "&ndash;"
        if isinstance(v, float):
            return float_format.format(v)
        return html.escape(str(v))

    names = [n or "" for n in frame.index.names]
    head = "".join(f'<th class="key">{_header(c)}</th>' for c in names)
    head += "".join(f"<th>{_header(c)}</th>" for c in frame)
    rows = [
        "<tr>"
        + "".join(
            f'<td class="key">{html.escape(str(i))}</td>'
            for i in (idx if len(names) > 1 else (idx,))
        )
        + "".join(f"<td>{cell(v)}</td>" for v in row)
        + "</tr>"
        for idx, row in zip(frame.index, frame.itertuples(index=False), strict=True)
    ]
    return (
        '<div class="table-scroll"><table>'
        f"<thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>"
    )


def metric_groups(metrics: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """The metrics table cut into `METRIC_GROUPS` (title, its columns; the index kept in
    each), then `OTHER_METRICS` for the columns in none; empty parts left out."""

    def member(column: str, keys: tuple[str, ...]) -> bool:
        return any(column == k or (k.endswith("_") and column.startswith(k)) for k in keys)

    parts: list[tuple[str, pd.DataFrame]] = []
    taken: set[str] = set()
    for title, keys in METRIC_GROUPS:
        cols = [c for c in metrics.columns if c not in taken and member(str(c), keys)]
        taken.update(cols)
        if cols:
            parts.append((title, metrics[cols]))
    rest = [c for c in metrics.columns if c not in taken]
    if rest:
        parts.append((OTHER_METRICS, metrics[rest]))
    return parts


def _page_start(title: str, subtitle: str) -> list[str]:
    """The head of a page and its title and subtitle."""
    return [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title>",
        f"<style>{_CSS}</style>",
        f"<script>{_SCRIPT}</script>",
        "</head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="sub">{html.escape(subtitle)}</p>',
    ]


def render_report(
    *,
    title: str,
    subtitle: str,
    headline: pd.DataFrame,
    headline_note: str,
    figures: Sequence[FigureEntry],
    metrics: pd.DataFrame,
    config_yaml: str,
    provenance: Mapping[str, object],
) -> str:
    """The report page as a string (module docstring). `metrics`: one row per estimate and
    vehicle (its index, e.g. (vehicle, estimate), shown in every part)."""
    parts = [
        *_page_start(title, subtitle),
        "<h2>Headline</h2>",
        _table(headline),
        f'<p class="note">{html.escape(headline_note)}</p>',
    ]
    if figures:
        parts.append("<h2>Figures</h2>")
        for f in figures:
            parts.append(
                f"<figure><h3>{html.escape(f.title)}</h3>{_img_tag(f.path, f.title)}"
                f"<figcaption>{html.escape(f.caption)}</figcaption></figure>"
            )
    parts.append("<h2>All metrics</h2>")
    for group, table in metric_groups(metrics):
        parts += [f"<h3>{html.escape(group)}</h3>", _table(table)]
    lines = len(config_yaml.splitlines())
    parts += [
        "<h2>Config</h2>",
        f"<details><summary>The resolved config ({lines} lines of YAML)</summary>",
        f"<pre>{html.escape(config_yaml)}</pre></details>",
        "<h2>Provenance</h2>",
        '<div class="table-scroll"><table><tbody>',
        *(
            f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(str(v))}</td></tr>"
            for k, v in provenance.items()
        ),
        "</tbody></table></div>",
        "</body></html>",
    ]
    return "\n".join(parts)


def render_summary(
    *,
    title: str,
    subtitle: str,
    table: pd.DataFrame,
    figure_png: bytes,
    figure_caption: str,
    reports: Mapping[str, str],
) -> str:
    """The page comparing runs (`cvslam summary`), self-contained like the report: the
    table, one figure, and a link to each run's report (`reports`: run -> relative URL)."""
    links = "".join(
        f'<li><a href="{html.escape(url)}">{html.escape(run)}</a></li>'
        for run, url in reports.items()
    )
    parts = [
        *_page_start(title, subtitle),
        "<h2>Runs</h2>",
        _table(table),
        f"<figure>{_png_tag(figure_png, title)}"
        f"<figcaption>{html.escape(figure_caption)}</figcaption></figure>",
        "<h2>Reports</h2>",
        f"<ul>{links}</ul>",
        "</body></html>",
    ]
    return "\n".join(parts)
