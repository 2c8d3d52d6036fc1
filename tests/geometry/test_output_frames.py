"""Export frames: re-expressing `T_nav_body` poses as `T_world_sensor`, the ENU frame, and
the checks of a `DatasetFrame`."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.geometry.output_frames import T_ENU_NAV, DatasetFrame, reexpress
from cvslam_cli.geometry.rotations import invert_T, make_T, quat_xyzw_to_matrix
from cvslam_cli.records.poses import PoseTable


def random_T(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return make_T(quat_xyzw_to_matrix(q / np.linalg.norm(q)), rng.normal(scale=5.0, size=3))


def random_table(n: int, rng: np.random.Generator) -> PoseTable:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return PoseTable(np.arange(n, dtype=np.int64) * 10**8, rng.normal(scale=30, size=(n, 3)), q)


def as_T(table: PoseTable) -> np.ndarray:
    R = quat_xyzw_to_matrix(table.q_nav_body_xyzw)
    return np.stack([make_T(r, p) for r, p in zip(R, table.p_nav_m, strict=True)])


def test_reexpress_is_the_matrix_product_and_inverts():
    rng = np.random.default_rng(0)
    table = random_table(20, rng)
    A, B = random_T(rng), random_T(rng)
    out = reexpress(table, A, B)
    np.testing.assert_array_equal(out.stamps_ns, table.stamps_ns)
    np.testing.assert_allclose(as_T(out), A @ as_T(table) @ B, atol=1e-12)
    back = reexpress(out, invert_T(A), invert_T(B))
    np.testing.assert_allclose(as_T(back), as_T(table), atol=1e-12)
    assert len(reexpress(random_table(0, rng), A, B)) == 0


def test_enu_is_z_up_beside_ned():
    north, east, down = 3.0, 4.0, 5.0
    np.testing.assert_allclose(T_ENU_NAV @ [north, east, down, 1.0], [east, north, -down, 1.0])
    assert np.linalg.det(T_ENU_NAV[:3, :3]) == pytest.approx(1.0)


def test_dataset_frame_checks_its_transforms():
    rng = np.random.default_rng(1)
    T = random_T(rng)
    f = DatasetFrame(T, np.eye(4), "w", "s")
    np.testing.assert_allclose(f.T_world_nav @ T, np.eye(4), atol=1e-12)
    with pytest.raises(ValueError, match="T_nav_world: expected a finite 4x4"):
        DatasetFrame(np.eye(3), np.eye(4), "w", "s")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="T_body_sensor: not a rigid transform"):
        DatasetFrame(np.eye(4), bad, "w", "s")
