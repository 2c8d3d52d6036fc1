"""`check_shape`: symbolic sizes bound once and shared, dtype kinds, messages."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.records.arrays import check_increasing, check_shape, first_not_increasing


def test_symbols_bind_at_first_use_and_must_agree_after():
    dims: dict[str, int] = {}
    a = check_shape("a", np.zeros((4, 3)), ("N", 3), "f", dims)
    assert a.shape == (4, 3) and dims == {"N": 4}
    check_shape("b", np.zeros(4, np.int64), ("N",), "iu", dims)
    with pytest.raises(ValueError, match=r"^c: expected integers of shape \(N,\) = \(4,\), "):
        check_shape("c", np.zeros(5, np.int64), ("N",), "iu", dims)


def test_repeated_symbol_within_one_shape():
    check_shape("P", np.eye(6), ("n", "n"), "f")
    with pytest.raises(ValueError, match=r"expected floats of shape \(n, n\) = \(6, 6\)"):
        check_shape("P", np.zeros((6, 5)), ("n", "n"), "f")


def test_values_are_returned_as_arrays_not_converted():
    out = check_shape("x", [1, 2, 3], (3,), "iu")
    assert isinstance(out, np.ndarray) and out.dtype.kind == "i"


@pytest.mark.parametrize(
    ("value", "dtype", "ok"),
    [
        (np.zeros(3), "iu", False),
        (np.zeros(0), "iu", True),  # np.asarray([]) is float: an empty array has no bad value
        (np.zeros(3, np.uint8), "iuf", True),
        (np.zeros(3, bool), "iuf", False),
        (np.zeros(3, np.uint16), np.dtype(np.uint8), False),
        (np.zeros(0, np.uint16), np.dtype(np.uint8), False),  # an exact dtype even when empty
        (np.zeros(3, np.uint8), np.dtype(np.uint8), True),
    ],
)
def test_dtype_kinds_and_exact_dtypes(value, dtype, ok):
    if ok:
        check_shape("v", value, (len(value),), dtype)
    else:
        with pytest.raises(ValueError, match=r"^v: expected .*, got "):
            check_shape("v", value, (len(value),), dtype)


def test_message_says_what_came():
    with pytest.raises(ValueError) as err:
        check_shape("rig.K", np.zeros((2, 3)), (2, 3, 3), "iuf")
    assert str(err.value) == (
        "rig.K: expected real numbers of shape (2, 3, 3), got float64 of shape (2, 3)"
    )


def test_first_not_increasing_strict_and_not():
    assert first_not_increasing(np.array([1, 2, 3])) is None
    assert first_not_increasing(np.array([1, 2, 2, 1])) == 2
    assert first_not_increasing(np.array([1, 2, 2, 1]), strict=False) == 3
    assert first_not_increasing(np.array([], dtype=np.int64)) is None
    with pytest.raises(ValueError, match=r"^t_s: expected strictly increasing, but entry 1 "):
        check_increasing("t_s", np.array([0.0, 0.0]))
    check_increasing("t_s", np.array([0.0, 0.0]), strict=False)
