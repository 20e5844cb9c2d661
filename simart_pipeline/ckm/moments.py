"""Per-cell power moments: the one definition of every CKM propagation layer, for both solvers.

The reference solver (PathSolver at cell centres) and the fast one-pass solver (shoot and bounce
over the grid) reduce what they find in a cell to the same power-weighted sums,
:class:`CellMoments`; :func:`layers_from_moments` turns the sums into layers. So both modes write
the same layers with the same names, units and definitions by construction.

Definitions (p: the power gain of a path or of a ray tube deposit, element to element):

- path gain ``G = sum p``; path loss ``-G`` in dB.
- time of arrival: the smallest delay; delays are accumulated as excess over ``tau0`` (the
  straight-line delay from the transmitter to the cell centre) so that float64 sums keep ns
  precision at km range; ``mean_delay = tau0 + sum p dtau / G``;
  RMS delay spread ``sqrt(sum p dtau^2 / G - (sum p dtau / G)^2)``.
- mean angle ``atan2(sum p sin x, sum p cos x)``; angular spread: the circular angle spread of
  3GPP TR 38.901 Annex A.1, ``sqrt(-2 ln R)`` with ``R = |sum p exp(j x)| / G``, for the azimuth
  and the zenith of arrival (ASA, ZSA) and of departure (ASD, ZSD), in degrees.
- LoS power fraction ``sum over line-of-sight contributions p / G``; LoS flag: fraction > 0.5.
- effective count ``(sum p)^2 / sum p^2`` (Kish): the number of equal contributions that would
  give the same spread of weights; 1 when one path or ray tube carries the cell's gain, the hit
  count when all carry the same. In fast mode a cell near 1 holds a Monte-Carlo value that one
  ray decided (docs/ckm-one-pass.md, heavy tails).
- beam gain of beam b: ``sum p |w_b^T v(u_dep)|^2`` (incoherent over paths: no inter-path phase),
  ``w_b`` the unit-norm precoder as the codebook stores it (no conjugation, as ``link.beams``) and
  ``v`` the transmit array response.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from simart_pipeline.link.budget import power_db

ANGLES = ("azimuth_arrival", "zenith_arrival", "azimuth_departure", "zenith_departure")
SPREAD_NAMES = {"azimuth_arrival": "asa_deg", "zenith_arrival": "zsa_deg",
                "azimuth_departure": "asd_deg", "zenith_departure": "zsd_deg"}
MEAN_ANGLE_NAMES = {"azimuth_arrival": "mean_azimuth_arrival_deg", "zenith_arrival": "mean_zenith_arrival_deg",
                    "azimuth_departure": "mean_azimuth_departure_deg",
                    "zenith_departure": "mean_zenith_departure_deg"}


@dataclass
class CellMoments:
    """Power-weighted sums over what reached each cell; every array has the same grid shape
    ``S`` (e.g. ``[bs, height, y, x]``), ``beam_power`` has ``S + [num_beams]``."""

    power: np.ndarray          # sum p (linear gain)
    los_power: np.ndarray      # sum p over line-of-sight contributions
    count: np.ndarray          # number of paths (reference) or ray hits (fast), int64
    min_delay_s: np.ndarray    # smallest delay; +inf where nothing arrived
    tau0_s: np.ndarray         # straight-line delay tx -> cell centre
    p_excess_delay_s: np.ndarray    # sum p (tau - tau0)
    p_excess_delay2_s2: np.ndarray  # sum p (tau - tau0)^2
    p_cos: np.ndarray          # [S, 4] sum p cos(angle), angles in ANGLES order
    p_sin: np.ndarray          # [S, 4] sum p sin(angle)
    beam_power: np.ndarray | None = None  # [S, num_beams]
    power_sq: np.ndarray | None = None    # sum p^2 (for the effective number of contributions)

    @classmethod
    def zeros(cls, shape: tuple[int, ...], num_beams: int | None = None) -> "CellMoments":
        z = np.zeros(shape)
        return cls(power=z.copy(), los_power=z.copy(), count=np.zeros(shape, np.int64),
                   min_delay_s=np.full(shape, np.inf), tau0_s=z.copy(), p_excess_delay_s=z.copy(),
                   p_excess_delay2_s2=z.copy(), p_cos=np.zeros(shape + (4,)), p_sin=np.zeros(shape + (4,)),
                   beam_power=None if num_beams is None else np.zeros(shape + (num_beams,)),
                   power_sq=z.copy())

    def merge(self, other: "CellMoments") -> "CellMoments":
        """Sums of two disjoint sets of contributions to the same cells (e.g. two ray batches)."""
        out = {}
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "min_delay_s":
                out[f.name] = np.minimum(a, b)
            elif f.name == "tau0_s":
                out[f.name] = a
            elif a is None or b is None:
                out[f.name] = None
            else:
                out[f.name] = a + b
        return CellMoments(**out)


def path_sum(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Sum over a path axis one term after another, in path order: the same bits whatever
    invalid (zero) paths pad the row after its valid ones. numpy's pairwise sum groups the terms
    by the axis length, and a call's rows are padded to its receiver with the most paths, so a CKM
    cell's sums moved by an ulp with the receivers traced beside it (the tiling)."""
    if x.shape[axis] == 0:
        return np.sum(x, axis=axis)
    return np.take(np.cumsum(x, axis=axis), -1, axis=axis)


