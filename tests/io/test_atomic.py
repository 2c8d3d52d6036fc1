"""Atomic writes: nothing complete-looking under the final name until the write is done."""

from __future__ import annotations

from pathlib import Path

import pytest

from cvslam_cli.io.atomic import (
    AtomicFile,
    atomic_dir,
    atomic_file,
    partial_path,
    write_bytes_atomic,
    write_text_atomic,
)


def names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_partial_path_is_beside_the_final_name(tmp_path):
    assert partial_path(tmp_path / "fuse") == tmp_path / "fuse.partial"
    assert partial_path(tmp_path / "a.tum") == tmp_path / "a.tum.partial"


def test_file_appears_only_when_the_block_completes(tmp_path):
    path = tmp_path / "sub" / "a.txt"
    with atomic_file(path) as tmp:
        assert tmp == partial_path(path) and tmp.parent.is_dir()  # parents made
        tmp.write_text("new")
        assert not path.exists()
    assert path.read_text() == "new" and names(path.parent) == ["a.txt"]


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_file_interrupted_keeps_the_old_one_and_no_partial(tmp_path, error):
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(type(error)), atomic_file(path) as tmp:
        tmp.write_text("half")
        raise error
    assert path.read_text() == "old" and names(tmp_path) == ["a.txt"]


def test_a_completed_write_replaces_the_old_file(tmp_path):
    path = tmp_path / "a.bin"
    write_bytes_atomic(path, b"old")
    with atomic_file(path) as tmp:
        tmp.write_bytes(b"new")
        assert path.read_bytes() == b"old"  # readers see the old file until the rename
    assert path.read_bytes() == b"new" and names(tmp_path) == ["a.bin"]


def test_text_is_written_with_the_encoding_and_no_newline_translation(tmp_path):
    write_text_atomic(tmp_path / "a.txt", "x\r\ny\n\u00b5")
    assert (tmp_path / "a.txt").read_bytes() == b"x\r\ny\n\xc2\xb5"
    write_text_atomic(tmp_path / "b.txt", "1.0\n", encoding="ascii")
    assert (tmp_path / "b.txt").read_bytes() == b"1.0\n"
    with pytest.raises(UnicodeEncodeError):
        write_text_atomic(tmp_path / "c.txt", "\u00b5", encoding="ascii")
    assert names(tmp_path) == ["a.txt", "b.txt"]


def test_an_open_writer_commits_or_discards(tmp_path):
    kept, dropped = AtomicFile(tmp_path / "kept"), AtomicFile(tmp_path / "dropped")
    for f in (kept, dropped):
        with f.tmp.open("wb") as fh:
            fh.write(b"data")
    kept.commit()
    dropped.discard()
    assert names(tmp_path) == ["kept"] and (tmp_path / "kept").read_bytes() == b"data"


def test_folder_appears_whole_and_replaces_the_old_one(tmp_path):
    out = tmp_path / "fuse"
    out.mkdir()
    (out / "stale.tum").write_text("old")
    with atomic_dir(out) as tmp:
        assert tmp == partial_path(out) and names(tmp) == []
        (tmp / "a.tum").write_text("new")
        assert names(out) == ["stale.tum"]  # the old folder stays until the block ends
    assert names(out) == ["a.tum"] and names(tmp_path) == ["fuse"]


@pytest.mark.parametrize("error", [ValueError("bug"), KeyboardInterrupt()])
def test_folder_interrupted_leaves_the_old_one_and_no_partial(tmp_path, error):
    out = tmp_path / "eval"
    out.mkdir()
    (out / "report.html").write_text("old")
    with pytest.raises(type(error)), atomic_dir(out) as tmp:
        (tmp / "report.html").write_text("complete-looking")
        raise error
    assert names(tmp_path) == ["eval"] and (out / "report.html").read_text() == "old"


def test_folder_interrupted_without_an_old_one_leaves_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt), atomic_dir(tmp_path / "a" / "mosaic") as tmp:
        (tmp / "all.png").write_bytes(b"png")
        raise KeyboardInterrupt
    assert names(tmp_path / "a") == []


def test_folder_clears_a_leftover_partial_and_replaces_a_file(tmp_path):
    out = tmp_path / "sim"
    out.write_text("a file in the way")
    partial_path(out).mkdir()
    (partial_path(out) / "left_over.mcap").write_text("crashed run")
    with atomic_dir(out) as tmp:
        assert names(tmp) == []
        (tmp / "uav1.mcap").write_text("new")
    assert names(out) == ["uav1.mcap"] and names(tmp_path) == ["sim"]
