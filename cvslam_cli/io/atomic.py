"""Atomic writes: a file or a whole folder appears under its final name only when complete.

Every writer of cvslam goes through here (DESIGN.md section 5): the content is written to
`<name>.partial` beside the final name and renamed when it is complete, so an interrupted
write (an error, Ctrl-C, a full disk) never leaves a file or folder with its final name that
looks finished; the `.partial` is removed when the write fails. A completed write replaces
what was under the final name: a file by one `os.replace`, a folder by removing the old one
just before renaming the new one into its place. Only a regular file (or, for a folder, a
folder) is ever replaced: a device, a pipe, a socket or a symbolic link under the final
name is an error, so `-o /dev/null` never turns a device into a file.

`check_writable(paths)` tries, before the work, what the writes will do at the end (create
the folders, create and remove each `.partial`), so that an unwritable or read-only folder,
a folder that is a file, or a name too long is found before minutes of work, not after.
"""

from __future__ import annotations

import abc
import contextlib
import os
import shutil
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Self

from cvslam_cli.errors import CvslamError

PARTIAL_SUFFIX = ".partial"


class OutputError(CvslamError):
    """An output cannot be written where it was asked for (names the path and why)."""


def _refuse_non_regular(path: Path, *, folder_ok: bool = False) -> None:
    """OutputError when something other than a regular file (or a folder, `folder_ok`) is
    at `path`; nothing there is fine."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise OutputError(f"{path}: cannot be written ({exc.strerror})") from None
    if stat.S_ISREG(mode) or (folder_ok and stat.S_ISDIR(mode)):
        return
    kind = {
        stat.S_ISLNK(mode): "a symbolic link",
        stat.S_ISDIR(mode): "a folder",
        stat.S_ISCHR(mode) or stat.S_ISBLK(mode): "a device",
        stat.S_ISFIFO(mode): "a pipe",
        stat.S_ISSOCK(mode): "a socket",
    }.get(True, "not a regular file")
    raise OutputError(f"{path}: is {kind}, not a regular file; it is not replaced")


def _make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        why = exc.strerror or str(exc)
        for above in (folder, *folder.parents):
            if above.exists() or above.is_symlink():
                if not above.is_dir():
                    why = f"{above} is a file, not a folder"
                break
        raise OutputError(f"{folder}: cannot create the output folder ({why})") from None


def check_writable(paths: Iterable[Path]) -> None:
    """Do now what writing each of `paths` will do at the end, undone at once: create its
    folders and its `.partial` (then remove them); OutputError naming the path and the reason
    (a read-only or unwritable folder, a folder that is a file, a name too long, something
    not a regular file under the name)."""
    for path in paths:
        path = Path(path)
        created = [p for p in (path.parent, *path.parent.parents) if not p.exists()]
        _make_folder(path.parent)
        try:
            _refuse_non_regular(path, folder_ok=True)
            tmp = partial_path(path)
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                continue  # a left-over partial: replaced when written
            except OSError as exc:
                raise OutputError(f"{path}: cannot be written ({exc.strerror or exc})") from None
            os.close(fd)
            tmp.unlink()
        finally:
            for folder in created:  # innermost first
                with contextlib.suppress(OSError):
                    folder.rmdir()


def partial_path(path: Path) -> Path:
    """The temporary name `path` is written under: `<name>.partial` beside it."""
    return path.with_name(path.name + PARTIAL_SUFFIX)


class AtomicFile:
    """One file written at `tmp` (parent folders created) and moved to `path` by `commit()`,
    or removed by `discard()`."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = partial_path(self.path)
        _refuse_non_regular(self.path)
        _make_folder(self.path.parent)

    def commit(self) -> None:
        try:
            _refuse_non_regular(self.path)  # again: something may have appeared meanwhile
        except OutputError:
            self.discard()
            raise
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
    _refuse_non_regular(path, folder_ok=True)
    shutil.rmtree(tmp, ignore_errors=True)
    _make_folder(tmp)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        _refuse_non_regular(path, folder_ok=True)
    except OutputError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
    tmp.rename(path)
