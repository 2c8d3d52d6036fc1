"""Array type aliases and `check_shape`, the one validator of an array's shape and dtype.

Records check their arrays at construction and readers check what a file holds with
`check_shape`, so every such error says the same thing the same way: what was expected
(shape with its symbolic sizes, and their values) and what came.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
I32 = NDArray[np.int32]
U8 = NDArray[np.uint8]
U16 = NDArray[np.uint16]
BoolArray = NDArray[np.bool_]

Dim = int | str
"""One entry of an expected shape: a size, or a symbol ("N") whose size `check_shape` binds."""

_KIND_WORDS = {
    "b": "booleans",
    "iu": "integers",
    "u": "unsigned integers",
    "f": "floats",
    "iuf": "real numbers",
}


def _shape_text(shape: Sequence[object]) -> str:
    inner = ", ".join(str(d) for d in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


def check_shape(
    name: str,
    value: object,
    shape: Sequence[Dim],
    dtype: str | np.dtype,
    dims: dict[str, int] | None = None,
) -> np.ndarray:
    """`value` as an array (`np.asarray`, not converted) after checking it.

    `shape`: one entry per axis, an int for that size or a symbol such as "N" for a size
    named in `dims`; a symbol not in `dims` yet takes this array's size there (`dims` is
    updated in place, so the checks of one record share their sizes).
    `dtype`: numpy kind characters ("b" booleans, "iu" integers, "iuf" real numbers, ...),
    which an empty array passes whatever its dtype (`np.asarray([])` is float), or an exact
    `np.dtype`.
    ValueError naming `name`, the expected shape with the values of its symbols and dtype,
    and the array's dtype and shape, for example
    "LandmarkMap.p_nav_m: expected real numbers of shape (N, 3) = (5, 3), got float64 of
    shape (4, 2)".
    """
    arr = np.asarray(value)
    sizes = {} if dims is None else dims
    if isinstance(dtype, str):
        ok_dtype = arr.dtype.kind in dtype or arr.size == 0
        wanted = _KIND_WORDS.get(dtype, f"dtype kind {dtype!r}")
    else:
        ok_dtype = arr.dtype == dtype
        wanted = str(dtype)
    ok_shape = arr.ndim == len(shape)
    if ok_shape:
        for dim, size in zip(shape, arr.shape, strict=True):
            if isinstance(dim, str):
                sizes.setdefault(dim, size)
                dim = sizes[dim]
            ok_shape = ok_shape and dim == size
    if ok_shape and ok_dtype:
        return arr
    expected = _shape_text(shape)
    if any(isinstance(d, str) for d in shape) and all(
        not isinstance(d, str) or d in sizes for d in shape
    ):
        expected += " = " + _shape_text([sizes[d] if isinstance(d, str) else d for d in shape])
    raise ValueError(
        f"{name}: expected {wanted} of shape {expected}, got {arr.dtype} of shape {arr.shape}"
    )


def first_not_increasing(values: NDArray, *, strict: bool = True) -> int | None:
    """Index of the first entry of the 1-D `values` that is not greater than the one before
    (`strict`) or is less than it (not `strict`), or None when they are in order."""
    step = np.diff(values)
    bad = np.flatnonzero(step <= 0 if strict else step < 0)
    return int(bad[0]) + 1 if bad.size else None


def check_increasing(name: str, values: NDArray, *, strict: bool = True) -> None:
    """ValueError naming `name` and the first entry out of order: the one validator of time
    order for stamps and sample times (`strict`: every entry later than the one before)."""
    k = first_not_increasing(values, strict=strict)
    if k is not None:
        order = "strictly increasing" if strict else "in time order"
        raise ValueError(
            f"{name}: expected {order}, but entry {k} ({values[k]}) comes after {values[k - 1]}"
        )