def path_moments(power: np.ndarray, delay_s: np.ndarray, valid: np.ndarray, los: np.ndarray,
                 angles_rad: np.ndarray, tau0_s: np.ndarray,
                 beam_power: np.ndarray | None = None) -> CellMoments:
    """Moments of discrete paths (the reference mode).

    :param power: ``[S, path]`` path gain; ``delay_s``, ``valid``, ``los`` likewise
    :param angles_rad: ``[S, path, 4]`` in :data:`ANGLES` order (azimuth/zenith of arrival, departure)
    :param tau0_s: ``[S]``; ``beam_power``: ``[S, path, num_beams]`` per-path beam gains
    """
    p = np.where(valid, power, 0.0).astype(np.float64)
    dtau = np.where(valid, delay_s - tau0_s[..., None], 0.0)
    ang = np.asarray(angles_rad, np.float64)
    return CellMoments(
        power=path_sum(p), los_power=path_sum(np.where(los & valid, p, 0.0)),
        count=valid.sum(-1).astype(np.int64),
        min_delay_s=np.min(np.where(valid, delay_s, np.inf), axis=-1, initial=np.inf),
        tau0_s=np.asarray(tau0_s, np.float64), p_excess_delay_s=path_sum(p * dtau),
        p_excess_delay2_s2=path_sum(p * dtau**2),
        p_cos=path_sum(p[..., None] * np.cos(ang), -2), p_sin=path_sum(p[..., None] * np.sin(ang), -2),
        beam_power=None if beam_power is None else path_sum(np.where(valid[..., None], beam_power, 0.0), -2),
        power_sq=path_sum(p * p))


def effective_count(m: CellMoments) -> np.ndarray:
    """Kish's effective sample size of each cell's sum, ``(sum p)^2 / sum p^2``: the hit count
    where every ray tube carries the same power, 1 where one carries it all; 0 where nothing
    arrived."""
    return np.where(m.power_sq > 0, m.power**2 / np.where(m.power_sq > 0, m.power_sq, 1.0), 0.0)


def too_few_hits(m: CellMoments, min_count: int = 1, min_effective_count: float = 1.0) -> np.ndarray:
    """Cells whose sums a layer does not trust: fewer than ``min_count`` ray hits or, with
    ``min_effective_count`` above 1, an effective count ``(sum p)^2 / sum p^2`` (Kish) below it:
    many hits, but one or two rays carry the sum. The one rule of ``enough_hits`` (path gain,
    ToA, LoS, beams; and of the adaptive pass) and of the spreads and mean angles, each with its
    own minimums (``ckm.min_hits_for_power`` / ``min_effective_hits_for_power``,
    ``ckm.min_hits_for_spread`` / ``min_effective_hits_for_spread``). A second moment needs more:
    Munich at 1e7 rays, every mechanism, the cells below 10 effective hits hold a delay spread 45
    ns (p50) from the same solver's at 1e8 rays, the others 4 ns (docs/ckm-one-pass.md, "Session
    37")."""
    few = m.count < min_count
    if min_effective_count > 1.0 and m.power_sq is not None:
        few = few | (m.power**2 < min_effective_count * m.power_sq)
    return few


