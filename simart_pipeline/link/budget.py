"""The link budget, written once: used by the ``kpis`` stage (:func:`.kpis.compute_kpis`, per
radio-clock instant and subcarrier) and by the channel-knowledge map's link layers
(:func:`simart_pipeline.ckm.link_layers.link_layers`, per cell, wideband). Plain numpy, float64.

The chain, for one receiver (a platform at one instant, or a map cell):

1. powers: ``dBm -> W`` (:func:`dbm_to_w`), ``W -> dBm`` (:func:`w_to_dbm`), dB of a linear power
   ratio (:func:`power_db`: NaN where the value is not positive, never -inf); each base station
   splits its transmit power evenly over the ``K`` allocated subcarriers (:func:`power_per_re_w`);
2. SINR per resource element ``S / (I + N)`` (:func:`sinr_per_re`); for a single-antenna receiver
   with the expected-interference rule (every other station transmits a beam drawn uniformly from
   its codebook: its mean beam power), :func:`station_sinr` gives each station's SINR if it served;
3. serving station (:func:`serving_station`): among the candidate stations (those that reach the
   receiver), the one whose best beam gives the highest wideband SINR; ties: the lowest index;
4. inner-loop link adaptation (:func:`inner_loop`): per-RE SINR -> EESM effective SINR for every
   MCS -> BLER / TBLER -> the highest MCS whose TBLER meets the target
   (:func:`.link_adaptation.select_mcs_inner_loop`); the outer loop stays in the ``kpis`` stage (a
   map has no transmission history);
5. rates (:func:`rates`): TBS of the MCS, ``MCS rate = TBS (1 - TBLER) / slot``, Shannon spectral
   efficiency ``mean_k log2(1 + SINR[k])`` and rate (times the allocated bandwidth).

**Masked, not served, served** (one meaning for both stages):

- *masked*: the receiver has no meaningful position for a link budget (inside a building, within
  1 cm of a transmitter, outside the CKM region, not traced): every value is NaN (integers -1),
  the rates included;
- *not served*: the receiver is valid but no base station reaches it: it gets no throughput, so
  its rates (MCS and Shannon) are **0 bit/s** (area means of a rate map stay right); SINR,
  effective SINR, BLER, TBLER are NaN; MCS index and TBS are -1;
- *served*: otherwise; every value is defined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simart_pipeline.link.link_adaptation import select_mcs_inner_loop
from simart_pipeline.link.ofdm import (allocated_resource_blocks, allocated_subcarriers,
                                       slot_duration_s, thermal_noise_power_w)
from simart_pipeline.link.phy_abstraction import PhyAbstraction
from simart_pipeline.link.tbs import num_re_for_tbs

CATEGORY = "pdsch"   # the links are downlink: base station -> platform (or map cell)

SERVING_RULE = ("per receiver, the candidate base station whose best beam has the highest "
                "wideband SINR (ties: lowest index)")
NOT_SERVED_RULE = ("masked receivers (inside a building, within 1 cm of a transmitter, outside "
                   "the map region, not traced) have NaN rates; a valid receiver that no base "
                   "station reaches is not served: rates 0, SINR/effective SINR/BLER/TBLER NaN, "
                   "MCS and TBS -1")


def power_db(x) -> np.ndarray:
    """``10 log10(x)`` where ``x > 0``, NaN elsewhere (never -inf); float64."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(x > 0, 10.0 * np.log10(np.where(x > 0, x, 1.0)), np.nan)


def dbm_to_w(power_dbm) -> np.ndarray:
    """Power in dBm to W (float64, broadcasts)."""
    return 10.0 ** ((np.asarray(power_dbm, dtype=np.float64) - 30.0) / 10.0)


def w_to_dbm(power_w) -> np.ndarray:
    """Power in W to dBm, NaN where not positive (:func:`power_db` of mW)."""
    return power_db(np.asarray(power_w, dtype=np.float64) * 1e3)


def power_per_re_w(tx_power_dbm, num_subcarriers: int) -> np.ndarray:
    """Transmit power per resource element: ``P_tx`` split evenly over the allocated subcarriers."""
    return dbm_to_w(tx_power_dbm) / num_subcarriers


def sinr_per_re(signal_w, interference_w, noise_w) -> np.ndarray:
    """``S / (I + N)`` per resource element (linear, broadcasts)."""
    return signal_w / (interference_w + noise_w)


