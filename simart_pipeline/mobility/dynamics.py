"""Jerk-limited motion along a corner-blended path, never exceeding a platform's dynamic limits.

The motion is built so that every limit holds by construction, then checked:

- **Path** (:mod:`simart_pipeline.mobility.path`): straight segments and clothoid-pair blends of
  continuous curvature, or stops at the vertices.
- **Speed profile** along arc length ``s``. On a blend the speed is constant, ``v_c``, so the
  acceleration is purely lateral, ``v_c**2 kappa``, and the jerk is
  ``v_c**3 sqrt(kappa'**2 + kappa**4)``: ``v_c`` is the largest speed that keeps both within the
  lateral-acceleration and jerk limits at the blend's peak curvature (and the cruise speed). On a
  straight segment the speed changes from its entry to its exit speed through symmetric S-curves
  (piecewise-constant jerk ``+-J``, acceleration at most ``A``, both zero at the ends), cruising in
  between at the highest speed the segment's length allows, up to the cruise speed: the
  time-optimal jerk-limited profile between the given end speeds. Entry and exit speeds that a
  segment is too short to join are lowered by a forward and a backward pass (the classic
  feed-rate planning of machine tools, here with the exact distance an S-curve needs). The motion
  starts and ends at rest, and stops where the path stops; there the platform turns in place to
  the next segment's heading with a minimum-jerk (quintic) yaw profile of bounded rate and
  angular acceleration.
- **Check**: speed, acceleration (total, tangential, lateral) and jerk are evaluated at nine
  instants of every piece of constant jerk (where they are polynomials whose extremes lie at the
  ends; on blends at the mid-point, which is a piece boundary). Should rounding push any ratio to
  its limit above 1, the whole motion is slowed by a uniform time scaling ``k``, which divides
  speed by ``k``, acceleration by ``k**2`` and jerk by ``k**3``.

Limits: ``A = min(max_tangential_acceleration_mps2, max_acceleration_mps2)`` along the path,
``min(max_lateral_acceleration_mps2, max_acceleration_mps2)`` across it (the two never act at the
same instant, so the total stays below ``max_acceleration_mps2``), ``J = max_jerk_mps3``, speed at
most ``min(cruise speed, max_speed_mps)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simart_pipeline.mobility import attitude as att
from simart_pipeline.mobility import path as geo

SAMPLES_PER_SEGMENT = 9
HEADROOM = 1 - 1e-9  # the plan aims this fraction of each limit, so rounding never crosses it


def _scurve_time(dv, a, j):
    """Time (s) of a symmetric S-curve changing speed by ``dv >= 0``, zero acceleration at both ends."""
    dv = np.asarray(dv, np.float64)
    return np.where(dv >= a * a / j, dv / a + a / j, 2.0 * np.sqrt(dv / j))


def _scurve_distance(v0, v1, a, j):
    """Distance (m) of that S-curve from ``v0`` to ``v1``: its mean speed is ``(v0 + v1) / 2``."""
    return 0.5 * (v0 + v1) * _scurve_time(np.abs(np.asarray(v1) - v0), a, j)


def _reach(v0: float, length: float, vmax: float, a: float, j: float) -> float:
    """Highest speed (<= vmax) an S-curve reaches from ``v0`` within ``length`` (closed form)."""
    if length <= 0:
        return v0
    db = (2 * v0 + a * a / j) * a / j             # distance to gain a**2 / j (no constant-a phase)
    if length <= db:
        # (2 v0 + j u**2) u = length with u = sqrt(dv / j): one positive root (Cardano), then Newton.
        p, q = 2 * v0 / j, -length / j
        r = np.sqrt(q * q / 4 + p ** 3 / 27)
        u = np.cbrt(-q / 2 + r) + np.cbrt(-q / 2 - r)
        for _ in range(2):
            u -= (u ** 3 + p * u + q) / (3 * u * u + p)
        dv = j * u * u
    else:
        # dv**2 / (2a) + dv (v0 / a + a / (2j)) + v0 a / j - length = 0, in its cancellation-free form.
        qa, qb, qc = 1 / (2 * a), v0 / a + a / (2 * j), v0 * a / j - length
        dv = -2 * qc / (qb + np.sqrt(qb * qb - 4 * qa * qc))
    return float(min(vmax, v0 + max(dv, 0.0)))


def _peak(va: np.ndarray, vb: np.ndarray, length: np.ndarray, vmax: float, a: float, j: float) -> np.ndarray:
    """Highest cruise speed of each straight segment: ``D(va, vp) + D(vp, vb) <= length``."""
    lo = np.maximum(va, vb)
    hi = np.full_like(lo, vmax)
    fits = _scurve_distance(va, hi, a, j) + _scurve_distance(hi, vb, a, j) <= length
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        ok = _scurve_distance(va, mid, a, j) + _scurve_distance(mid, vb, a, j) <= length
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    return np.where(fits, vmax, lo)


def _phases(v0: float, v1: float, a: float, j: float) -> list[tuple[float, float]]:
    """(jerk m s-3, duration s) of the S-curve from ``v0`` to ``v1``."""
    dv = abs(v1 - v0)
    if dv <= 0:
        return []
    sgn = 1.0 if v1 > v0 else -1.0
    if dv >= a * a / j:
        tj, ta = a / j, dv / a - a / j
        return [(sgn * j, tj)] + ([(0.0, ta)] if ta > 0 else []) + [(-sgn * j, tj)]
    tj = float(np.sqrt(dv / j))
    return [(sgn * j, tj), (-sgn * j, tj)]


def turn_in_place_time(dyaw: float, max_rate: float, max_acc: float) -> float:
    """Duration (s) of a quintic yaw turn by ``dyaw`` (rad) within the rate and angular-acceleration
    limits: its peak rate is ``15/8 dyaw / T``, its peak acceleration ``10/sqrt(3) dyaw / T**2``."""
    d = abs(dyaw)
    return max(15 * d / (8 * max_rate), np.sqrt(10 * d / (np.sqrt(3) * max_acc)))


@dataclass
class MotionPlan:
    """A platform's motion: pieces of constant jerk along the path, and turns in place.

    Segment arrays are ``[num_segments]``: path piece, start time (s, from the motion start,
    before time scaling), duration (s), and at the segment start the arc length on the piece (m),
    speed (m s-1), tangential acceleration (m s-2), with the constant jerk (m s-3); turns in
    place carry the yaw at their start and the yaw change (rad).
    """

    path: geo.CornerPath
    limits: object
    attitude: str
    start_s: float
    seg_piece: np.ndarray
    seg_t0: np.ndarray
    seg_duration: np.ndarray
    seg_s0: np.ndarray
    seg_v0: np.ndarray
    seg_a0: np.ndarray
    seg_jerk: np.ndarray
    seg_turn: np.ndarray
    seg_yaw0: np.ndarray
    seg_dyaw: np.ndarray
    time_scaling: float = 1.0

    @property
    def motion_duration_s(self) -> float:
        """Time (s) from the start of the motion to its end at rest, after time scaling."""
        return float((self.seg_t0[-1] + self.seg_duration[-1]) * self.time_scaling)

    @property
    def end_s(self) -> float:
        return self.start_s + self.motion_duration_s

    def evaluate(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """The motion at times ``t_s`` [n] (s): ``position_m``, ``velocity_mps``,
        ``acceleration_mps2``, ``jerk_mps3`` ([n, 3], world), ``orientation_xyzw`` [n, 4]
        (base_link into world), ``angular_velocity_radps`` [n, 3] (base_link), ``yaw_rad`` [n].
        Before the start and after the end the platform is at rest at the path's ends."""
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        tau = (t - self.start_s) / self.time_scaling
        end = self.seg_t0[-1] + self.seg_duration[-1]
        tc = np.clip(tau, 0.0, end)
        i = np.clip(np.searchsorted(self.seg_t0, tc, side="right") - 1, 0, len(self.seg_t0) - 1)
        out = self._state(i, tc - self.seg_t0[i])
        outside = (tau <= 0) | (tau >= end)
        for k in ("velocity_mps", "acceleration_mps2", "jerk_mps3", "angular_velocity_radps"):
            out[k][outside] = 0.0
        for k in ("tangential_acceleration_mps2", "lateral_acceleration_mps2"):
            out.pop(k)
        return out

    def _state(self, i: np.ndarray, u: np.ndarray) -> dict[str, np.ndarray]:
        """State at local time ``u`` (s, unscaled) into segments ``i``, time scaling applied."""
        k = self.time_scaling
        u = np.clip(u, 0.0, self.seg_duration[i])
        j = self.seg_jerk[i]
        a = self.seg_a0[i] + j * u
        v = self.seg_v0[i] + self.seg_a0[i] * u + j * u * u / 2
        s = self.seg_s0[i] + self.seg_v0[i] * u + self.seg_a0[i] * u * u / 2 + j * u ** 3 / 6
        piece = self.seg_piece[i]
        pos, tan, k1, k2 = geo.evaluate(self.path, piece, s)
        vel = tan * v[:, None]
        acc = k1 * (v * v)[:, None] + tan * a[:, None]
        jerk = k2 * (v ** 3)[:, None] + 3 * k1 * (v * a)[:, None] + tan * j[:, None]
        # Heading: the line's, along a blend the horizontal tangent's, in a turn the quintic's.
        yaw = self.path.heading_rad[piece].copy()
        yaw_rate = np.zeros_like(yaw)
        blend = (self.path.kind[piece] == geo.BLEND) & ~self.seg_turn[i]
        if blend.any():
            yb, rb = geo.blend_heading(self.path, piece[blend], tan[blend], k1[blend])
            yaw[blend], yaw_rate[blend] = yb, rb * v[blend]
        turn = self.seg_turn[i]
        if turn.any():
            dur = self.seg_duration[i][turn]
            x = u[turn] / dur
            yaw[turn] = self.seg_yaw0[i][turn] + self.seg_dyaw[i][turn] * (10 * x**3 - 15 * x**4 + 6 * x**5)
            yaw_rate[turn] = self.seg_dyaw[i][turn] * (30 * x**2 - 60 * x**3 + 30 * x**4) / dur
        vel, acc, jerk, yaw_rate = vel / k, acc / k**2, jerk / k**3, yaw_rate / k
        if self.attitude == "thrust":
            quat, omega = att.thrust_attitude(acc, jerk, yaw, yaw_rate)
        else:
            quat, omega = att.level_attitude(yaw, yaw_rate)
        return {"position_m": pos, "velocity_mps": vel, "acceleration_mps2": acc, "jerk_mps3": jerk,
                "orientation_xyzw": quat, "angular_velocity_radps": omega, "yaw_rad": yaw,
                "tangential_acceleration_mps2": a / k**2,
                "lateral_acceleration_mps2": np.linalg.norm(k1, axis=1) * v * v / k**2}

    def segment_samples(self, n: int = SAMPLES_PER_SEGMENT) -> dict[str, np.ndarray]:
        """The state at ``n`` evenly spaced instants of every segment, both ends included (each
        segment's own polynomial at its ends, so one-sided values at every boundary)."""
        i = np.repeat(np.arange(len(self.seg_t0)), n)
        u = np.tile(np.linspace(0.0, 1.0, n), len(self.seg_t0)) * self.seg_duration[i]
        out = self._state(i, u)
        out["time_s"] = self.start_s + (self.seg_t0[i] + u) * self.time_scaling
        return out

    def limit_ratios(self) -> dict[str, float]:
        """Largest value over the motion divided by its limit, per limited quantity (<= 1: within)."""
        lim = self.limits
        st = self.segment_samples()
        return {
            "speed": float(np.linalg.norm(st["velocity_mps"], axis=1).max() / lim.max_speed_mps),
            "acceleration": float(np.linalg.norm(st["acceleration_mps2"], axis=1).max() / lim.max_acceleration_mps2),
            "tangential_acceleration": float(np.abs(st["tangential_acceleration_mps2"]).max()
                                             / lim.max_tangential_acceleration_mps2),
            "lateral_acceleration": float(st["lateral_acceleration_mps2"].max() / lim.max_lateral_acceleration_mps2),
            "jerk": float(np.linalg.norm(st["jerk_mps3"], axis=1).max() / lim.max_jerk_mps3),
        }


