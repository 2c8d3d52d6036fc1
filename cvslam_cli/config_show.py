"""`cvslam config show`: the resolved config as commented YAML, each value with its source.

The comments are those of `configs/default.yaml` (one per key, or one per group of keys
that follow it at the same level: `width` and `height` share one); the source of a value
is the defaults, the config file or the `--set`/`--calib` option that set it last
(`config.value_sources`). The text is valid YAML: saved, it loads as the same config.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import yaml

_KEY_RE = re.compile(r"^(\s*)([A-Za-z_][A-Za-z0-9_]*)\s*:")
DEFAULT = "default"
VEHICLES = "logs.vehicles"
VEHICLE_DEFAULTS = "logs.vehicle_defaults"


def key_comments(text: str) -> dict[str, list[str]]:
    """The comment lines above each key of a commented YAML text, by dotted key path. A
    value's comment also applies to the values after it at the same level and under the
    same parent that have none of their own (a section, `key:` with a block below, has only
    its own and ends that); a blank line ends a comment (the file's header)."""
    comments: dict[str, list[str]] = {}
    stack: list[tuple[int, str]] = []  # (indent, key) of the enclosing keys
    carried: dict[tuple[int, str], list[str]] = {}  # (indent, parent) -> last comment there
    pending: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped:
            pending = []
            continue
        if stripped.startswith("#"):
            pending.append(stripped[1:].removeprefix(" "))  # an example's indent kept
            continue
        m = _KEY_RE.match(line)
        if not m:  # a list item or a continued value
            pending = []
            continue
        indent = len(m.group(1))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        parent = ".".join(k for _, k in stack)
        path = f"{parent}.{m.group(2)}" if parent else m.group(2)
        section = not line[m.end() :].split("#", 1)[0].strip()  # `key:` with a block below
        if section:  # only its own comment, and none carried past it
            carried.pop((indent, parent), None)
            if pending:
                comments[path] = pending
        else:
            if pending:
                carried[(indent, parent)] = pending
            if (indent, parent) in carried:
                comments[path] = carried[(indent, parent)]
        pending = []
        stack.append((indent, m.group(2)))
    return comments


def _comment_of(path: str, comments: Mapping[str, list[str]]) -> list[str]:
    """The comment of `path`; a vehicle's keys have those of logs.vehicle_defaults."""
    if path in comments:
        return comments[path]
    if path.startswith(VEHICLES + "."):
        rest = path[len(VEHICLES) + 1 :].partition(".")[2]
        if rest:
            return comments.get(f"{VEHICLE_DEFAULTS}.{rest}", [])
    return []


def _source_of(path: str, sources: Mapping[str, str]) -> str:
    """Who set `path`: the last source setting it or a mapping above it, else (a vehicle's
    key) whoever set the same key of logs.vehicle_defaults, else the defaults."""
    parts = path.split(".")
    for n in range(len(parts), 0, -1):
        hit = sources.get(".".join(parts[:n]))
        if hit is not None:
            return hit
    if path.startswith(VEHICLES + ".") and len(parts) > 3:
        return _source_of(".".join([VEHICLE_DEFAULTS, *parts[3:]]), sources)
    return DEFAULT


def _scalar(value: Any) -> str:
    text = yaml.safe_dump(value, default_flow_style=True, width=10**6).strip()
    return text.removesuffix("...").strip()


def _label(source: str) -> str:
    return source if source == DEFAULT or source.startswith("--") else f"file {source}"


def _selected(path: str, prefix: str | None) -> bool:
    """Whether `path` is shown for `prefix`: it, what is below it and what is above it."""
    if not prefix:
        return True
    return path == prefix or path.startswith(prefix + ".") or prefix.startswith(path + ".")


def render_config(
    data: Mapping[str, Any],
    comments: Mapping[str, list[str]],
    sources: Mapping[str, str],
    prefix: str | None = None,
) -> str:
    """The config `data` (`config.to_dict`) as YAML with each key's comment above it and
    each value's source after it (`# default`, `# file my.yaml`, `# --set ...`); only the
    keys at or below the dotted `prefix` (and their parents) when given."""
    lines: list[str] = []

    def walk(node: Mapping[str, Any], path: str, indent: str) -> None:
        shown: list[str] = []  # the comment above the previous sibling: a group's, once
        for key, value in node.items():
            sub = f"{path}.{key}" if path else str(key)
            if not _selected(sub, prefix):
                continue
            comment = _comment_of(sub, comments)
            if comment != shown:
                lines.extend(f"{indent}# {c}" if c else f"{indent}#" for c in comment)
                shown = comment
            if isinstance(value, Mapping) and value:
                lines.append(f"{indent}{key}:")
                walk(value, sub, indent + "  ")
            else:
                source = _label(_source_of(sub, sources))
                lines.append(f"{indent}{key}: {_scalar(value)}  # {source}")

    walk(data, "", "")
    return "\n".join(lines) + "\n"


def key_paths(data: Mapping[str, Any], path: str = "") -> list[str]:
    """Every dotted key path of `data`, sections and leaves."""
    out = []
    for key, value in data.items():
        sub = f"{path}.{key}" if path else str(key)
        out.append(sub)
        if isinstance(value, Mapping):
            out.extend(key_paths(value, sub))
    return out
