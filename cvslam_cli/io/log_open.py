"""Which reader opens a log path: the one place that decides, by what the path is.

- a `.mcap` file (or any file starting with the MCAP magic bytes): `McapLogSource`, the fast
  path;
- a file-compressed MCAP (`.mcap.zstd`, what rosbag2 writes with `--compression-mode file`)
  given on its own: decompressed, streaming, into a temporary file read by `McapLogSource`;
- a rosbag2 folder (or its `metadata.yaml`), a sqlite3 `.db3` file, a ROS 1 `.bag`:
  `RosbagsLogSource` (rosbags_source.py).
"""

from __future__ import annotations

import re
import shutil
import tempfile
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path

import zstandard

from cvslam_cli.errors import LogError
from cvslam_cli.io.mcap_source import MCAP_MAGIC, LogSource, McapLogSource, RawMessage, TopicInfo
from cvslam_cli.io.rosbags_source import RosbagsLogSource

LOG_KINDS = (
    "an .mcap file, a rosbag2 folder (with metadata.yaml), a sqlite3 .db3 bag, a ROS 1 .bag "
    "or an .mcap.zstd"
)
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


_VEHICLE_NAME = re.compile(r"^[A-Za-z0-9_]+$")


def split_log_args(args: Sequence[str | Path]) -> tuple[list[Path], dict[str, Path]]:
    """(plain log paths, vehicle -> log) of command-line log arguments: `NAME=PATH` binds the
    log at PATH to vehicle NAME (unless a file of that whole name exists)."""
    paths: list[Path] = []
    bound: dict[str, Path] = {}
    for arg in map(str, args):
        name, sep, rest = arg.partition("=")
        if sep and rest and _VEHICLE_NAME.match(name) and not Path(arg).exists():
            if name in bound:
                raise LogError(f"{arg}: vehicle {name} is already bound to {bound[name]}")
            bound[name] = Path(rest)
        else:
            paths.append(Path(arg))
    return paths, bound


def open_log(path: Path) -> LogSource:
    """The `LogSource` for `path` (module docstring); LogError naming the path and the kinds
    of log accepted when it is none of them."""
    if path.name == "metadata.yaml" and path.is_file():
        path = path.parent
    if not path.exists():
        raise LogError(f"{path}: file not found")
    if path.is_dir() or path.suffix in (".db3", ".bag"):
        return RosbagsLogSource(path)
    head = _head(path)
    if head.startswith(_ZSTD_MAGIC):
        return DecompressedMcapSource(path)
    if head == MCAP_MAGIC or path.suffix == ".mcap":
        return McapLogSource(path)
    raise LogError(f"{path}: not a log this tool reads (expected {LOG_KINDS})")


def _head(path: Path) -> bytes:
    try:
        with path.open("rb") as f:
            return f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise LogError(f"{path}: cannot read ({exc.strerror})") from None


class DecompressedMcapSource:
    """A zstd-compressed MCAP file, decompressed once (streaming, constant memory) into a
    temporary file that lives as long as this object; read through `McapLogSource`."""

    def __init__(self, path: Path) -> None:
        self.name = str(path)
        self._tmp = tempfile.TemporaryDirectory(prefix="cvslam-mcap-")
        out = Path(self._tmp.name) / path.name.removesuffix(".zstd").removesuffix(".zst")
        try:
            with path.open("rb") as src, out.open("wb") as dst:
                reader = zstandard.ZstdDecompressor().stream_reader(src)
                shutil.copyfileobj(reader, dst, 1 << 20)
        except (zstandard.ZstdError, OSError) as exc:
            raise LogError(f"{path}: cannot decompress (zstd: {exc})") from None
        self._inner = McapLogSource(out)
        self._inner.name = self.name
        self.warnings = self._inner.warnings

    def topics(self) -> dict[str, TopicInfo]:
        return self._inner.topics()

    def messages(self, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
        return self._inner.messages(topics)

    def metadata(self) -> dict[str, dict[str, str]]:
        return self._inner.metadata()
