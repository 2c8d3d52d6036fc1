"""`cvslam info`: what is in a set of logs, per vehicle, and what is wrong with it.

`inspect_logs` streams every message once (bounded memory) and returns a plain dict
(the `--json` output); `render_text` formats it for a terminal.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cvslam_cli.config import Config
from cvslam_cli.errors import CvslamError
from cvslam_cli.io.log_stats import Problem
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import LogSource
from cvslam_cli.io.topic_map import ROLES


def inspect_logs(sources: list[LogSource], cfg: Config) -> dict[str, Any]:
    logs = LogSet(sources, cfg.logs, strict=False)
    calibration: dict[str, Any] = {}
    for name, v in logs.vehicles.items():
        if v.has_stereo:
            try:
                calibration[name] = logs.rig(name).describe()
            except CvslamError as exc:
                calibration[name] = {"error": str(exc)}
                logs.problems.append(_error(str(exc)))
    for _ in logs.records(roles=ROLES):
        pass

    vehicles: dict[str, Any] = {}
    for name, v in logs.vehicles.items():
        vs = logs.stats[name]
        topics = []
        for role in v.present:
            topic = v.topic(role)
            ts = vs.topics.get(topic)
            info = v.infos[role]
            entry: dict[str, Any] = {
                "topic": topic,
                "role": role,
                "type": info.schema_name,
                "count": ts.count if ts else 0,
            }
            if ts is not None and ts.count:
                gaps = ts.gaps(cfg.logs.gap_factor)
                entry.update(
                    {
                        "rate_hz": round(ts.rate_hz, 3),
                        "first_ns": ts.first_ns,
                        "last_ns": ts.last_ns,
                        "span_s": round(ts.span_s, 6),
                        "gaps": len(gaps),
                        "largest_gap_s": round(max(gaps), 6) if gaps else 0.0,
                        "backwards": ts.backwards,
                        "dropped_nonfinite": ts.dropped_nonfinite,
                    }
                )
                if ts.image_size is not None:
                    entry["image"] = {
                        "width": ts.image_size[0],
                        "height": ts.image_size[1],
                        "encoding": ts.encoding,
                    }
                if gaps:
                    logs.problems.append(
                        _warning(
                            f"{topic}: {len(gaps)} gap(s) longer than {cfg.logs.gap_factor:g} "
                            f"nominal periods (largest {max(gaps):.3f} s)"
                        )
                    )
                if ts.dropped_nonfinite:
                    logs.problems.append(
                        _warning(
                            f"{topic}: {ts.dropped_nonfinite} message(s) with NaN/inf values "
                            "dropped"
                        )
                    )
                if ts.backwards:
                    logs.problems.append(
                        _warning(f"{topic}: timestamps go backwards {ts.backwards} time(s)")
                    )
            topics.append(entry)
        firsts = [t["first_ns"] for t in topics if t.get("first_ns") is not None]
        lasts = [t["last_ns"] for t in topics if t.get("last_ns") is not None]
        stereo = {
            "pairs": vs.stereo_pairs,
            "unpaired_left": vs.unpaired_left,
            "unpaired_right": vs.unpaired_right,
            "max_pair_offset_ms": round(vs.max_pair_offset_ns * 1e-6, 6),
            "tolerance_ms": cfg.logs.stereo_pair_tolerance_ms,
        }
        if v.has_stereo and (vs.unpaired_left or vs.unpaired_right):
            logs.problems.append(
                _warning(
                    f"vehicle {name}: {vs.unpaired_left} left and {vs.unpaired_right} right images "
                    f"without a partner within {cfg.logs.stereo_pair_tolerance_ms:g} ms"
                )
            )
        if not v.has_stereo and ("left_image" in v.present or "right_image" in v.present):
            logs.problems.append(
                _warning(f"vehicle {name}: only one camera's images; no stereo pairs")
            )
        vehicles[name] = {
            "kind": v.config.kind,
            "start_ns": min(firsts) if firsts else None,
            "end_ns": max(lasts) if lasts else None,
            "duration_s": round((max(lasts) - min(firsts)) * 1e-9, 6) if firsts else 0.0,
            "topics": topics,
            "stereo": stereo,
            "calibration": calibration.get(name),
        }
    if not vehicles:
        seen = ", ".join(f"{t} ({i.schema_name})" for t, i in sorted(logs.topic_infos.items()))
        logs.problems.append(
            _error(
                f"{logs.names}: no vehicle found; topics seen: {seen or 'none'}; name a "
                "vehicle's topics with logs.vehicles.NAME.topics.<role> (or the templates of "
                "logs.vehicle_defaults.topics), and give each robot's log as NAME=LOG"
            )
        )
    return {
        "logs": [_describe_source(s) for s in sources],
        "vehicles": vehicles,
        "other_topics": [
            {"topic": i.topic, "type": i.schema_name, "count": i.message_count}
            for i in logs.unassigned_topics()
        ],
        "problems": [{"severity": p.severity, "text": p.text} for p in _unique(logs.problems)],
    }


def _error(text: str) -> Problem:
    return Problem("error", text)


def _warning(text: str) -> Problem:
    return Problem("warning", text)


def _unique(items: list[Problem]) -> list[Problem]:
    out: list[Problem] = []
    for i in items:
        if i not in out:
            out.append(i)
    return out


def _describe_source(src: LogSource) -> dict[str, Any]:
    entry: dict[str, Any] = {"path": src.name}
    path = Path(src.name)
    if path.exists():
        files = [p for p in path.rglob("*") if p.is_file()] if path.is_dir() else [path]
        entry["size_bytes"] = sum(p.stat().st_size for p in files)
    entry["metadata"] = src.metadata()
    return entry


def first_error(report: dict[str, Any]) -> str | None:
    for p in report["problems"]:
        if p["severity"] == "error":
            return str(p["text"])
    return None


def render_text(report: dict[str, Any]) -> str:
    lines: list[str] = []
    for lg in report["logs"]:
        size = lg.get("size_bytes")
        lines.append(f"log {lg['path']}" + (f"  ({size / 1e6:.1f} MB)" if size else ""))
        for name, md in lg.get("metadata", {}).items():
            if "nav_frame" in md or "dataset" in md:
                lines.append(
                    f"  metadata {name}: "
                    + ", ".join(
                        f"{k}={v}"
                        for k, v in md.items()
                        if k in ("dataset", "vehicle", "nav_frame")
                    )
                )
    if not report["vehicles"]:
        lines.append(
            "no vehicles found (no topic matches the vehicle topic map; see "
            "logs.vehicles in the config)"
        )
    for name, v in report["vehicles"].items():
        lines.append("")
        lines.append(f"vehicle {name} ({v['kind']}): {v['duration_s']:.3f} s")
        lines.append(
            f"  {'topic':44s} {'type':32s} {'count':>7s} {'rate Hz':>9s} "
            f"{'span s':>9s} {'gaps':>5s}"
        )
        for t in v["topics"]:
            rate = f"{t['rate_hz']:.2f}" if "rate_hz" in t else "-"
            span = f"{t['span_s']:.3f}" if "span_s" in t else "-"
            lines.append(
                f"  {t['topic']:44s} {t['type']:32s} {t['count']:7d} {rate:>9s} "
                f"{span:>9s} {t.get('gaps', 0):5d}"
            )
            if "image" in t:
                im = t["image"]
                lines.append(f"      image {im['width']}x{im['height']} {im['encoding']}")
        s = v["stereo"]
        lines.append(
            f"  stereo pairs: {s['pairs']} (unpaired left {s['unpaired_left']}, right "
            f"{s['unpaired_right']}; max offset {s['max_pair_offset_ms']:.3f} ms, "
            f"tolerance {s['tolerance_ms']:g} ms)"
        )
        cal = v["calibration"]
        if cal is None:
            lines.append("  calibration: none (no stereo images)")
        elif "error" in cal:
            lines.append(f"  calibration: ERROR {cal['error']}")
        else:
            lines.append(
                f"  calibration: baseline {cal['baseline_m']:.4f} m, "
                f"{'rectified' if cal['rectified'] else 'not rectified'}"
            )
            for side in ("left", "right"):
                c = cal[side]
                d = ", ".join(f"{x:.6g}" for x in c["D"]) or "none"
                lines.append(
                    f"    {side:5s} {c['width']}x{c['height']} fx={c['fx']:.3f} "
                    f"fy={c['fy']:.3f} cx={c['cx']:.3f} cy={c['cy']:.3f} "
                    f"{c['distortion_model']} [{d}]  from {c['source']}"
                )
    if report["other_topics"]:
        lines.append("")
        lines.append("topics not assigned to a vehicle:")
        for t in report["other_topics"]:
            lines.append(f"  {t['topic']:44s} {t['type']:32s} {t['count']:7d}")
    lines.append("")
    if report["problems"]:
        lines.append("problems:")
        for p in report["problems"]:
            lines.append(f"  {p['severity']}: {p['text']}")
    else:
        lines.append("problems: none")
    return "\n".join(lines)