def layers_from_moments(m: CellMoments, min_count_for_spread: int = 1,
                        min_count_for_power: int = 1, min_effective_count_for_power: float = 1.0,
                        min_effective_count_for_spread: float = 1.0) -> dict[str, np.ndarray]:
    """Layer arrays (grid shape ``S``) from moments; NaN where a layer has no value.

    ``has_path``: anything arrived. ``enough_hits``: something arrived and ``count`` reaches
    ``min_count_for_power``; path gain, ToA, mean delay, LoS and beams are NaN (LoS False, best
    beam -1) elsewhere: a cell reached by a ray or two holds a gain that can be tens of dB off (the
    fast solver's guard; 1 in reference mode, where each count is an exact path). With
    ``min_effective_count_for_power`` above 1, a cell whose ``effective_count`` (Kish) stays below
    it is masked the same way: many hits, but one ray carries the gain. Spreads and mean angles
    also need ``min_count_for_spread`` hits and an effective count of
    ``min_effective_count_for_spread`` (:func:`too_few_hits`).
    """
    has = m.power > 0
    g = np.where(has, m.power, 1.0)
    enough = has & ~too_few_hits(m, min_count_for_power, min_effective_count_for_power)
    out: dict[str, np.ndarray] = {"has_path": has, "enough_hits": enough, "count": m.count}
    if m.power_sq is not None:  # Kish's effective sample size of the cell's sum
        out["effective_count"] = np.where(has, effective_count(m), np.nan)
    out["path_gain_db"] = np.where(enough, power_db(m.power), np.nan)
    out["path_loss_db"] = -out["path_gain_db"]
    out["los_power_fraction"] = np.where(enough, m.los_power / g, np.nan)
    out["los"] = enough & (m.los_power / g > 0.5)
    out["toa_s"] = np.where(enough & np.isfinite(m.min_delay_s), m.min_delay_s, np.nan)
    mean_excess = m.p_excess_delay_s / g
    var = np.maximum(m.p_excess_delay2_s2 / g - mean_excess**2, 0.0)
    stable = enough & ~too_few_hits(m, min_count_for_spread, min_effective_count_for_spread)
    out["mean_delay_s"] = np.where(enough, m.tau0_s + mean_excess, np.nan)
    out["rms_delay_spread_s"] = np.where(stable, np.sqrt(var), np.nan)
    for k, name in enumerate(ANGLES):
        c, s = m.p_cos[..., k], m.p_sin[..., k]
        r = np.clip(np.hypot(c, s) / g, 1e-300, 1.0)
        out[SPREAD_NAMES[name]] = np.where(stable, np.degrees(np.sqrt(-2.0 * np.log(r))), np.nan)
        out[MEAN_ANGLE_NAMES[name]] = np.where(stable, np.degrees(np.arctan2(s, c)), np.nan)
    if m.beam_power is not None:
        bp = m.beam_power
        out["beam_gain_db"] = np.where(enough[..., None], power_db(bp), np.nan)
        best = np.argmax(bp, axis=-1)
        out["best_beam"] = np.where(enough, best, -1).astype(np.int32)
        best_gain = np.take_along_axis(bp, best[..., None], axis=-1)[..., 0]
        out["best_beam_gain_db"] = np.where(enough, power_db(best_gain), np.nan)
    return out


# Units and definitions of every layer above: the store attrs and docs/ckm.md use these.
LAYER_ATTRS: dict[str, dict[str, str]] = {
    "has_path": dict(long_name="something arrived in the cell (a path or a ray)"),
    "enough_hits": dict(long_name="something arrived and the cell's count reaches ckm.min_hits_for_power "
                        "(fast mode; reference mode: has_path): gain, ToA, LoS and beam layers hold values"),
    "count": dict(units="1", long_name="number of paths (reference mode) or ray hits (fast mode)"),
    "effective_count": dict(units="1", long_name="effective number of contributions (sum p)^2 / sum p^2 (Kish): "
                            "1 when one path (reference) or one ray (fast) carries the cell's gain",
                            nan_means="cell masked (inside a building or outside the region), or nothing reached it"),
    "path_gain_db": dict(units="dB", long_name="path gain, incoherent sum over paths, element to element"),
    "path_loss_db": dict(units="dB", long_name="path loss (= -path gain)"),
    "los_power_fraction": dict(units="1", long_name="fraction of the path gain carried by line of sight"),
    "los": dict(long_name="line of sight: LoS power fraction above 0.5"),
    "toa_s": dict(units="s", long_name="time of arrival: delay of the earliest contribution"),
    "mean_delay_s": dict(units="s", long_name="power-weighted mean delay"),
    "rms_delay_spread_s": dict(units="s", long_name="RMS delay spread (power-weighted)"),
    "asa_deg": dict(units="degree", long_name="azimuth spread of arrival, circular (3GPP TR 38.901 A.1)"),
    "zsa_deg": dict(units="degree", long_name="zenith spread of arrival, circular (3GPP TR 38.901 A.1)"),
    "asd_deg": dict(units="degree", long_name="azimuth spread of departure, circular (3GPP TR 38.901 A.1)"),
    "zsd_deg": dict(units="degree", long_name="zenith spread of departure, circular (3GPP TR 38.901 A.1)"),
    "mean_azimuth_arrival_deg": dict(units="degree", long_name="power-weighted circular mean azimuth of arrival"),
    "mean_zenith_arrival_deg": dict(units="degree", long_name="power-weighted circular mean zenith of arrival"),
    "mean_azimuth_departure_deg": dict(units="degree", long_name="power-weighted circular mean azimuth of departure"),
    "mean_zenith_departure_deg": dict(units="degree", long_name="power-weighted circular mean zenith of departure"),
    "beam_gain_db": dict(units="dB", long_name="gain with each codebook beam at the transmitter, incoherent over paths"),
    "best_beam": dict(units="1", long_name="codebook index of the beam with the highest incoherent gain (-1: none)"),
    "best_beam_gain_db": dict(units="dB", long_name="gain of the best beam, incoherent over paths"),
}
