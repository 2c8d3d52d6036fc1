"""The one reader of text and YAML inputs and the one stamp-order check: one-line errors
naming the file (and the line) with the error class the caller asks for."""

from __future__ import annotations

import pytest

from cvslam_cli.errors import ConfigError, CvslamError, DatasetError
from cvslam_cli.io.textfiles import (
    check_stamps_increasing,
    data_lines,
    read_text,
    read_yaml_mapping,
)


def test_read_text_errors_name_the_file_and_what_was_expected(tmp_path):
    with pytest.raises(DatasetError, match=r"nope\.txt: not found, expected a list"):
        read_text(tmp_path / "nope.txt", "a list", DatasetError)
    with pytest.raises(CvslamError, match=r": is not a file, expected a list"):
        read_text(tmp_path, "a list")
    (tmp_path / "b.txt").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(CvslamError, match=r"b\.txt: is not a UTF-8 text file, expected a list"):
        read_text(tmp_path / "b.txt", "a list")


def test_read_yaml_mapping(tmp_path):
    f = tmp_path / "a.yaml"
    f.write_text("")
    assert read_yaml_mapping(f, "a config", ConfigError, empty_ok=True) == {}
    with pytest.raises(ConfigError, match=r"a\.yaml: expected a YAML mapping \(a config\), got"):
        read_yaml_mapping(f, "a config", ConfigError)
    f.write_text("%YAML:1.0\nk: 1\n")  # OpenCV's first line
    assert read_yaml_mapping(f, "a sensor.yaml") == {"k": 1}
    f.write_text("%YAML:1.0\nk: 1\nj: [1, 2\n")
    with pytest.raises(CvslamError, match=r"a\.yaml: not valid YAML at line 4 .*a sensor\.yaml$"):
        read_yaml_mapping(f, "a sensor.yaml")


def test_stamps_must_increase_naming_the_line(tmp_path):
    lines = [no for no, _ in data_lines("# head\n1\n\n2\n2\n")]
    assert lines == [2, 4, 5]
    check_stamps_increasing(tmp_path / "t.csv", [1, 2, 3], lines)
    with pytest.raises(
        DatasetError,
        match=r"t\.csv: line 5: timestamp 0\.000000002 s does not increase "
        r"\(previous 0\.000000002 s, line 4\)",
    ):
        check_stamps_increasing(tmp_path / "t.csv", [1, 2, 2], lines, DatasetError)
