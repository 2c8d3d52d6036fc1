"""The record of every landmark observation the filter uses (updates, new landmarks, joint
initialisation, localisation), per vehicle, for `cvslam refine` (`fuse/observations.npz`).
Appending costs a list append per frame; nothing here changes the estimate."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cvslam_cli.records.arrays import F64, I64


@dataclass(eq=False)
class ObservationLog:
    """One vehicle's observations: per call, the frame stamp, landmark ids (k,) and their
    measurements z (k, 4)."""

    stamps_ns: list[int] = field(default_factory=list)
    ids: list[I64] = field(default_factory=list)
    z: list[F64] = field(default_factory=list)

    def add(self, stamp_ns: int, ids: I64, z: F64) -> None:
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if len(ids):
            self.stamps_ns.append(int(stamp_ns))
            self.ids.append(ids.copy())
            self.z.append(np.array(z, dtype=float).reshape(len(ids), 4))

    def arrays(self) -> tuple[I64, I64, F64]:
        """(stamps (N,), landmark ids (N,), z (N, 4)), in the order recorded."""
        if not self.ids:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 4))
        stamps = np.repeat(np.array(self.stamps_ns, dtype=np.int64), [len(i) for i in self.ids])
        return stamps, np.concatenate(self.ids), np.concatenate(self.z)
