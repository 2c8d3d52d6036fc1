"""Ground-truth motion for the simulator: smooth paths with exact derivatives and attitude.

Frames (DESIGN.md section 3): nav = NED (x north, y east, z down), body = FRD, attitude as
ZYX Euler angles Ψ = (roll φ, pitch θ, yaw ψ) with `C_nav_body` = Rz(ψ) Ry(θ) Rx(φ) (the
paper's C^n_b). Times are float seconds `t_s` here; the caller converts to `stamp_ns`.

`waypoint_trajectory` interpolates the waypoints with a quintic B-spline (C^4), so position,
velocity, acceleration, jerk and snap are all analytic spline derivatives. The attitude is a
closed-form function of velocity and acceleration (yaw along the horizontal velocity, roll and
pitch from the lateral and forward acceleration), and its rates are obtained by exact
differentiation (chain rule, carried out with second-order Taylor "jets"), so the body angular
rate is consistent with the attitude to rounding error: the simulated IMU (eq. 1-2 inputs f^b,
ω^b) is the exact derivative of the ground truth, not a finite-difference approximation.
"""

from __future__ import annotations

import abc
import itertools
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline

from cvslam_cli.geometry.gravity import G_M_S2
from cvslam_cli.records.arrays import F64

# Below this fraction of the nominal speed the horizontal velocity is considered too small for
# the heading (yaw) to be well defined.
_MIN_HORIZONTAL_SPEED_FRACTION = 0.05


@dataclass(frozen=True, eq=False)
class MotionSample:
    """Exact motion at N times.

    t_s: (N,) seconds.
    p_nav_m: (N, 3) position of the body origin in nav (NED), metres.
    v_nav_m_s: (N, 3) velocity in nav, m/s.
    a_nav_m_s2: (N, 3) acceleration in nav (kinematic, gravity not included), m/s^2.
    C_nav_body: (N, 3, 3) body -> nav rotation (paper's C^n_b).
    euler_rad: (N, 3) ZYX Euler angles (roll, pitch, yaw), yaw wrapped to (-pi, pi].
    omega_body_rad_s: (N, 3) angular rate of body w.r.t. nav, expressed in body (ω^b).
    alpha_body_rad_s2: (N, 3) time derivative of omega_body_rad_s.
    """

    t_s: F64
    p_nav_m: F64
    v_nav_m_s: F64
    a_nav_m_s2: F64
    C_nav_body: F64
    euler_rad: F64
    omega_body_rad_s: F64
    alpha_body_rad_s2: F64

    @property
    def v_body_m_s(self) -> F64:
        """(N, 3) velocity expressed in body (the paper's state v^b, eq. 3)."""
        return np.einsum("nji,nj->ni", self.C_nav_body, self.v_nav_m_s)


class Trajectory(abc.ABC):
    """A rigid-body motion defined over [t0_s, t1_s]."""

    t0_s: float
    t1_s: float

    @property
    def duration_s(self) -> float:
        return self.t1_s - self.t0_s

    @abc.abstractmethod
    def sample(self, t_s: F64) -> MotionSample:
        """Exact motion at the (N,) times `t_s` (seconds)."""

    @abc.abstractmethod
    def distance_m(self) -> float:
        """Path length between t0_s and t1_s, metres."""


# ---------------------------------------------------------------------------------------------
# Rotation helpers (vectorised)


def euler_zyx_to_matrix_batch(euler_rad: F64) -> F64:
    """(N, 3) (roll, pitch, yaw) -> (N, 3, 3) C_nav_body = Rz(yaw) Ry(pitch) Rx(roll).

    Same convention as `cvslam_cli.geometry.rotations.euler_zyx_to_matrix`, vectorised.
    """
    e = np.asarray(euler_rad, dtype=float)
    cr, sr = np.cos(e[..., 0]), np.sin(e[..., 0])
    cp, sp = np.cos(e[..., 1]), np.sin(e[..., 1])
    cy, sy = np.cos(e[..., 2]), np.sin(e[..., 2])
    C = np.empty((*e.shape[:-1], 3, 3))
    C[..., 0, 0] = cp * cy
    C[..., 0, 1] = sr * sp * cy - cr * sy
    C[..., 0, 2] = cr * sp * cy + sr * sy
    C[..., 1, 0] = cp * sy
    C[..., 1, 1] = sr * sp * sy + cr * cy
    C[..., 1, 2] = cr * sp * sy - sr * cy
    C[..., 2, 0] = -sp
    C[..., 2, 1] = sr * cp
    C[..., 2, 2] = cr * cp
    return C


