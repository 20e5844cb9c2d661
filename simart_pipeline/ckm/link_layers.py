"""Link-level CKM layers per cell: serving base station, SINR with interference, MCS, BLER, rate.

Per cell, independently of every other cell (no link-adaptation state carries over), with the
same models as the ``kpis`` stage (docs/link-level.md):

- each base station splits its transmit power over the allocated subcarriers; noise per resource
  element is thermal over one subcarrier spacing with the receiver's noise figure;
- each base station's best beam maximises its incoherent beam gain at the cell (which also
  maximises the SINR, since the interference does not depend on the serving station's beam); the
  serving station has the highest best-beam received power;
- interference: every other station transmits on the same resource elements with a beam drawn
  uniformly from its codebook; the layer uses the expected power (mean over its beams);
- the map's gains are incoherent (wideband), so the SINR is flat over the subcarriers and the EESM
  effective SINR of a flat SINR equals it; MCS: the inner loop for the BLER target (no outer loop:
  a map has no transmission history); rate = TBS x (1 - TBLER) / slot; Shannon rate = B log2(1 + SINR).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from simart_pipeline.config import SceneConfig
from simart_pipeline.link.link_adaptation import select_mcs_inner_loop
from simart_pipeline.link.ofdm import allocated_resource_blocks, allocated_subcarriers, slot_duration_s, \
    thermal_noise_power_w
from simart_pipeline.link.phy_abstraction import PhyAbstraction
from simart_pipeline.link.tbs import num_re_for_tbs

NOT_SERVED = "no base station reaches the cell, or the cell is masked"


def _db(x):
    x = np.asarray(x, np.float64)
    return np.where(x > 0, 10 * np.log10(np.where(x > 0, x, 1.0)), np.nan)


def link_layers(cfg: SceneConfig, beam_power: np.ndarray, has_path: np.ndarray, traced: np.ndarray) -> xr.Dataset:
    """``beam_power [B, H, y, x, K]`` incoherent beam gains, ``has_path [B, H, y, x]``,
    ``traced [H, y, x]`` -> layers over (height, y, x)."""
    ofdm, link, rx = cfg.ofdm, cfg.link, cfg.receiver
    _, num_rb = allocated_resource_blocks(ofdm, link)
    n_sc = allocated_subcarriers(ofdm, link).size
    p_re_w = 10 ** ((np.array([b.power_dbm for b in cfg.base_stations], np.float64) - 30) / 10) / n_sc
    noise_w = float(thermal_noise_power_w(ofdm.subcarrier_spacing_hz, rx.temperature_k, rx.noise_figure_db))
    p_re = p_re_w[:, None, None, None]
    best_gain = beam_power.max(axis=-1) if beam_power.shape[-1] else np.zeros(beam_power.shape[:-1])
    signal_per_bs = np.where(has_path, p_re * best_gain, 0.0)                  # [B, H, y, x]
    mean_interf = np.where(has_path, p_re * beam_power.mean(axis=-1), 0.0)     # [B, H, y, x]
    served = traced & (signal_per_bs > 0).any(axis=0)
    best_bs = np.where(served, np.argmax(signal_per_bs, axis=0), -1).astype(np.int32)
    idx = np.maximum(best_bs, 0)[None]
    signal = np.take_along_axis(signal_per_bs, idx, axis=0)[0]
    interference = mean_interf.sum(axis=0) - np.take_along_axis(mean_interf, idx, axis=0)[0]
    sinr = np.where(served, signal / (interference + noise_w), np.nan)
    snr = np.where(served, signal / noise_w, np.nan)

    n_re = int(num_re_for_tbs(num_rb, ofdm.num_ofdm_symbols, link.dmrs_re_per_prb, link.overhead_re_per_prb))
    phy = PhyAbstraction(n_re, link.mcs_table)
    mcs = np.full(sinr.shape, -1, np.int64)
    eff, bler, tbler = (np.full(sinr.shape, np.nan) for _ in range(3))
    if served.any():
        m, e, b, tb = select_mcs_inner_loop(phy, sinr[served][:, None], link.bler_target)
        mcs[served], eff[served], bler[served], tbler[served] = m, e, b, tb
    tbs_bits = np.where(served, phy.transport_block.tbs_bits[np.maximum(mcs, 0)], 0)
    rate = np.where(served, tbs_bits * (1 - np.nan_to_num(tbler)) / slot_duration_s(ofdm), np.nan)
    band_hz = n_sc * ofdm.subcarrier_spacing_hz
    shannon = np.where(served, band_hz * np.log2(1 + np.where(served, sinr, 0.0)), np.nan)
    d3 = ("height", "y", "x")
    nan = dict(nan_means=NOT_SERVED)
    return xr.Dataset({
        "best_bs": (d3, best_bs, dict(units="1", long_name="index (on bs) of the serving base station: "
                                      "highest best-beam received power; -1 where none")),
        "served": (d3, served, dict(long_name="some base station reaches the cell")),
        "sinr_db": (d3, _db(sinr).astype(np.float32), dict(
            units="dB", long_name="SINR per resource element with interference: serving station's best "
            "beam over the expected interference of the others (mean over their beams) plus noise", **nan)),
        "snr_db": (d3, _db(snr).astype(np.float32), dict(units="dB", long_name="SNR per resource element "
                                                          "(interference off)", **nan)),
        "effective_sinr_db": (d3, _db(eff).astype(np.float32), dict(
            units="dB", long_name="EESM effective SINR at the selected MCS (flat over the subcarriers "
            "in a map, so equal to the SINR)", **nan)),
        "mcs_index": (d3, mcs.astype(np.int16), dict(
            units="1", long_name=f"MCS of TS 38.214 table {link.mcs_table} chosen by the inner loop for "
            f"transport BLER <= {link.bler_target}; -1 where not served")),
        "bler": (d3, bler.astype(np.float32), dict(units="1", long_name="code-block error rate at the "
                                                    "selected MCS", **nan)),
        "tbler": (d3, tbler.astype(np.float32), dict(units="1", long_name="transport block error rate "
                                                      "at the selected MCS", **nan)),
        "rate_bps": (d3, rate.astype(np.float32), dict(
            units="bit s-1", long_name="achievable rate from the MCS: TBS x (1 - TBLER) / slot", **nan)),
        "shannon_rate_bps": (d3, shannon.astype(np.float32), dict(
            units="bit s-1", long_name="Shannon rate: allocated bandwidth x log2(1 + SINR)", **nan)),
    })
