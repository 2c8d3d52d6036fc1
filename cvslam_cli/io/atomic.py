"""Atomic writes: a file or a whole folder appears under its final name only when complete.

Every writer of cvslam goes through here (DESIGN.md section 5): the content is written to
`<name>.partial` beside the final name and renamed when it is complete, so an interrupted
write (an error, Ctrl-C, a full disk) never leaves a file or folder with its final name that
looks finished; the `.partial` is removed when the write fails. A completed write replaces
what was under the final name: a file by one `os.replace`, a folder by removing the old one
just before renaming the new one into its place.
"""

from __future__ import annotations

import abc
import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Self

PARTIAL_SUFFIX = ".partial"


def partial_path(path: Path) -> Path:
    """The temporary name `path` is written under: `<name>.partial` beside it."""
    return path.with_name(path.name + PARTIAL_SUFFIX)


class AtomicFile:
    """One file written at `tmp` (parent folders created) and moved to `path` by `commit()`,
    or removed by `discard()`."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = partial_path(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)

    def commit(self) -> None:
        os.replace(self.tmp, self.path)

    def discard(self) -> None:
        self.tmp.unlink(missing_ok=True)


class AtomicWriter(abc.ABC):
    """A writer that stays open across calls (a log, an archive written member by member)
    into an `AtomicFile`. As a context manager it calls `close()` (finish, then commit) when
    the block completes and `abort()` (discard) when it raises."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def abort(self) -> None: ...


@contextlib.contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """`with atomic_file(path) as tmp:` write `tmp`; it becomes `path` when the block
    completes and is removed when the block raises."""
    f = AtomicFile(path)
    try:
        yield f.tmp
    except BaseException:
        f.discard()
        raise
    f.commit()


def write_bytes_atomic(path: Path, data: bytes) -> None:
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: Path, text: str, encoding: str = "utf-8") -> None:
    with atomic_file(path) as tmp:
        tmp.write_text(text, encoding=encoding)


@contextlib.contextmanager
def atomic_dir(path: Path) -> Iterator[Path]:
    """`with atomic_dir(path) as tmp:` fill the empty folder `tmp` (`<path>.partial`, left
    over ones removed first); when the block completes it replaces `path` (a folder or a
    file there is removed first), when it raises it is removed."""
    tmp = partial_path(path)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
    tmp.rename(path)
