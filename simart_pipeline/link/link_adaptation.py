"""MCS selection for a transport-BLER target: inner loop (ILLA) and outer loop (OLLA).

- **Inner loop**: the highest MCS whose TBLER at the effective SINR (EESM with that MCS's beta)
  does not exceed the target; if none does, the lowest MCS that has a BLER curve.
- **Outer loop** (Pedersen et al., "Frequency domain scheduling for OFDMA with limited and noisy
  channel feedback", VTC 2007-Fall; step ratio of Sampath et al., PIMRC 1997): the inner loop
  applied to the last reported effective SINR minus an offset (dB) that grows by ``delta_up`` on
  every NACK and shrinks by ``delta_down = delta_up * target / (1 - target)`` on every ACK, so
  that the long-run NACK rate converges to the target; the offset is clipped to its limits.
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.link.phy_abstraction import PhyAbstraction


def inner_loop_mcs(tbler_per_mcs, available, bler_target: float) -> np.ndarray:
    """Highest MCS with ``TBLER <= bler_target``, else the lowest available one.

    ``tbler_per_mcs``: ``[..., M]`` (NaN: no curve); ``available``: ``[M]`` bool.
    Returns ``[...]`` int64.
    """
    tbler = np.asarray(tbler_per_mcs, dtype=np.float64)
    available = np.asarray(available, dtype=bool)
    if not available.any():
        raise ValueError("no MCS has a BLER curve")
    ok = (tbler <= bler_target) & available          # NaN compares False
    M = tbler.shape[-1]
    highest = M - 1 - np.argmax(ok[..., ::-1], axis=-1)
    return np.where(ok.any(axis=-1), highest, int(np.argmax(available))).astype(np.int64)


def select_mcs_inner_loop(phy: PhyAbstraction, sinr, bler_target: float, axis=-1):
    """Inner-loop MCS of per-resource-element SINRs ``sinr`` (linear, REs along ``axis``).

    Returns ``(mcs [...], sinr_eff [...], bler [...], tbler [...])`` at the chosen MCS.
    """
    eff_all = phy.effective_sinr_all_mcs(sinr, axis=axis)             # [..., M]
    m = np.arange(phy.num_mcs)
    _, tbler_all = phy.bler(eff_all, m)
    mcs = inner_loop_mcs(tbler_all, phy.available, bler_target)
    eff = np.take_along_axis(eff_all, mcs[..., None], axis=-1)[..., 0]
    bler, tbler = phy.bler(eff, mcs)
    return mcs, eff, bler, tbler


def select_mcs_outer_loop(phy: PhyAbstraction, sinr, uniform, bler_target: float,
                          delta_up_db: float = 1.0, offset_limits_db=(-20.0, 20.0),
                          scheduled=None):
    """Outer-loop link adaptation over consecutive transmissions.

    - ``sinr``: ``[T, R, K]`` linear SINR per resource element of ``R`` receivers over ``T``
      consecutive transmissions;
    - ``uniform``: ``[T, R]`` uniform draws in [0, 1): the transport block of transmission ``t``
      is acknowledged (ACK) when ``uniform >= TBLER``;
    - ``scheduled``: ``[T, R]`` bool (default all): unscheduled entries transmit nothing and leave
      the loop's state as it is.

    At the first transmission of a receiver (no feedback yet) the inner loop on the current SINR
    picks the MCS. Afterwards, MCS(t) = inner loop on ``SINR_eff,dB(t-1) - offset(t)`` (the
    report of the last transmission, one transmission old), where ``SINR_eff(t-1)`` used the
    beta of the MCS of ``t-1``.
    Returns ``(mcs, sinr_eff, bler, tbler, ack, offset_db)``, each ``[T, R]`` (offset: the one
    applied at ``t``); where not scheduled: mcs -1, floats NaN, ack False.
    """
    sinr = np.asarray(sinr, dtype=np.float64)
    T, R, _ = sinr.shape
    scheduled = np.ones((T, R), bool) if scheduled is None else np.asarray(scheduled, bool)
    delta_down = delta_up_db * bler_target / (1.0 - bler_target)
    lo, hi = offset_limits_db
    m_all = np.arange(phy.num_mcs)
    offset = np.zeros(R)
    last_eff_db = np.full(R, np.nan)
    last_ack = np.full(R, -1)                          # -1: no feedback pending
    out_mcs = np.full((T, R), -1, np.int64)
    out_eff, out_bler, out_tbler, out_off = (np.full((T, R), np.nan) for _ in range(4))
    out_ack = np.zeros((T, R), bool)
    for t in range(T):
        s = scheduled[t]
        # feedback of a receiver's last transmission updates its offset at its next one
        step = np.where(last_ack == 0, delta_up_db, np.where(last_ack == 1, -delta_down, 0.0))
        offset = np.where(s, np.clip(offset + step, lo, hi), offset)
        last_ack = np.where(s, -1, last_ack)
        fresh = np.isnan(last_eff_db)
        _, tb_olla = phy.bler(10.0 ** ((last_eff_db - offset) / 10.0)[:, None], m_all[None])
        mcs = inner_loop_mcs(tb_olla, phy.available, bler_target)
        if np.any(fresh & s):
            mcs_inner, *_ = select_mcs_inner_loop(phy, sinr[t], bler_target)
            mcs = np.where(fresh, mcs_inner, mcs)
        eff = phy.effective_sinr(sinr[t], mcs)
        bler, tbler = phy.bler(eff, mcs)
        ack = uniform[t] >= tbler
        out_mcs[t] = np.where(s, mcs, -1)
        out_eff[t], out_bler[t], out_tbler[t] = (np.where(s, v, np.nan) for v in (eff, bler, tbler))
        out_ack[t] = s & ack
        out_off[t] = np.where(s, offset, np.nan)
        last_ack = np.where(s, ack.astype(int), last_ack)
        with np.errstate(divide="ignore"):
            last_eff_db = np.where(s & (eff > 0), 10.0 * np.log10(eff), last_eff_db)
    return out_mcs, out_eff, out_bler, out_tbler, out_ack, out_off