def euler_rates_to_body_rates(euler_rad: F64, euler_dot_rad_s: F64) -> F64:
    """ω^b = E(Ψ)^{-1} Ψ̇ for ZYX Euler angles (inverse of the paper's E_nb, eq. 1).

    With C = Rz(ψ) Ry(θ) Rx(φ), the body rate is the sum of the three elementary rates, each
    rotated into body: ω^b = φ̇ e_x + Rx(φ)^T θ̇ e_y + Rx(φ)^T Ry(θ)^T ψ̇ e_z, i.e.
        p = φ̇ − ψ̇ sin θ
        q = θ̇ cos φ + ψ̇ sin φ cos θ
        r = −θ̇ sin φ + ψ̇ cos φ cos θ
    """
    e = np.asarray(euler_rad, dtype=float)
    d = np.asarray(euler_dot_rad_s, dtype=float)
    cr, sr = np.cos(e[..., 0]), np.sin(e[..., 0])
    cp, sp = np.cos(e[..., 1]), np.sin(e[..., 1])
    return np.stack(
        [
            d[..., 0] - d[..., 2] * sp,
            d[..., 1] * cr + d[..., 2] * sr * cp,
            -d[..., 1] * sr + d[..., 2] * cr * cp,
        ],
        axis=-1,
    )


def _body_accelerations(euler: F64, d1: F64, d2: F64) -> F64:
    """dω^b/dt from Ψ, Ψ̇, Ψ̈ (derivative of `euler_rates_to_body_rates`)."""
    cr, sr = np.cos(euler[:, 0]), np.sin(euler[:, 0])
    cp, sp = np.cos(euler[:, 1]), np.sin(euler[:, 1])
    rd, pd, yd = d1[:, 0], d1[:, 1], d1[:, 2]
    rdd, pdd, ydd = d2[:, 0], d2[:, 1], d2[:, 2]
    return np.stack(
        [
            rdd - ydd * sp - yd * pd * cp,
            pdd * cr - pd * rd * sr + ydd * sr * cp + yd * rd * cr * cp - yd * pd * sr * sp,
            -pdd * sr - pd * rd * cr + ydd * cr * cp - yd * rd * sr * cp - yd * pd * cr * sp,
        ],
        axis=-1,
    )


# ---------------------------------------------------------------------------------------------
# Second-order Taylor jets: exact value, first and second time derivative through the chain rule


@dataclass(frozen=True, eq=False)
class _Jet:
    """f, f', f'' (arrays of the same shape)."""

    v: F64
    d1: F64
    d2: F64

    def __add__(self, o: _Jet) -> _Jet:
        return _Jet(self.v + o.v, self.d1 + o.d1, self.d2 + o.d2)

    def __sub__(self, o: _Jet) -> _Jet:
        return _Jet(self.v - o.v, self.d1 - o.d1, self.d2 - o.d2)

    def __mul__(self, o: _Jet | float) -> _Jet:
        if isinstance(o, _Jet):
            return _Jet(
                self.v * o.v,
                self.d1 * o.v + self.v * o.d1,
                self.d2 * o.v + 2.0 * self.d1 * o.d1 + self.v * o.d2,
            )
        return _Jet(self.v * o, self.d1 * o, self.d2 * o)

    def __truediv__(self, o: _Jet) -> _Jet:
        # r = 1/g: r' = -g'/g^2, r'' = -g''/g^2 + 2 g'^2/g^3
        inv = 1.0 / o.v
        r = _Jet(inv, -o.d1 * inv**2, -o.d2 * inv**2 + 2.0 * o.d1**2 * inv**3)
        return self * r

    def compose(self, f0: F64, f1: F64, f2: F64) -> _Jet:
        """g(self) given g, g', g'' evaluated at self.v (Faà di Bruno, order 2)."""
        return _Jet(f0, f1 * self.d1, f2 * self.d1**2 + f1 * self.d2)


