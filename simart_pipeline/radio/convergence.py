"""Is PathSolver's sampling converged for this scene? The same links traced again with more samples.

PathSolver finds a path only where one of its ``samples_per_src`` rays met the faces of that
path's interaction sequence (and sampled its wedge); a far facade subtends few of them. The
default (1e5, on the run-time/error front of the demo, ``benchmarks.raytracing_front``) misses
paths on the demo itself (a link 4.7 dB and 85 ns off 1e6's) and far reflections in larger scenes:
in Sionna's ``etoile`` (750 x 575 m) cells 100-150 m from a 15 m station held delay spreads of
36-47 ns at 1e5 samples and 110-590 ns at 1e7, up to a quarter of their power arriving more than
1 us after the first path, while their path gain moved by under 1.5 dB: the delay spread is what
gives the missing paths away (docs/ray-tracing.md, "Sampling convergence").

:func:`sampling_convergence` traces a few receivers at the configured samples and at ``factor``
times as many, with the configured solver otherwise, and compares each (transmitter, receiver)
link's total path gain and RMS delay spread. The asset checks ``cirs_sampling_converged`` and
``ckm_reference_converged`` report it in the Dagster UI (a warning: the data is what was asked
for, but not what more samples give).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simart_pipeline.quality import CheckResult

CHECK_FACTOR = 10  # the second trace's samples per source, times the configured
CHECK_RECEIVERS = 8  # receivers traced twice (spread over the session, or over a map's cells)
GAIN_TOLERANCE_DB = 1.0  # a link's path gain may move this much with 10x the samples
# ... and its RMS delay spread this much, or this share of the finer trace's, whichever is larger:
# a few ns is sampling noise in the weak paths; tens of ns is a missing far path
DELAY_SPREAD_TOLERANCE_S = 10e-9
DELAY_SPREAD_TOLERANCE_REL = 0.2


def within_tolerance(path_gain_db: np.ndarray, rms_delay_spread_s: np.ndarray) -> np.ndarray:
    """Whether a link (or cell) traced with fewer and with more samples agrees: ``path_gain_db`` and
    ``rms_delay_spread_s`` [2, ...] (coarser, finer; gain -inf or NaN, spread NaN where there is
    none). True where both traces have a gain, it moves by at most :data:`GAIN_TOLERANCE_DB`, and
    the spread by at most max(:data:`DELAY_SPREAD_TOLERANCE_S`, :data:`DELAY_SPREAD_TOLERANCE_REL` of
    the finer one's) where both hold one. The sampling checks' rule, and the benchmark's
    (``benchmarks.ckm_solver.settled_cells``)."""
    g, ds = np.asarray(path_gain_db), np.asarray(rms_delay_spread_s)
    ds_tol = np.maximum(DELAY_SPREAD_TOLERANCE_S, DELAY_SPREAD_TOLERANCE_REL * np.nan_to_num(ds[1]))
    with np.errstate(invalid="ignore"):
        gain_ok = np.isfinite(g[0]) & np.isfinite(g[1]) & (np.abs(g[1] - g[0]) <= GAIN_TOLERANCE_DB)
        ds_ok = ~(np.isfinite(ds[0]) & np.isfinite(ds[1])) | (np.abs(ds[1] - ds[0]) <= ds_tol)
    return gain_ok & ds_ok


@dataclass
class SamplingConvergence:
    """Path gain and RMS delay spread of links ``[num_tx, num_rx]`` at two sample counts."""

    samples_per_src: int
    check_samples_per_src: int
    rx_position_m: np.ndarray       # [num_rx, 3]
    path_gain_db: np.ndarray        # [2, num_tx, num_rx]: configured, check; -inf where no path
    rms_delay_spread_s: np.ndarray  # [2, num_tx, num_rx]; NaN where no path

    def result(self, what: str) -> CheckResult:
        """A check result: one problem per link that moved beyond the tolerances."""
        g, ds = self.path_gain_db, self.rms_delay_spread_s
        s0, s1 = f"{self.samples_per_src:,}", f"{self.check_samples_per_src:,}"
        problems = []
        agree = within_tolerance(g, ds)
        with np.errstate(invalid="ignore"):
            dg = np.where(np.isfinite(g[0]) & np.isfinite(g[1]), g[1] - g[0], np.nan)
            dds = ds[1] - ds[0]
        for b, r in zip(*np.nonzero(np.isfinite(g[0]) | np.isfinite(g[1]))):
            where = f"tx {b} -> {what} at {np.round(self.rx_position_m[r], 1).tolist()} m"
            if not np.isfinite(g[0, b, r]):
                problems.append(f"{where}: no path at {s0} samples, {g[1, b, r]:.1f} dB at {s1}")
            elif not np.isfinite(g[1, b, r]):
                problems.append(f"{where}: {g[0, b, r]:.1f} dB at {s0} samples, no path at {s1}")
            elif not agree[b, r]:
                problems.append(f"{where}: path gain {g[0, b, r]:.1f} -> {g[1, b, r]:.1f} dB, RMS delay "
                                f"spread {1e9 * ds[0, b, r]:.1f} -> {1e9 * ds[1, b, r]:.1f} ns from {s0} to "
                                f"{s1} samples")
        meta = {"samples_per_src": self.samples_per_src, "check_samples_per_src": self.check_samples_per_src,
                "links_compared": int((np.isfinite(g[0]) | np.isfinite(g[1])).sum()),
                "worst_path_gain_change_db": _worst(dg), "worst_delay_spread_change_ns": _worst(1e9 * dds),
                "gain_tolerance_db": GAIN_TOLERANCE_DB,
                "delay_spread_tolerance": f"max({1e9 * DELAY_SPREAD_TOLERANCE_S:g} ns, "
                                          f"{100 * DELAY_SPREAD_TOLERANCE_REL:g} % of the finer trace's)"}
        ok = (f"{meta['links_compared']} links: path gain and RMS delay spread at {s0} samples per source "
              f"within tolerance of {s1}")
        out = CheckResult.of(problems, ok, meta)
        if problems:
            out.description += (f"; raise ray_tracing.samples_per_src (now {self.samples_per_src:,}) until "
                                f"this check passes: the configured samples miss paths of this scene")
        return out


def _worst(x: np.ndarray) -> float | None:
    """The entry of largest magnitude (signed), None where none is finite."""
    x = np.asarray(x, np.float64).ravel()
    x = x[np.isfinite(x)]
    return None if not len(x) else round(float(x[np.argmax(np.abs(x))]), 3)


def spread_receivers(candidates: np.ndarray, num: int = CHECK_RECEIVERS) -> np.ndarray:
    """Up to ``num`` indices of ``candidates`` (positions ``[N, 3]``), evenly spaced in their order
    (over the session's instants, or a tile's cells row by row): deterministic."""
    n = len(candidates)
    return np.unique(np.linspace(0, n - 1, min(num, n)).round().astype(np.int64)) if n else np.zeros(0, np.int64)


def link_gain_and_spread(paths) -> tuple[np.ndarray, np.ndarray]:
    """Path gain (dB, incoherent, antenna-pair mean) and RMS delay spread (s) of each (transmitter,
    receiver) link of :class:`~simart_pipeline.radio.tracer.TracedPaths`, ``[num_tx, num_rx]``: the
    reference CKM's definitions (:func:`~simart_pipeline.ckm.moments.path_moments`,
    :func:`~simart_pipeline.ckm.moments.layers_from_moments`); NaN where a link has no path."""
    from simart_pipeline.ckm import moments as mom

    def per_link(v):  # [rx, tx, ...] -> [tx, rx, ...]
        return np.swapaxes(np.asarray(v), 0, 1)

    power = per_link(np.mean(np.abs(paths.a.astype(np.complex128)) ** 2, axis=(1, 3)))  # [tx, rx, path]
    valid, tau = per_link(paths.valid), per_link(paths.tau_s)
    first = np.min(np.where(valid, tau, np.inf), axis=-1, initial=np.inf)  # delays relative to the first path's
    angles = per_link(np.stack([paths.phi_r, paths.theta_r, paths.phi_t, paths.theta_t], axis=-1))
    layers = mom.layers_from_moments(mom.path_moments(power, tau, valid, per_link(paths.los), angles,
                                                      np.where(np.isfinite(first), first, 0.0)))
    return layers["path_gain_db"], layers["rms_delay_spread_s"]


def sampling_convergence(radio, tx_position_m: np.ndarray, tx_orientation_rad: np.ndarray,
                         rx_position_m: np.ndarray, deterministic: bool = True,
                         factor: int = CHECK_FACTOR) -> SamplingConvergence:
    """Trace ``rx_position_m [N, 3]`` from the transmitters at the radio scene's
    ``samples_per_src`` and at ``factor`` times it (the solver's other settings and seed
    unchanged; the scene's settings and learned candidate caps are restored afterwards)."""
    cfg = radio.solver_config
    fine = cfg.model_copy(update={"samples_per_src": int(cfg.samples_per_src) * int(factor)})
    # the candidate caps the scene learns per receiver: the finer trace's would outlast it
    learned = dict(radio._candidates_per_rx)
    gains, spreads = [], []
    try:
        for solver in (cfg, fine):
            radio.solver_config = solver
            gain, spread = link_gain_and_spread(radio.trace(
                np.asarray(tx_position_m, np.float64), np.asarray(tx_orientation_rad, np.float64),
                np.asarray(rx_position_m, np.float64), deterministic=deterministic))
            gains.append(np.where(np.isnan(gain), -np.inf, gain))
            spreads.append(spread)
    finally:
        radio.solver_config = cfg
        radio._candidates_per_rx = learned
    return SamplingConvergence(int(cfg.samples_per_src), int(fine.samples_per_src),
                               np.asarray(rx_position_m, np.float64), np.stack(gains), np.stack(spreads))