def plan_motion(path: geo.CornerPath, limits, cruise_speed_mps: float, attitude: str = "level",
                start_s: float = 0.0) -> MotionPlan:
    """The jerk-limited motion along ``path`` from rest to rest, starting at ``start_s`` (s).

    :param limits: a :class:`simart_pipeline.config.DynamicLimits` (or any object with its fields).
    :param cruise_speed_mps: the speed aimed at on straight segments (capped by ``max_speed_mps``).
    :param attitude: ``"thrust"`` (quadrotor: body z along ``a + g``) or ``"level"``.
    """
    vmax = min(cruise_speed_mps, limits.max_speed_mps) * HEADROOM
    a_t = min(limits.max_tangential_acceleration_mps2, limits.max_acceleration_mps2) * HEADROOM
    a_n = min(limits.max_lateral_acceleration_mps2, limits.max_acceleration_mps2) * HEADROOM
    jmax = limits.max_jerk_mps3 * HEADROOM
    lines = np.flatnonzero(path.kind == geo.LINE)
    kmax, krate = geo.blend_curvature(path)
    length = path.length_m[lines]
    # Speed at each junction of lines: blends at their largest speed, stops and ends at rest.
    vj = np.zeros(len(lines) + 1)
    for k, p in enumerate(lines[:-1]):
        if path.kind[p + 1] == geo.BLEND:
            b = p + 1
            vj[k + 1] = min(vmax, np.sqrt(a_n / kmax[b]), np.cbrt(jmax / np.hypot(krate[b], kmax[b] ** 2)))
    for k in range(len(lines)):
        vj[k + 1] = min(vj[k + 1], _reach(vj[k], length[k], vmax, a_t, jmax))
    for k in range(len(lines) - 1, -1, -1):
        vj[k] = min(vj[k], _reach(vj[k + 1], length[k], vmax, a_t, jmax))
    vp = _peak(vj[:-1], vj[1:], length, vmax, a_t, jmax)
    rows: list[tuple] = []   # piece, duration, s0, v0, a0, jerk, turn, yaw0, dyaw
    for k, p in enumerate(lines):
        s, v, a = 0.0, vj[k], 0.0
        cruise = length[k] - _scurve_distance(vj[k], vp[k], a_t, jmax) - _scurve_distance(vp[k], vj[k + 1], a_t, jmax)
        phases = _phases(vj[k], vp[k], a_t, jmax)
        if cruise > 0 and vp[k] > 0:
            phases.append((0.0, float(cruise / vp[k])))
        phases += _phases(vp[k], vj[k + 1], a_t, jmax)
        for jerk, dur in phases:
            rows.append((p, dur, s, v, a, jerk, False, 0.0, 0.0))
            s += v * dur + a * dur ** 2 / 2 + jerk * dur ** 3 / 6
            v += a * dur + jerk * dur ** 2 / 2
            a += jerk * dur
        if k + 1 == len(lines):
            if not phases:
                rows.append((p, 0.0, length[k], 0.0, 0.0, 0.0, False, 0.0, 0.0))
            break
        if path.kind[p + 1] == geo.BLEND:
            lc = path.half_length_m[p + 1]
            for half in range(2):  # split at the peak curvature, so the check sees it
                rows.append((p + 1, lc / vj[k + 1], half * lc, vj[k + 1], 0.0, 0.0, False, 0.0, 0.0))
        else:
            dyaw = path.heading_rad[lines[k + 1]] - path.heading_rad[p]
            if abs(dyaw) > 1e-12:
                dur = turn_in_place_time(dyaw, limits.max_yaw_rate_radps, limits.max_yaw_acceleration_radps2)
                rows.append((p, dur, length[k], 0.0, 0.0, 0.0, True, path.heading_rad[p], dyaw))
    cols = list(zip(*rows))
    dur = np.array(cols[1], np.float64)
    plan = MotionPlan(path, limits, attitude, float(start_s), np.array(cols[0], np.int64),
                      np.concatenate([[0.0], np.cumsum(dur)[:-1]]), dur, np.array(cols[2], np.float64),
                      np.array(cols[3], np.float64), np.array(cols[4], np.float64), np.array(cols[5], np.float64),
                      np.array(cols[6], bool), np.array(cols[7], np.float64), np.array(cols[8], np.float64))
    r = plan.limit_ratios()
    k = max(1.0, r["speed"], np.sqrt(max(r["acceleration"], r["tangential_acceleration"],
                                          r["lateral_acceleration"])), np.cbrt(r["jerk"]))
    if k > 1.0:
        plan.time_scaling = float(k * (1 + 1e-12))
    return plan