def _jet_sqrt(x: _Jet) -> _Jet:
    s = np.sqrt(x.v)
    return x.compose(s, 0.5 / s, -0.25 / (s * x.v))


def _jet_atan(x: _Jet) -> _Jet:
    den = 1.0 + x.v**2
    return x.compose(np.arctan(x.v), 1.0 / den, -2.0 * x.v / den**2)


def _jet_saturate(x: _Jet, limit: float) -> _Jet:
    """limit * tanh(x / limit): ≈ x for |x| << limit, smooth, |result| < limit."""
    th = np.tanh(x.v / limit)
    sech2 = 1.0 - th**2
    return x.compose(limit * th, sech2, -2.0 * th * sech2 / limit)


# ---------------------------------------------------------------------------------------------
# Spline trajectory


class SplineTrajectory(Trajectory):
    """Quintic spline through waypoints with velocity-aligned attitude (see module docstring).

    Build with `waypoint_trajectory`. A closed trajectory is periodic: `sample` accepts any time
    and wraps it onto [t0_s, t1_s) (repeated laps); an open one rejects times outside
    [t0_s, t1_s].
    """

    def __init__(
        self,
        spline: BSpline,
        knots_t_s: F64,
        *,
        kind: Literal["uav", "ugv"],
        closed: bool,
        max_tilt_rad: float,
        z_ugv_m: float,
    ) -> None:
        self.kind = kind
        self.closed = closed
        self.max_tilt_rad = max_tilt_rad
        self.knots_t_s = knots_t_s
        self.t0_s = float(knots_t_s[0])
        self.t1_s = float(knots_t_s[-1])
        self._derivs = [spline] + [spline.derivative(n) for n in range(1, 5)]
        self._z_ugv_m = z_ugv_m

    def _wrap(self, t: F64) -> F64:
        if self.closed:
            return self.t0_s + np.mod(t - self.t0_s, self.duration_s)
        tol = 1e-9 * max(1.0, abs(self.t1_s))
        if t.size and (t.min() < self.t0_s - tol or t.max() > self.t1_s + tol):
            raise ValueError(
                f"times [{t.min():.6f}, {t.max():.6f}] s outside the trajectory "
                f"[{self.t0_s:.6f}, {self.t1_s:.6f}] s"
            )
        return np.clip(t, self.t0_s, self.t1_s)

    def _derivatives(self, t_s: F64) -> list[F64]:
        """[p, v, a, j, s] each (N, 3) in nav."""
        tw = self._wrap(np.asarray(t_s, dtype=float).reshape(-1))
        out = [np.asarray(d(tw), dtype=float).reshape(-1, 3) for d in self._derivs]
        if self.kind == "ugv":
            out[0][:, 2] = self._z_ugv_m
            for d in out[1:]:
                d[:, 2] = 0.0
        return out

    def sample(self, t_s: F64) -> MotionSample:
        """Exact motion at `t_s` (N,).

        Attitude (all from the spline derivatives v, a, j, s, horizontal components x, y):
          H = v_x² + v_y², h = √H (horizontal speed)
          c = v_x a_y − v_y a_x, d = v_x a_x + v_y a_y
          yaw   ψ = atan2(v_y, v_x),         ψ̇ = c / H
          UAV:  a_lat = c / h (towards the right wing), a_fwd = d / h
                roll  φ = S(atan(a_lat / g))   (coordinated-turn bank)
                pitch θ = S(−atan(a_fwd / g))  (nose down to accelerate)
                S(x) = max_tilt · tanh(x / max_tilt)  (smooth saturation)
          UGV:  φ = θ = 0, z constant.
        Rates Ψ̇, Ψ̈ come from exact second-order jets (ċ and Ḣ need the jerk, c̈ and Ḧ the
        snap), then ω^b = E(Ψ)^{-1} Ψ̇ and α^b = dω^b/dt.
        """
        t = np.asarray(t_s, dtype=float).reshape(-1)
        p, v, a, j, s = self._derivatives(t)
        n = t.size
        vx, vy = _Jet(v[:, 0], a[:, 0], j[:, 0]), _Jet(v[:, 1], a[:, 1], j[:, 1])
        ax, ay = _Jet(a[:, 0], j[:, 0], s[:, 0]), _Jet(a[:, 1], j[:, 1], s[:, 1])
        H = vx * vx + vy * vy
        c = vx * ay - vy * ax
        yaw_rate = c / H  # jet of ψ̇: (ψ̇, ψ̈, ψ⃛)
        yaw = np.arctan2(v[:, 1], v[:, 0])
        euler = np.zeros((n, 3))
        d1 = np.zeros((n, 3))
        d2 = np.zeros((n, 3))
        euler[:, 2], d1[:, 2], d2[:, 2] = yaw, yaw_rate.v, yaw_rate.d1
        if self.kind == "uav":
            h = _jet_sqrt(H)
            d = vx * ax + vy * ay
            roll = _jet_saturate(_jet_atan((c / h) * (1.0 / G_M_S2)), self.max_tilt_rad)
            pitch = _jet_saturate(_jet_atan((d / h) * (-1.0 / G_M_S2)), self.max_tilt_rad)
            for col, jet in ((0, roll), (1, pitch)):
                euler[:, col], d1[:, col], d2[:, col] = jet.v, jet.d1, jet.d2
        return MotionSample(
            t_s=t,
            p_nav_m=p,
            v_nav_m_s=v,
            a_nav_m_s2=a,
            C_nav_body=euler_zyx_to_matrix_batch(euler),
            euler_rad=euler,
            omega_body_rad_s=euler_rates_to_body_rates(euler, d1),
            alpha_body_rad_s2=_body_accelerations(euler, d1, d2),
        )

    def distance_m(self) -> float:
        """Arc length ∫|v| dt over [t0_s, t1_s] (8-point Gauss-Legendre per knot interval)."""
        x, w = np.polynomial.legendre.leggauss(8)
        a, b = self.knots_t_s[:-1, None], self.knots_t_s[1:, None]
        tq = 0.5 * (b - a) * x[None, :] + 0.5 * (a + b)
        v = self._derivatives(tq.reshape(-1))[1]
        speed = np.linalg.norm(v, axis=1).reshape(tq.shape)
        return float(np.sum(0.5 * (b - a) * w[None, :] * speed))


