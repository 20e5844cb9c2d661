"""Link-level KPIs from the channel impulse responses (``cirs`` store, docs/data-contract.md).

Model, per radio-clock instant:

- OFDM: one symbol of ``num_subcarriers`` resource elements; each base station splits its power
  ``tx_power_dbm`` evenly over them. Noise per resource element: thermal noise over one
  subcarrier spacing with the receiver's noise figure.
- Beams: each base station precodes with one beam of its DFT codebook (:mod:`.beams`); a link's
  best beam maximises the wideband beam gain (mean over subcarriers); the receiver combines its
  antennas by maximum-ratio combining (MRC) per subcarrier.
- Serving: each receiver is served by the base station whose best-beam received power is highest.
- Interference: every other base station transmits on the same resource elements with a beam drawn
  uniformly from its codebook; the stored SINR uses the expected interference power after the
  receiver's MRC combiner (the mean over that station's beams).
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.constants import speed_of_light

from simart_pipeline.config import SceneConfig
from simart_pipeline.link.beams import beamformed_channel, dft_codebook
from simart_pipeline.link.ofdm import (channel_frequency_response, subcarrier_offsets_hz,
                                       thermal_noise_power_w)

DEFAULT_MAX_CHUNK_BYTES = 256 * 2**20  # working set of one time chunk
NAN_LINK = "no valid path on this link (link_has_path false), or a linear value of exactly 0"
NAN_RX = ("receiver not served (rx_served false: no valid path to any base station), "
          "or a zero signal")

INTERFERENCE_RULE = (
    "every non-serving base station transmits on the same resource elements with a beam drawn "
    "uniformly from its DFT codebook; stored SINR uses the expected interference power after the "
    "receiver's MRC combiner (mean over that station's beams), per subcarrier")
NOISE_MODEL = ("thermal noise k_B T B 10^(NF/10) over one subcarrier spacing per resource element, "
               "at the receiver temperature and noise figure; receive combining by MRC")
POWER_ALLOCATION = "transmit power split evenly over all subcarriers of one OFDM symbol"


def dbm_to_w(power_dbm) -> np.ndarray:
    """Power in dBm to W (float64, broadcasts)."""
    return 10.0 ** ((np.asarray(power_dbm, dtype=np.float64) - 30.0) / 10.0)


def _db(x) -> np.ndarray:
    """10 log10(x) where x > 0, NaN elsewhere (never -inf)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x > 0, 10.0 * np.log10(np.where(x > 0, x, 1.0)), np.nan)