def station_sinr(signal_w, mean_interference_w, noise_w, axis: int = 0) -> np.ndarray:
    """SINR of each station (along ``axis``) if it served, single receive antenna: its signal over
    the expected interference of all the others (``mean_interference_w``: each station's power
    with a beam drawn uniformly from its codebook, 0 where it does not reach) plus noise."""
    # the others' sum as (sum before) + (sum after): sums of non-negative terms, never total - own,
    # which cancels to rounding noise (and depends on the stations' order) when one station dominates
    m = np.moveaxis(np.asarray(mean_interference_w, dtype=np.float64), axis, 0)
    before = np.concatenate([np.zeros_like(m[:1]), np.cumsum(m, axis=0)[:-1]])
    after = np.concatenate([np.cumsum(m[::-1], axis=0)[:-1][::-1], np.zeros_like(m[:1])])
    return sinr_per_re(signal_w, np.moveaxis(before + after, 0, axis), noise_w)


def serving_station(best_sinr, candidate, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """The serving station along ``axis``: the candidate with the highest best-beam wideband SINR
    (ties: lowest index). Returns ``(served, serving)``, ``axis`` removed; ``serving`` is 0 where
    not served (callers mask it)."""
    candidate = np.asarray(candidate, dtype=bool)
    served = candidate.any(axis=axis)
    serving = np.where(candidate, best_sinr, -1.0).argmax(axis=axis)   # SINR >= 0 > -1
    return served, serving


@dataclass(frozen=True)
class Allocation:
    """The resource allocation and receiver of a scene: what every link budget needs."""

    first_rb: int
    num_rb: int
    subcarriers: np.ndarray       # allocated subcarrier indices on the carrier
    num_subcarriers: int          # K
    bandwidth_hz: float           # K df
    slot_s: float
    noise_w: float                # thermal noise per resource element
    num_re: int                   # N_RE for the TBS
    phy: PhyAbstraction


def allocation(ofdm, link, receiver) -> Allocation:
    """:class:`Allocation` of the config sections ``ofdm``, ``link`` and ``receiver``."""
    first_rb, num_rb = allocated_resource_blocks(ofdm, link)
    sc = allocated_subcarriers(ofdm, link)
    n_re = int(num_re_for_tbs(num_rb, ofdm.num_ofdm_symbols, link.dmrs_re_per_prb,
                              link.overhead_re_per_prb))
    return Allocation(
        first_rb=first_rb, num_rb=num_rb, subcarriers=sc, num_subcarriers=sc.size,
        bandwidth_hz=sc.size * ofdm.subcarrier_spacing_hz, slot_s=slot_duration_s(ofdm),
        noise_w=float(thermal_noise_power_w(ofdm.subcarrier_spacing_hz, receiver.temperature_k,
                                            receiver.noise_figure_db)),
        num_re=n_re, phy=PhyAbstraction(n_re, link.mcs_table, CATEGORY))


def inner_loop(phy: PhyAbstraction, sinr, served, bler_target: float):
    """Inner-loop MCS of the per-RE SINRs ``sinr [..., K]`` where ``served [...]``.

    Returns ``(mcs, effective_sinr, bler, tbler)`` ``[...]``: -1 / NaN where not served."""
    m, e, b, tb = select_mcs_inner_loop(phy, sinr, bler_target)
    return (np.where(served, m, -1),) + tuple(np.where(served, v, np.nan) for v in (e, b, tb))


def rates(phy: PhyAbstraction, mcs, tbler, sinr, served, masked, slot_s: float,
          bandwidth_hz: float) -> dict[str, np.ndarray]:
    """TBS and rates of the selected MCS and Shannon rates, ``[...]`` from ``mcs``/``tbler [...]``
    and the per-RE ``sinr [..., K]``.

    - ``tbs_bits``: TBS of the MCS, -1 where not served;
    - ``mcs_rate_bps``: ``TBS (1 - TBLER) / slot``;
    - ``shannon_spectral_efficiency_bpshz``: ``mean_k log2(1 + SINR[k])``;
    - ``shannon_rate_bps``: that times the allocated bandwidth.

    Rates are 0 where not served and NaN where ``masked``.
    """
    tbs_bits = np.where(served, phy.transport_block.tbs_bits[np.maximum(mcs, 0)], -1)
    mcs_rate = np.where(served, tbs_bits * (1.0 - np.nan_to_num(tbler)) / slot_s, 0.0)
    with np.errstate(invalid="ignore"):
        shannon_se = np.where(served, np.mean(np.log1p(sinr), axis=-1) / np.log(2.0), 0.0)
    mcs_rate = np.where(masked, np.nan, mcs_rate)
    shannon_se = np.where(masked, np.nan, shannon_se)
    return dict(tbs_bits=tbs_bits, mcs_rate_bps=mcs_rate,
                shannon_spectral_efficiency_bpshz=shannon_se,
                shannon_rate_bps=shannon_se * bandwidth_hz)