class StationaryTrajectory(Trajectory):
    """A body at rest at a fixed pose over [t0_s, t1_s] (e.g. IMU calibration, noise tests)."""

    def __init__(self, p_nav_m: F64, euler_rad: F64, t0_s: float, t1_s: float) -> None:
        self.p_nav_m = np.asarray(p_nav_m, dtype=float).reshape(3)
        self.euler_rad = np.asarray(euler_rad, dtype=float).reshape(3)
        if not (np.all(np.isfinite(self.p_nav_m)) and np.all(np.isfinite(self.euler_rad))):
            raise ValueError("stationary pose must be finite")
        if not t1_s > t0_s:
            raise ValueError(f"t1_s ({t1_s}) must be greater than t0_s ({t0_s})")
        self.t0_s, self.t1_s = float(t0_s), float(t1_s)

    def sample(self, t_s: F64) -> MotionSample:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        n = t.size
        euler = np.tile(self.euler_rad, (n, 1))
        zeros = np.zeros((n, 3))
        return MotionSample(
            t_s=t,
            p_nav_m=np.tile(self.p_nav_m, (n, 1)),
            v_nav_m_s=zeros.copy(),
            a_nav_m_s2=zeros.copy(),
            C_nav_body=euler_zyx_to_matrix_batch(euler),
            euler_rad=euler,
            omega_body_rad_s=zeros.copy(),
            alpha_body_rad_s2=zeros.copy(),
        )

    def distance_m(self) -> float:
        return 0.0