def _kpis_chunk(a, tau_s, valid, fc_hz, offsets_hz, weights, p_re_w, on_rx, rx_of_link):
    """KPIs of one time chunk, all linear.

    ``a [T, L, r, n, P]``, ``tau_s``/``valid [T, L, P]``, ``weights [B, n]``, ``p_re_w [L]``
    (W per resource element), ``on_rx [R, L]`` (link ends at receiver), ``rx_of_link [L]``.
    """
    L = valid.shape[1]
    H = channel_frequency_response(a, tau_s, valid, fc_hz, offsets_hz)   # [T, L, r, n, K]
    Y = beamformed_channel(H, weights)                                   # [T, L, r, B, K]
    gain = np.sum(Y.real**2 + Y.imag**2, axis=2).mean(axis=-1)          # [T, L, B]
    has_path = valid.any(axis=-1)                                        # [T, L]
    best = gain.argmax(axis=-1)                                          # [T, L]
    best_gain = np.take_along_axis(gain, best[..., None], axis=-1)[..., 0]
    rx_power_w = p_re_w * best_gain                                      # [T, L] per RE

    # Serving link per receiver: highest best-beam power among its links that have a path.
    candidate = has_path[:, None, :] & on_rx[None]                       # [T, R, L]
    served = candidate.any(axis=-1)                                      # [T, R]
    serving = np.where(candidate, rx_power_w[:, None, :], -1.0).argmax(axis=-1)  # [T, R]
    serving_beam = np.take_along_axis(best, serving, axis=1)             # [T, R]

    # Effective channel of each link's best beam, then of each receiver's serving link.
    y_best = np.take_along_axis(Y, best[:, :, None, None, None], axis=3)[:, :, :, 0, :]  # [T,L,r,K]
    y_serv = np.take_along_axis(y_best, serving[:, :, None, None], axis=1)          # [T,R,r,K]
    signal_gain = np.sum(y_serv.real**2 + y_serv.imag**2, axis=2) * served[..., None]  # [T,R,K]
    signal_w = p_re_w[serving][..., None] * signal_gain                  # [T, R, K]

    # MRC combiner v = h / |h| per subcarrier; interference after it, averaged over beams.
    norm = np.sqrt(signal_gain)
    v = np.where(norm[:, :, None, :] > 0, y_serv / np.where(norm > 0, norm, 1.0)[:, :, None, :], 0)
    v_link = v[:, rx_of_link]                                            # [T, L, r, K]
    combined = np.sum(v_link.conj()[:, :, :, None, :] * H, axis=2)       # [T, L, n, K]
    z = weights @ combined                                               # [T, L, B, K]
    interf_gain = np.mean(z.real**2 + z.imag**2, axis=2)                 # [T, L, K]
    interferer = candidate & (np.arange(L)[None, None, :] != serving[..., None])  # [T, R, L]
    interference_w = np.einsum("trl,tlk->trk", interferer * p_re_w, interf_gain)    # [T, R, K]
    return dict(gain=gain, has_path=has_path, best=best, best_gain=best_gain,
                rx_power_w=rx_power_w, served=served, serving=serving,
                serving_beam=serving_beam, signal_w=signal_w, interference_w=interference_w)


