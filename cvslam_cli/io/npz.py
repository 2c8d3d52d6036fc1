"""Byte-reproducible .npz archives, written whole or member by member.

`numpy.savez` stamps every member with the current wall-clock time, so two runs with the
same inputs differ byte for byte. These writers produce the same format (a zip of .npy
members, readable by `numpy.load`) with a fixed member timestamp, so the same arrays in the
same order always give the same bytes. `NpzWriter` adds members one at a time (memory stays
bounded for per-frame data); the archive is written to `<path>.partial` and renamed only
when closed without error.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import AtomicFile, AtomicWriter

_EPOCH = (1980, 1, 1, 0, 0, 0)


class NpzWriter(AtomicWriter):
    def __init__(self, path: Path, *, compress: bool = False) -> None:
        self.path = path
        self._file = AtomicFile(path)
        self._method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
        self._zip = zipfile.ZipFile(self._file.tmp, "w", compression=self._method, allowZip64=True)

    def add(self, name: str, array: np.ndarray) -> None:
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.asanyarray(array), allow_pickle=False)
        info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
        info.compress_type = self._method
        info.external_attr = 0o644 << 16
        self._zip.writestr(info, buf.getvalue())

    def close(self) -> None:
        self._zip.close()
        self._file.commit()

    def abort(self) -> None:
        self._zip.close()
        self._file.discard()


def save_npz(path: Path, arrays: Mapping[str, np.ndarray], *, compress: bool = False) -> None:
    """Write `arrays` (members in sorted name order)."""
    with NpzWriter(path, compress=compress) as w:
        for name in sorted(arrays):
            w.add(name, arrays[name])


def load_versioned_npz(
    path: Path,
    format_name: str,
    version: int,
    kind: str,
    redo: str,
    members: Sequence[str] | None = None,
) -> dict[str, np.ndarray]:
    """The arrays of a cvslam .npz file whose `format` and `version` members must be
    `format_name` and `version` (all members, or only `members`: the others are not read).
    `CvslamError` naming the file when it is missing, unreadable, of another format or
    version (then saying to run `redo` again); `kind` ("feature", "pose covariance") names
    the file in these messages."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            fmt = str(npz["format"]) if "format" in npz.files else ""
            if fmt != format_name:
                raise CvslamError(f"{path}: not a cvslam {kind} file (format {fmt or 'missing'!r})")
            try:
                found = int(npz["version"]) if "version" in npz.files else -1
            except (TypeError, ValueError):
                found = -1
            if found != version:
                raise CvslamError(
                    f"{path}: {kind} format version {found}, this cvslam reads version "
                    f"{version}; run `{redo}` again"
                )
            return {k: npz[k] for k in (npz.files if members is None else members)}
    except CvslamError:
        raise
    except FileNotFoundError:
        raise CvslamError(f"{path}: {kind} file not found") from None
    except Exception as exc:  # numpy, zipfile and zlib raise many kinds for a damaged file
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise CvslamError(f"{path}: not a readable {kind} file ({why})") from None