def waypoint_trajectory(
    waypoints_nav_m: F64,
    speed_m_s: float,
    *,
    kind: Literal["uav", "ugv"],
    closed: bool = False,
    t0_s: float = 0.0,
    max_tilt_rad: float = 0.35,
) -> SplineTrajectory:
    """A smooth (C^4) trajectory through `waypoints_nav_m` (K, 3) at about `speed_m_s`.

    Knot times are the cumulative chord lengths divided by the speed. The position is the
    quintic interpolating B-spline through the waypoints at those times:
      closed=False: velocity at each end = speed × direction of the first/last segment,
                    acceleration 0 at both ends (the vehicle is already cruising);
      closed=True:  periodic spline (position and its first four derivatives continuous
                    across the closing point; the loop returns exactly to its start). A last
                    waypoint equal to the first is accepted and dropped.
    kind="ugv" needs all waypoints at the same z ((K, 2) input is taken as z = 0); the
    vehicle stays level. kind="uav" banks and pitches with the acceleration, up to
    ±max_tilt_rad (smooth saturation).

    Raises ValueError for fewer than 2 (closed: 3) distinct waypoints, repeated consecutive
    waypoints, a non-positive speed, an unknown kind, a UGV path that is not level, or a path
    whose horizontal speed gets too small for the heading to be defined (vertical segments).
    """
    if kind not in ("uav", "ugv"):
        raise ValueError(f"kind must be 'uav' or 'ugv', got {kind!r}")
    wp = np.asarray(waypoints_nav_m, dtype=float)
    if wp.ndim == 2 and wp.shape[1] == 2 and kind == "ugv":
        wp = np.column_stack([wp, np.zeros(len(wp))])
    if wp.ndim != 2 or wp.shape[1] != 3:
        raise ValueError(f"waypoints must be a (K, 3) array, got shape {wp.shape}")
    if not np.all(np.isfinite(wp)):
        raise ValueError("waypoints must be finite")
    if not (np.isfinite(speed_m_s) and speed_m_s > 0):
        raise ValueError(f"speed must be positive, got {speed_m_s}")
    if not (0.0 < max_tilt_rad < np.pi / 2):
        raise ValueError(f"max_tilt_rad must be in (0, pi/2), got {max_tilt_rad}")
    if closed and len(wp) >= 2 and np.linalg.norm(wp[-1] - wp[0]) < 1e-9:
        wp = wp[:-1]
    need = 3 if closed else 2
    if len(wp) < need:
        raise ValueError(
            f"a {'closed' if closed else 'open'} trajectory needs at least {need} "
            f"distinct waypoints, got {len(wp)}"
        )
    if kind == "ugv" and np.ptp(wp[:, 2]) > 1e-9:
        raise ValueError(
            f"a ugv trajectory must be level: waypoint z spans {np.ptp(wp[:, 2]):.3g} m"
        )
    pts = np.vstack([wp, wp[:1]]) if closed else wp
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    bad = np.flatnonzero(seg < 1e-6)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"waypoints {i} and {(i + 1) % len(wp)} coincide (repeated consecutive waypoints)"
        )
    knots = t0_s + np.concatenate([[0.0], np.cumsum(seg)]) / speed_m_s
    if closed:
        spline = make_interp_spline(knots, pts, k=5, bc_type="periodic")
    else:
        v0 = speed_m_s * (pts[1] - pts[0]) / seg[0]
        v1 = speed_m_s * (pts[-1] - pts[-2]) / seg[-1]
        zero = np.zeros(3)
        spline = make_interp_spline(
            knots, pts, k=5, bc_type=([(1, v0), (2, zero)], [(1, v1), (2, zero)])
        )
    traj = SplineTrajectory(
        spline, knots, kind=kind, closed=closed, max_tilt_rad=max_tilt_rad, z_ugv_m=wp[0, 2]
    )
    # The heading follows the horizontal velocity: it must not vanish anywhere.
    per = 32
    tq = np.concatenate(
        [np.linspace(a, b, per, endpoint=False) for a, b in itertools.pairwise(knots)]
        + [knots[-1:]]
    )
    v = traj._derivatives(tq)[1]
    h = np.hypot(v[:, 0], v[:, 1])
    i = int(np.argmin(h))
    if h[i] < _MIN_HORIZONTAL_SPEED_FRACTION * speed_m_s:
        raise ValueError(
            f"horizontal speed drops to {h[i]:.3g} m/s near t = {tq[i]:.2f} s: heading "
            "undefined (vertical segment or cusp); add waypoints or make the path less steep"
        )
    return traj