def _chunk_steps(sizes: dict, num_beams: int, num_subcarriers: int, max_bytes: int) -> int:
    """Time steps per chunk so that the complex128 working set stays under ``max_bytes``."""
    L, r, n, P, K, B = (sizes["link"], sizes["rx_ant"], sizes["tx_ant"], sizes["path"],
                        num_subcarriers, num_beams)
    # a, phase, H (+ temporaries), Y, combined product, z: 16 bytes per complex value.
    per_step = 16 * L * (r * n * P + P * K + 3 * r * n * K + 2 * r * B * K + n * K + B * K)
    return max(1, int(max_bytes // per_step))


def _var(dims, data, units, long_name, **attrs):
    return xr.Variable(dims, data, dict(units=units, long_name=long_name, **attrs))


def compute_kpis(cirs: xr.Dataset, cfg: SceneConfig,
                 max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES) -> xr.Dataset:
    """Per-(time, link) beam KPIs and per-(time, platform) SINR, SNR and Shannon rate.

    ``cirs``: the ``cirs`` dataset (docs/data-contract.md; read lazily, chunk by chunk over
    ``time``); ``cfg``: the scene config (OFDM numerology, receiver noise, codebook, arrays).
    The receivers of the links are the platforms: per-receiver results are on dim ``platform``.
    """
    ofdm = cfg.ofdm
    fc_hz = float(ofdm.carrier_frequency_hz)
    if "carrier_frequency_hz" in cirs.attrs and not np.isclose(
            float(cirs.attrs["carrier_frequency_hz"]), fc_hz, rtol=1e-9):
        raise ValueError(f"cirs carrier {cirs.attrs['carrier_frequency_hz']} Hz differs from the "
                         f"config's {fc_hz} Hz")
    offsets_hz = subcarrier_offsets_hz(ofdm)
    K = offsets_hz.size
    array = cfg.base_stations[0].array  # one transmit array per scene (config validator)
    weights, directions = dft_codebook(cirs["tx_ant_position_m"].values, speed_of_light / fc_hz,
                                       array.rows, array.cols, cfg.codebook.oversampling)
    B = weights.shape[0]

    tx_of_link = np.asarray(cirs["tx"].values).astype(str)
    rx_link_names = np.asarray(cirs["rx"].values).astype(str)
    platforms = list(dict.fromkeys(rx_link_names))
    rx_of_link = np.array([platforms.index(r) for r in rx_link_names], dtype=np.int64)
    on_rx = rx_of_link[None, :] == np.arange(len(platforms))[:, None]   # [R, L]
    p_re_w = dbm_to_w(cirs["tx_power_dbm"].transpose("link").values) / K  # [L], W per RE
    noise_w = float(thermal_noise_power_w(ofdm.subcarrier_spacing_hz, cfg.receiver.temperature_k,
                                          cfg.receiver.noise_figure_db))

    T, L, R = cirs.sizes["time"], cirs.sizes["link"], len(platforms)
    out = dict(gain=np.zeros((T, L, B)), has_path=np.zeros((T, L), bool),
               best=np.zeros((T, L), np.int64), best_gain=np.zeros((T, L)),
               rx_power_w=np.zeros((T, L)), served=np.zeros((T, R), bool),
               serving=np.zeros((T, R), np.int64), serving_beam=np.zeros((T, R), np.int64),
               signal_w=np.zeros((T, R, K)), interference_w=np.zeros((T, R, K)))
    step = _chunk_steps(cirs.sizes, B, K, max_chunk_bytes)
    for t0 in range(0, T, step):
        part = cirs.isel(time=slice(t0, t0 + step))
        res = _kpis_chunk(part["a"].transpose("time", "link", "rx_ant", "tx_ant", "path").values,
                          part["tau_s"].transpose("time", "link", "path").values,
                          part["valid"].transpose("time", "link", "path").values.astype(bool),
                          fc_hz, offsets_hz, weights, p_re_w, on_rx, rx_of_link)
        for key, value in res.items():
            out[key][t0:t0 + step] = value

    has_path, served = out["has_path"], out["served"]
    signal_w, total_w = out["signal_w"], out["interference_w"] + noise_w
    sinr = signal_w / total_w                                            # [T, R, K]
    sinr_wb = signal_w.sum(-1) / total_w.sum(-1)
    snr = signal_w.sum(-1) / (K * noise_w)
    spectral_eff = np.mean(np.log1p(sinr), axis=-1) / np.log(2.0)        # 0 where not served
    rate = spectral_eff * ofdm.bandwidth_hz
    serving_tx = np.where(served, tx_of_link[out["serving"]], "")

    link_mask = has_path[..., None]
    TL, TR = ("time", "link"), ("time", "platform")
    data = dict(
        link_has_path=_var(TL, has_path, "1", "link has at least one valid path"),
        beam_gain_db=_var(TL + ("beam",), np.where(link_mask, _db(out["gain"]), np.nan), "dB",
                          "wideband beam gain (mean over subcarriers, MRC over rx antennas)",
                          nan_means=NAN_LINK),
        best_beam=_var(TL, out["best"], "1", "beam with the largest wideband gain",
                       valid_where="link_has_path"),
        best_beam_gain_db=_var(TL, np.where(has_path, _db(out["best_gain"]), np.nan), "dB",
                               "wideband gain of the best beam", nan_means=NAN_LINK),
        rx_power_per_re_dbm=_var(TL, np.where(has_path, _db(out["rx_power_w"] * 1e3), np.nan),
                                 "dBm", "received power per resource element with the best beam",
                                 nan_means=NAN_LINK),
        rx_served=_var(TR, served, "1", "receiver has a valid path to at least one base station"),
        serving_link=_var(TR, out["serving"], "1", "index on dim link of the serving link",
                          valid_where="rx_served"),
        serving_tx=xr.Variable(TR, serving_tx.astype(str), dict(
            long_name="serving base station (empty where rx_served is false)")),
        serving_beam=_var(TR, out["serving_beam"], "1", "beam of the serving base station",
                          valid_where="rx_served"),
        sinr_per_subcarrier_db=_var(TR + ("subcarrier",),
                                    np.where(served[..., None], _db(sinr), np.nan), "dB",
                                    "SINR per subcarrier with expected interference",
                                    nan_means=NAN_RX),
        sinr_db=_var(TR, np.where(served, _db(sinr_wb), np.nan), "dB",
                     "wideband SINR: subcarrier-summed signal over summed interference plus noise",
                     nan_means=NAN_RX),
        snr_db=_var(TR, np.where(served, _db(snr), np.nan), "dB",
                    "wideband SNR of the serving link (no interference)", nan_means=NAN_RX),
        spectral_efficiency_bpshz=_var(TR, spectral_eff, "bit s-1 Hz-1",
                                       "Shannon spectral efficiency, mean over subcarriers of "
                                       "log2(1 + SINR); 0 where not served"),
        shannon_rate_bps=_var(TR, rate, "bit s-1",
                              "Shannon rate: spectral efficiency times bandwidth; "
                              "0 where not served"),
    )
    zenith = np.arccos(np.clip(directions[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(directions[:, 1], directions[:, 0])
    coords = dict(
        time=xr.Variable("time", cirs["time"].values.astype(np.int64),
                         dict(units="ns", long_name="simulated time since session start")),
        link=xr.Variable("link", cirs["link"].values.astype(np.int64),
                         dict(units="1", long_name="link index (base station major)")),
        tx=xr.Variable("link", tx_of_link, dict(long_name="base station of the link")),
        rx=xr.Variable("link", rx_link_names, dict(long_name="platform (receiver) of the link")),
        platform=xr.Variable("platform", np.array(platforms, dtype=str),
                             dict(long_name="receiving platform")),
        beam=_var("beam", np.arange(B, dtype=np.int64), "1", "DFT codebook beam index"),
        axis=xr.Variable("axis", np.array(["x", "y", "z"]),
                         dict(long_name="axis of the array frame")),
        beam_direction=_var(("beam", "axis"), directions, "1",
                            "beam direction unit vector in the base station array frame"),
        beam_zenith_rad=_var("beam", zenith, "rad", "beam zenith angle in the array frame"),
        beam_azimuth_rad=_var("beam", azimuth, "rad", "beam azimuth angle in the array frame"),
        subcarrier=_var("subcarrier", np.arange(K, dtype=np.int64), "1", "subcarrier index"),
        subcarrier_offset_hz=_var("subcarrier", offsets_hz, "Hz",
                                  "baseband offset of the subcarrier from the carrier"),
    )
    attrs = dict(
        interference_rule=INTERFERENCE_RULE, noise_model=NOISE_MODEL,
        power_allocation=POWER_ALLOCATION,
        serving_rule="highest best-beam received power per resource element; ties: lowest link",
        codebook=f"DFT, half-bin-shifted grid, invisible beams dropped; {array.rows} rows x "
                 f"{array.cols} cols, oversampling {cfg.codebook.oversampling}, {B} beams",
        codebook_rows=array.rows, codebook_cols=array.cols,
        codebook_oversampling=cfg.codebook.oversampling, codebook_num_beams=B,
        numerology_mu=ofdm.numerology_mu, subcarrier_spacing_hz=float(ofdm.subcarrier_spacing_hz),
        num_subcarriers=K, num_resource_blocks=ofdm.num_resource_blocks,
        bandwidth_hz=float(ofdm.bandwidth_hz), carrier_frequency_hz=fc_hz,
        noise_figure_db=cfg.receiver.noise_figure_db, temperature_k=cfg.receiver.temperature_k,
        noise_power_per_re_dbm=float(_db(noise_w * 1e3)),
    )
    return xr.Dataset(data, coords=coords, attrs=attrs)
