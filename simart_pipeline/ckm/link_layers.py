"""Link-level CKM layers per cell: serving base station, SINR with interference, MCS, BLER, rate.

Per cell, independently of every other cell (no link-adaptation state carries over), with the
link budget of the ``kpis`` stage (:mod:`simart_pipeline.link.budget`, docs/link-level.md):

- each base station splits its transmit power over the allocated subcarriers; noise per resource
  element is thermal over one subcarrier spacing with the receiver's noise figure;
- each base station's best beam maximises its incoherent beam gain at the cell (which also
  maximises the SINR, since the interference does not depend on the serving station's beam); the
  serving station is, among those that reach the cell, the one whose best beam gives the highest
  SINR (ties: lowest index), the ``kpis`` stage's rule (:func:`.budget.serving_station`);
- interference: every other station transmits on the same resource elements with a beam drawn
  uniformly from its codebook; the layer uses the expected power (mean over its beams);
- the map's gains are incoherent (wideband), so the SINR is flat over the subcarriers and the EESM
  effective SINR of a flat SINR equals it; MCS: the inner loop for the BLER target (no outer loop:
  a map has no transmission history); rate = TBS x (1 - TBLER) / slot; Shannon rate = B log2(1 + SINR).
- masked cells (not traced: inside a building, outside the region) have NaN rates; a traced cell
  that no station reaches is not served: rates 0, SINRs/BLER NaN, ``best_bs``/MCS/TBS -1.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from simart_pipeline.config import SceneConfig
from simart_pipeline.link.budget import (allocation, inner_loop, power_db, power_per_re_w, rates,
                                         serving_station, sinr_per_re, station_sinr,
                                         SERVING_RULE)

MASKED = "cell masked: inside a building or outside the region (not traced)"
NOT_SERVED = ("no base station reaches the cell (not served; fast mode: with ckm.min_hits_for_power ray "
              "hits), or the cell is masked")
RATE_NAN = MASKED + "; the rate is 0 where no base station reaches a traced cell (not served)"


def link_layers(cfg: SceneConfig, beam_power: np.ndarray, has_path: np.ndarray, traced: np.ndarray) -> xr.Dataset:
    """``beam_power [B, H, y, x, K]`` incoherent beam gains, ``has_path [B, H, y, x]``,
    ``traced [H, y, x]`` -> layers over (height, y, x)."""
    ofdm, link = cfg.ofdm, cfg.link
    alloc = allocation(ofdm, link, cfg.receiver)
    p_re = power_per_re_w([b.power_dbm for b in cfg.base_stations], alloc.num_subcarriers)[:, None, None, None]
    noise_w = alloc.noise_w
    best_gain = beam_power.max(axis=-1) if beam_power.shape[-1] else np.zeros(beam_power.shape[:-1])
    signal_per_bs = np.where(has_path, p_re * best_gain, 0.0)                  # [B, H, y, x]
    mean_interf = np.where(has_path, p_re * beam_power.mean(axis=-1), 0.0)     # [B, H, y, x]
    sinr_per_bs = station_sinr(signal_per_bs, mean_interf, noise_w, axis=0)
    served, serving = serving_station(sinr_per_bs, has_path & traced[None], axis=0)
    best_bs = np.where(served, serving, -1).astype(np.int32)
    idx = serving[None]
    signal = np.take_along_axis(signal_per_bs, idx, axis=0)[0]
    sinr_re = np.where(served, np.take_along_axis(sinr_per_bs, idx, axis=0)[0], 0.0)[..., None]  # flat: K = 1
    sinr = np.where(served, sinr_re[..., 0], np.nan)
    snr = np.where(served, sinr_per_re(signal, 0.0, noise_w), np.nan)
    phy = alloc.phy
    mcs, eff, bler, tbler = inner_loop(phy, sinr_re, served, link.bler_target)
    rate = rates(phy, mcs, tbler, sinr_re, served, ~traced, alloc.slot_s, alloc.bandwidth_hz)

    d3 = ("height", "y", "x")
    nan = dict(nan_means=NOT_SERVED)
    rate_nan = dict(nan_means=RATE_NAN)
    return xr.Dataset({
        "best_bs": (d3, best_bs, dict(units="1", long_name="index (on bs) of the serving base station: "
                                      f"{SERVING_RULE}; -1 where not served or masked")),
        "served": (d3, served, dict(long_name="the cell is traced and some base station reaches it")),
        "sinr_db": (d3, power_db(sinr).astype(np.float32), dict(
            units="dB", long_name="SINR per resource element with interference: serving station's best "
            "beam over the expected interference of the others (mean over their beams) plus noise", **nan)),
        "snr_db": (d3, power_db(snr).astype(np.float32), dict(units="dB", long_name="SNR per resource "
                                                               "element (interference off)", **nan)),
        "effective_sinr_db": (d3, power_db(eff).astype(np.float32), dict(
            units="dB", long_name="EESM effective SINR at the selected MCS (flat over the subcarriers "
            "in a map, so equal to the SINR)", **nan)),
        "mcs_index": (d3, mcs.astype(np.int16), dict(
            units="1", long_name=f"MCS of TS 38.214 table {link.mcs_table} chosen by the inner loop for "
            f"transport BLER <= {link.bler_target}; -1 where not served or masked")),
        "tbs_bits": (d3, rate["tbs_bits"].astype(np.int32), dict(
            units="bit", long_name="transport block size of the selected MCS (TS 38.214 5.1.3.2); -1 "
            "where not served or masked")),
        "bler": (d3, bler.astype(np.float32), dict(units="1", long_name="code-block error rate at the "
                                                    "selected MCS", **nan)),
        "tbler": (d3, tbler.astype(np.float32), dict(units="1", long_name="transport block error rate "
                                                      "at the selected MCS", **nan)),
        "rate_bps": (d3, rate["mcs_rate_bps"].astype(np.float32), dict(
            units="bit s-1", long_name="achievable rate from the MCS: TBS x (1 - TBLER) / slot; 0 where "
            "not served", **rate_nan)),
        "shannon_rate_bps": (d3, rate["shannon_rate_bps"].astype(np.float32), dict(
            units="bit s-1", long_name="Shannon rate: allocated bandwidth x log2(1 + SINR); 0 where not "
            "served", **rate_nan)),
    })
