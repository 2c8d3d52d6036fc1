"""The landmark observations a filter run used: which vehicle saw which landmark when, and
the stereo measurement it used (the input `cvslam refine` re-solves with)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, check_shape


@dataclass(frozen=True, eq=False)
class ObservationTable:
    """N observations, in no particular order: `vehicles` the vehicle names, vehicle (N,)
    int64 an index into them, stamp_ns (N,) int64 the frame's stamp, landmark_id (N,) int64
    the id in the run's map (`map.csv` `id`), z_px (N, 4) float64 (u_l, v_l, u_r, v_r), the
    undistorted pixels of the stereo match (eq. 19's measurement)."""

    vehicles: tuple[str, ...]
    vehicle: I64
    stamp_ns: I64
    landmark_id: I64
    z_px: F64

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        for name, shape in (
            ("vehicle", ("N",)),
            ("stamp_ns", ("N",)),
            ("landmark_id", ("N",)),
            ("z_px", ("N", 4)),
        ):
            dtype = "f" if name == "z_px" else "iu"
            check_shape(f"ObservationTable.{name}", getattr(self, name), shape, dtype, dims)
        v = self.vehicle
        if len(v) and not (v.min() >= 0 and v.max() < len(self.vehicles)):
            raise ValueError("ObservationTable.vehicle: expected indices into vehicles")

    def __len__(self) -> int:
        return len(self.stamp_ns)

    @staticmethod
    def concatenate(
        vehicles: Sequence[str], parts: Sequence[tuple[int, I64, I64, F64]]
    ) -> ObservationTable:
        """One table from (vehicle index, stamps (k,), landmark ids (k,), z (k, 4)) parts."""

        def cat(i: int, dtype: type, shape: tuple[int, ...]) -> np.ndarray:
            arrays = [np.asarray(p[i], dtype=dtype).reshape(-1, *shape) for p in parts]
            return np.concatenate(arrays) if arrays else np.zeros((0, *shape), dtype=dtype)

        veh = [np.full(len(p[1]), p[0], dtype=np.int64) for p in parts]
        return ObservationTable(
            tuple(vehicles),
            np.concatenate(veh) if veh else np.zeros(0, dtype=np.int64),
            cat(1, np.int64, ()).reshape(-1),
            cat(2, np.int64, ()).reshape(-1),
            cat(3, np.float64, (4,)),
        )
