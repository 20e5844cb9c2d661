"""Link- and system-level KPIs from the channel impulse responses: the ``kpis`` store.

Pipeline per radio-clock instant (each instant is treated as one scheduled slot):
CIRs -> CFR on the allocated subcarriers (:mod:`.ofdm`) -> beams (:mod:`.beams`) -> serving base
station, best beam and SINR per resource element with interference (:mod:`.sinr`) -> EESM, BLER,
TBS, TBLER (:mod:`.phy_abstraction`) -> MCS for a TBLER target (:mod:`.link_adaptation`) ->
rates from the MCS and from Shannon; the link budget (dB, serving station, inner loop, TBS,
rates, what "not served" means) is :mod:`.budget`, shared with the CKM's link layers. Every KPI's
definition, unit and reference:
``docs/link-level.md``; each variable's attrs carry ``units``, ``long_name`` and ``definition``.

Masking: a link without a valid path, or whose receiver is inside a building or within 1 cm of
the transmitter (``cirs`` flags), has no per-link KPI (NaN, -1); a receiver with either flag on
any of its links has every KPI masked (NaN); a receiver with no path to any base station is not
served (SINR NaN, rates 0).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from simart_pipeline.config import SceneConfig
from simart_pipeline.link.beams import dft_codebook
from simart_pipeline.link.budget import (CATEGORY, SERVING_RULE, allocation, dbm_to_w, inner_loop,
                                         power_db, power_per_re_w, rates, sinr_per_re, w_to_dbm)
from simart_pipeline.link.kpi_definitions import (DEFINITIONS, NAN_INTERFERENCE, NAN_LINK, NAN_RATE,
                                                  NAN_RX, REFERENCES)
from simart_pipeline.link.link_adaptation import select_mcs_outer_loop
from simart_pipeline.link.ofdm import subcarrier_offsets_hz
from simart_pipeline.link.sinr import INTERFERENCE_RULE, chunk_steps, sinr_chunk
from simart_pipeline.vocabulary import AXES, SPEED_OF_LIGHT_MPS

DEFAULT_MAX_CHUNK_BYTES = 256 * 2**20   # working set of one time chunk
HARQ_STREAM = 0x4B5049                  # seed stream of the HARQ draws, next to cfg.seed
LINK_FLAGS = ("link_no_path", "link_rx_inside_building", "link_rx_near_tx")

__all__ = ["CATEGORY", "check_cirs", "compute_kpis", "dbm_to_w"]


def _var(dims, data, units, long_name, definition=None, **attrs):
    a = dict(units=units, long_name=long_name)
    if definition:
        a["definition"] = definition
    a.update(attrs)
    return xr.Variable(dims, data, a)


def check_cirs(cirs: xr.Dataset, source: str = "cirs") -> None:
    """Raise ``ValueError`` naming ``source`` when the dataset breaks the ``cirs`` contract that
    the KPIs rely on (variables, dims, flags consistent with ``valid``)."""
    need = {"a": ("time", "link", "rx_ant", "tx_ant", "path"), "tau_s": ("time", "link", "path"),
            "valid": ("time", "link", "path"), "tx_power_dbm": ("link",),
            "tx_ant_position_m": ("tx_ant", "axis")}
    need.update({f: ("time", "link") for f in LINK_FLAGS})
    problems = [f"variable {k!r} missing" for k in need if k not in cirs.variables]
    problems += [f"variable {k!r} has dims {cirs[k].dims}, expected a permutation of {d}"
                 for k, d in need.items() if k in cirs.variables and set(cirs[k].dims) != set(d)]
    problems += [f"coordinate {k!r} on dim link missing" for k in ("tx", "rx")
                 if k not in cirs.coords or cirs[k].dims != ("link",)]
    if not problems:
        if not np.isfinite(cirs["tx_power_dbm"].values).all():
            problems.append("tx_power_dbm holds NaN or inf")
        no_path = ~cirs["valid"].transpose("time", "link", "path").values.any(-1)
        flag = cirs["link_no_path"].transpose("time", "link").values.astype(bool)
        if not np.array_equal(no_path, flag):
            problems.append(f"link_no_path disagrees with valid at {(no_path != flag).sum()} "
                            "(time, link) entries")
    if problems:
        raise ValueError(f"{source}: not a usable cirs dataset: " + "; ".join(problems))


def _check_chunk(a, tau_s, valid, source: str, t0: int) -> None:
    bad_tau = valid & ~(np.isfinite(tau_s) & (tau_s >= 0))
    bad_a = valid[:, :, None, None, :] & ~np.isfinite(a)
    if bad_tau.any() or bad_a.any():
        t = t0 + int(np.argwhere(bad_tau if bad_tau.any() else bad_a.any((2, 3)))[0, 0])
        raise ValueError(f"{source}: valid paths with a non-finite or negative tau_s, or a "
                         f"non-finite a (first at time index {t})")


def _codebook(cirs, cfg, fc_hz, weights):
    """Precoders and their coordinates: a file's weights, or the DFT grid of the config."""
    array = cfg.base_stations[0].array   # one transmit array per scene (config validator)
    if weights is not None:
        w = np.asarray(weights, dtype=np.complex128)
        if w.ndim != 2 or w.shape[1] != cirs.sizes["tx_ant"]:
            raise ValueError(f"codebook weights must be [num_beams, {cirs.sizes['tx_ant']}], "
                             f"got {w.shape}")
        return w, {}, f"file codebook.path={cfg.codebook.path}, {w.shape[0]} beams"
    cb = dft_codebook(cirs["tx_ant_position_m"].transpose("tx_ant", "axis").values,
                      SPEED_OF_LIGHT_MPS / fc_hz, array.rows, array.cols, cfg.codebook.oversampling,
                      cfg.codebook.visible_only)
    nan_dir = "beam beyond end-fire (beam_visible false): no real direction"
    with np.errstate(invalid="ignore"):
        zenith = np.arccos(np.clip(cb.directions[:, 2], -1.0, 1.0))
        azimuth = np.arctan2(cb.directions[:, 1], cb.directions[:, 0])
    coords = dict(
        beam_direction_cosine_y=_var("beam", cb.direction_cosines[:, 0], "1",
                                     "beam direction cosine u_y (array frame, y = columns)"),
        beam_direction_cosine_z=_var("beam", cb.direction_cosines[:, 1], "1",
                                     "beam direction cosine u_z (array frame, z = rows)"),
        beam_visible=xr.Variable("beam", cb.visible, dict(
            long_name="beam direction inside visible space (u_y^2 + u_z^2 <= 1)")),
        beam_direction=_var(("beam", "axis"), cb.directions, "1",
                            "beam direction unit vector in the base station array frame",
                            nan_means=nan_dir),
        beam_zenith_rad=_var("beam", zenith, "rad", "beam zenith angle in the array frame",
                             nan_means=nan_dir),
        beam_azimuth_rad=_var("beam", azimuth, "rad", "beam azimuth angle in the array frame",
                              nan_means=nan_dir))
    desc = (f"DFT, half-bin-shifted grid of direction cosines; {array.rows} rows x {array.cols} "
            f"cols, oversampling {cfg.codebook.oversampling}, "
            f"{'visible beams only' if cfg.codebook.visible_only else 'all grid beams'}, "
            f"{cb.weights.shape[0]} beams")
    return cb.weights, coords, desc


def compute_kpis(cirs: xr.Dataset, cfg: SceneConfig, codebook_weights=None, source: str = "cirs",
                 max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES) -> xr.Dataset:
    """The ``kpis`` dataset of one (scene, weather) from its ``cirs`` dataset.

    - ``cirs``: docs/data-contract.md (processed chunk by chunk over ``time``);
    - ``cfg``: the scene config (``ofdm``, ``receiver``, ``codebook``, ``link``, arrays, seed);
    - ``codebook_weights``: ``[B, tx_ant]`` precoders from ``codebook.path`` (None: DFT grid);
    - ``source``: how errors name the input (e.g. the store's path).

    Per-link KPIs are on ``(time, link[, beam])``, per-receiver KPIs on ``(time, platform[,
    subcarrier])``; the receivers of the links are the platforms.
    """
    check_cirs(cirs, source)
    ofdm, link, rxcfg = cfg.ofdm, cfg.link, cfg.receiver
    fc_hz = float(ofdm.carrier_frequency_hz)
    if "carrier_frequency_hz" in cirs.attrs and not np.isclose(
            float(cirs.attrs["carrier_frequency_hz"]), fc_hz, rtol=1e-9):
        raise ValueError(f"{source}: carrier {cirs.attrs['carrier_frequency_hz']} Hz differs "
                         f"from the config's ofdm.carrier_frequency_hz {fc_hz} Hz")
    alloc = allocation(ofdm, link, rxcfg)
    first_rb, num_rb, sc, K = alloc.first_rb, alloc.num_rb, alloc.subcarriers, alloc.num_subcarriers
    offsets_hz = subcarrier_offsets_hz(ofdm)[sc]
    weights, beam_coords, codebook_desc = _codebook(cirs, cfg, fc_hz, codebook_weights)
    B = weights.shape[0]

    tx_of_link = np.asarray(cirs["tx"].values).astype(str)
    rx_link_names = np.asarray(cirs["rx"].values).astype(str)
    platforms = list(dict.fromkeys(rx_link_names))
    rx_of_link = np.array([platforms.index(r) for r in rx_link_names], dtype=np.int64)
    T, L, R = cirs.sizes["time"], cirs.sizes["link"], len(platforms)
    p_re_w = power_per_re_w(cirs["tx_power_dbm"].transpose("link").values, K)   # W per RE
    noise_w = alloc.noise_w

    flags = {f: cirs[f].transpose("time", "link").values.astype(bool) for f in LINK_FLAGS}
    has_path = ~flags["link_no_path"]
    on_rx = rx_of_link[None, :] == np.arange(R)[:, None]                  # [R, L]
    rx_inside = (flags["link_rx_inside_building"][:, None, :] & on_rx).any(-1)   # [T, R]
    rx_near = (flags["link_rx_near_tx"][:, None, :] & on_rx).any(-1)
    rx_masked = rx_inside | rx_near
    link_ok = has_path & ~rx_masked[:, rx_of_link]                        # [T, L]

    out = dict(gain=np.zeros((T, L, B)), beam_sinr=np.zeros((T, L, B)),
               best=np.zeros((T, L), np.int64), served=np.zeros((T, R), bool),
               serving=np.zeros((T, R), np.int64), signal_w=np.zeros((T, R, K)),
               interference_w=np.zeros((T, R, K)))
    step = chunk_steps(cirs.sizes, B, K, max_chunk_bytes)
    for t0 in range(0, T, step):
        part = cirs.isel(time=slice(t0, t0 + step))
        a = part["a"].transpose("time", "link", "rx_ant", "tx_ant", "path").values
        tau = part["tau_s"].transpose("time", "link", "path").values
        valid = part["valid"].transpose("time", "link", "path").values.astype(bool)
        _check_chunk(a, tau, valid, source, t0)
        res = sinr_chunk(a, tau, valid, fc_hz, offsets_hz, weights, p_re_w, noise_w, rx_of_link,
                         link_ok[t0:t0 + step], R)
        for key, value in res.items():
            out[key][t0:t0 + step] = value

    served, serving = out["served"], out["serving"]
    serving_beam = np.take_along_axis(out["best"], serving, axis=1)
    signal_w, interference_w = out["signal_w"], out["interference_w"]
    sinr = sinr_per_re(signal_w, interference_w, noise_w)                 # [T, R, K]

    # PHY abstraction and link adaptation on the served receivers' per-RE SINR.
    n_re, phy = alloc.num_re, alloc.phy
    uniform = np.random.default_rng((cfg.seed, HARQ_STREAM)).random((T, R))
    mcs = np.full((T, R), -1, np.int64)
    eff, bler, tbler = (np.full((T, R), np.nan) for _ in range(3))
    olla_offset = None
    if link.link_adaptation == "outer_loop":
        mcs, eff, bler, tbler, ack, olla_offset = select_mcs_outer_loop(
            phy, sinr, uniform, link.bler_target, link.olla_delta_up_db,
            link.olla_offset_limits_db, scheduled=served)
    else:
        per_step = max(1, max_chunk_bytes // (8 * 4 * max(R, 1) * phy.num_mcs * K))
        for t0 in range(0, T, per_step):
            sl = slice(t0, t0 + per_step)
            mcs[sl], eff[sl], bler[sl], tbler[sl] = inner_loop(phy, sinr[sl], served[sl],
                                                               link.bler_target)
        ack = served & (uniform >= tbler)
    tb = phy.transport_block
    mcs_safe = np.maximum(mcs, 0)

    def per_mcs(values):   # a per-MCS value at each receiver's MCS, -1 where not served
        return np.where(served, np.asarray(values)[mcs_safe], -1)

    slot_s, band_hz = alloc.slot_s, alloc.bandwidth_hz
    rate = rates(phy, mcs, tbler, sinr, served, rx_masked, slot_s, band_hz)
    tbs_bits, mcs_rate = rate["tbs_bits"], rate["mcs_rate_bps"]
    serving_tx = np.where(served, tx_of_link[serving], "")

    gain, beam_sinr, best = out["gain"], out["beam_sinr"], out["best"]
    best_gain = np.take_along_axis(gain, best[..., None], -1)[..., 0]
    best_sinr = np.take_along_axis(beam_sinr, best[..., None], -1)[..., 0]
    lm = link_ok[..., None]
    TL, TR, TRK = ("time", "link"), ("time", "platform"), ("time", "platform", "subcarrier")
    s3 = served[..., None]
    data = dict(
        link_has_path=xr.Variable(TL, has_path, dict(
            long_name="link has at least one valid path (not link_no_path)")),
        link_kpis_valid=xr.Variable(TL, link_ok, dict(
            long_name="link has a path and its receiver is neither inside a building nor "
                      "within 1 cm of the transmitter: per-link KPIs are valid")),
        beam_gain_db=_var(TL + ("beam",), np.where(lm, power_db(gain), np.nan), "dB",
                          "wideband beam gain", "mean over allocated subcarriers k of "
                          "sum_r |sum_n w_b,n H_r,n[k]|^2 (MRC over receive antennas)",
                          nan_means=NAN_LINK),
        beam_sinr_db=_var(TL + ("beam",), np.where(lm, power_db(beam_sinr), np.nan), "dB",
                          "wideband SINR if this link served with this beam",
                          "sum_k S[k] / sum_k (I[k] + N), interference per interference_rule",
                          nan_means=NAN_LINK),
        best_beam=_var(TL, np.where(link_ok, best, -1), "1",
                       "beam that maximises the link's wideband SINR (ties: lowest index); "
                       "-1 where link_kpis_valid is false", valid_where="link_kpis_valid"),
        best_beam_gain_db=_var(TL, np.where(link_ok, power_db(best_gain), np.nan), "dB",
                               "wideband gain of the best beam", nan_means=NAN_LINK),
        best_beam_sinr_db=_var(TL, np.where(link_ok, power_db(best_sinr), np.nan), "dB",
                               "wideband SINR of the best beam", nan_means=NAN_LINK),
        rx_power_per_re_dbm=_var(TL, np.where(link_ok, w_to_dbm(p_re_w * best_gain), np.nan),
                                 "dBm", "received power per resource element with the best beam "
                                 "(RSRP-like)", "p_tx / K times the best beam's wideband gain",
                                 nan_means=NAN_LINK),
        rx_inside_building=xr.Variable(TR, rx_inside, dict(
            long_name="receiver inside a building (cirs link_rx_inside_building): KPIs masked")),
        rx_near_tx=xr.Variable(TR, rx_near, dict(
            long_name="receiver within 1 cm of a transmitter (cirs link_rx_near_tx): KPIs "
                      "masked")),
        rx_served=xr.Variable(TR, served, dict(
            long_name="receiver is served: a valid path to at least one base station and its "
                      "KPIs are not masked")),
        serving_link=_var(TR, np.where(served, serving, -1), "1",
                          "index on dim link of the serving link; -1 where not served",
                          valid_where="rx_served"),
        serving_tx=xr.Variable(TR, serving_tx.astype(str), dict(
            long_name="serving base station (empty where rx_served is false)")),
        serving_beam=_var(TR, np.where(served, serving_beam, -1), "1",
                          "beam of the serving base station; -1 where not served",
                          valid_where="rx_served"),
        signal_power_per_re_dbm=_var(TR, np.where(served, w_to_dbm(signal_w.mean(-1)), np.nan),
                                     "dBm", "received signal power per resource element after "
                                     "MRC, mean over allocated subcarriers", nan_means=NAN_RX),
        interference_power_per_re_dbm=_var(
            TR, np.where(served, w_to_dbm(interference_w.mean(-1)), np.nan), "dBm",
            "expected interference power per resource element after MRC, mean over allocated "
            "subcarriers", nan_means=NAN_INTERFERENCE),
        sinr_per_subcarrier_db=_var(TRK, np.where(s3, power_db(sinr), np.nan), "dB",
                                    "SINR per resource element of the allocated subcarriers",
                                    "S[k] / (I[k] + N) of the serving link and beam",
                                    nan_means=NAN_RX),
        sinr_db=_var(TR, np.where(served, power_db(signal_w.sum(-1)
                                                   / (interference_w + noise_w).sum(-1)), np.nan),
                     "dB", "wideband SINR",
                     "sum_k S[k] / sum_k (I[k] + N)", nan_means=NAN_RX),
        snr_db=_var(TR, np.where(served, power_db(signal_w.sum(-1) / (K * noise_w)), np.nan),
                    "dB",
                    "wideband SNR of the serving link and beam (no interference)",
                    "sum_k S[k] / (K N)", nan_means=NAN_RX),
        effective_sinr_db=_var(TR, power_db(eff), "dB", "EESM effective SINR at the selected MCS",
                               "-beta_m ln(mean_k exp(-SINR[k] / beta_m)), log-sum-exp",
                               nan_means=NAN_RX),
        mcs_index=_var(TR, mcs, "1", f"MCS index I_MCS of TS 38.214 Table 5.1.3.1-"
                       f"{link.mcs_table} selected by link adaptation; -1 where not served",
                       valid_where="rx_served"),
        modulation_order=_var(TR, per_mcs(phy.mcs.modulation_order), "bit", "modulation order "
                              "Q_m (bits per symbol); -1 where not served",
                              valid_where="rx_served"),
        code_rate=_var(TR, np.where(served, phy.mcs.code_rate[mcs_safe], np.nan), "1",
                       "target code rate R of the MCS", nan_means=NAN_RX),
        tbs_bits=_var(TR, tbs_bits, "bit", "transport block size (TS 38.214 5.1.3.2); -1 where "
                      "not served", valid_where="rx_served"),
        num_code_blocks=_var(TR, per_mcs(tb.num_code_blocks), "1", "code blocks C of the "
                             "transport block (TS 38.212 5.2.2); -1 where not served",
                             valid_where="rx_served"),
        code_block_size_bits=_var(TR, per_mcs(tb.code_block_size_bits), "bit",
                                  "code-block size K' with CRC (TS 38.212 5.2.2); -1 where not "
                                  "served", valid_where="rx_served"),
        ldpc_base_graph=_var(TR, per_mcs(tb.ldpc_base_graph), "1", "LDPC base graph (TS 38.212 "
                             "7.2.2); -1 where not served", valid_where="rx_served"),
        bler=_var(TR, bler, "1", "code-block error rate at the effective SINR",
                  "AWGN BLER table of the MCS at code-block size K' (nearest grid point)",
                  nan_means=NAN_RX),
        tbler=_var(TR, tbler, "1", "transport block error rate", "1 - (1 - BLER)^C",
                   nan_means=NAN_RX),
        harq_ack=xr.Variable(TR, ack, dict(
            long_name="transport block decoded (ACK): uniform draw >= TBLER, seeded by the "
                      "config seed; false where not served", valid_where="rx_served")),
        mcs_rate_bps=_var(TR, mcs_rate, "bit s-1", "expected goodput of the selected MCS",
                          "TBS (1 - TBLER) / slot duration; 0 where not served",
                          nan_means=NAN_RATE),
        mcs_spectral_efficiency_bpshz=_var(TR, mcs_rate / band_hz, "bit s-1 Hz-1",
                                           "spectral efficiency of the selected MCS",
                                           "mcs_rate_bps / allocated bandwidth",
                                           nan_means=NAN_RATE),
        shannon_spectral_efficiency_bpshz=_var(TR, rate["shannon_spectral_efficiency_bpshz"],
                                               "bit s-1 Hz-1", "Shannon spectral efficiency",
                                               "mean_k log2(1 + SINR[k]); 0 where not served",
                                               nan_means=NAN_RATE),
        shannon_rate_bps=_var(TR, rate["shannon_rate_bps"], "bit s-1", "Shannon rate",
                              "shannon_spectral_efficiency_bpshz times the allocated bandwidth",
                              nan_means=NAN_RATE),
        mcs_modulation_order=_var("mcs", phy.mcs.modulation_order, "bit",
                                  "modulation order Q_m per MCS index"),
        mcs_code_rate=_var("mcs", phy.mcs.code_rate, "1", "target code rate R per MCS index"),
        mcs_eesm_beta=_var("mcs", phy.beta, "1", "EESM calibration factor beta per MCS index"),
        mcs_has_bler_curve=xr.Variable("mcs", phy.available, dict(
            long_name="a BLER table exists for the MCS (only those are selectable)")),
        mcs_tbs_bits=_var("mcs", tb.tbs_bits, "bit", "transport block size per MCS index for "
                          "the allocation"),
    )
    if olla_offset is not None:
        data["olla_offset_db"] = _var(TR, olla_offset, "dB", "outer-loop SINR offset applied "
                                      "to the last effective SINR report", nan_means=NAN_RX)
    for name, var in data.items():
        if var.dtype.kind in "fiu" and "definition" not in var.attrs:
            var.attrs["definition"] = DEFINITIONS[name]
    coords = dict(
        time=xr.Variable("time", cirs["time"].values.astype(np.int64),
                         dict(units="ns", long_name="simulated time since session start")),
        link=xr.Variable("link", cirs["link"].values.astype(np.int64),
                         dict(units="1", long_name="link index (base station major)")),
        tx=xr.Variable("link", tx_of_link, dict(long_name="base station of the link")),
        rx=xr.Variable("link", rx_link_names, dict(long_name="platform (receiver) of the link")),
        platform=xr.Variable("platform", np.array(platforms, dtype=str),
                             dict(long_name="receiving platform")),
        beam=_var("beam", np.arange(B, dtype=np.int64), "1", "codebook beam index"),
        axis=xr.Variable("axis", np.array(AXES),
                         dict(long_name="axis of the array frame")),
        subcarrier=_var("subcarrier", sc.astype(np.int64), "1",
                        "subcarrier index on the carrier (allocated subcarriers only)"),
        subcarrier_offset_hz=_var("subcarrier", offsets_hz, "Hz",
                                  "baseband offset of the subcarrier from the carrier"),
        mcs=_var("mcs", np.arange(phy.num_mcs, dtype=np.int64), "1", "MCS index I_MCS"),
        **beam_coords,
    )
    attrs = dict(
        interference_rule=INTERFERENCE_RULE,
        noise_model="thermal noise k_B T df 10^(NF/10) per resource element (one subcarrier "
                    "spacing df) at the receiver temperature and noise figure",
        power_allocation="each base station splits its transmit power evenly over the K "
                         "allocated subcarriers of an OFDM symbol (p = P_tx / K per resource "
                         "element); every base station transmits on the same allocation",
        combining="maximum-ratio combining over the receive antennas, matched per subcarrier "
                  "to the serving beam",
        serving_rule=SERVING_RULE + " (here: the link index)",
        best_beam_rule="per link, the beam with the highest wideband SINR",
        masking_rule="per-link KPIs need a valid path and a receiver neither inside a building "
                     "nor within 1 cm of the transmitter; a receiver with either flag on any "
                     "of its links has every KPI masked (NaN, -1); rates are 0 where a "
                     "receiver has no path to any base station",
        slot_rule="each radio-clock instant is one slot in which each served receiver gets the "
                  "whole allocation and one transport block (full buffer)",
        phy_abstraction="EESM with per-MCS beta -> AWGN BLER table at the code-block size -> "
                        "TBLER = 1 - (1 - BLER)^C, as Sionna SYS; BLER lookup on a 0.1 dB x "
                        "100 bit grid",
        link_adaptation=link.link_adaptation, bler_target=link.bler_target,
        mcs_table=f"TS 38.214 Table 5.1.3.1-{link.mcs_table}", bler_table_category="PDSCH",
        codebook=codebook_desc, codebook_num_beams=B,
        numerology_mu=ofdm.numerology_mu, subcarrier_spacing_hz=float(ofdm.subcarrier_spacing_hz),
        cyclic_prefix=ofdm.cyclic_prefix, num_ofdm_symbols=ofdm.num_ofdm_symbols,
        slot_duration_s=slot_s, num_subcarriers_carrier=ofdm.num_subcarriers,
        num_resource_blocks_carrier=ofdm.num_resource_blocks,
        first_allocated_resource_block=first_rb, num_allocated_resource_blocks=num_rb,
        num_allocated_subcarriers=K, allocated_bandwidth_hz=float(band_hz),
        num_re_for_tbs=n_re, dmrs_re_per_prb=link.dmrs_re_per_prb,
        overhead_re_per_prb=link.overhead_re_per_prb, num_layers=1,
        carrier_frequency_hz=fc_hz, noise_figure_db=rxcfg.noise_figure_db,
        temperature_k=rxcfg.temperature_k, noise_power_per_re_dbm=float(w_to_dbm(noise_w)),
        harq_seed=f"numpy default_rng(({cfg.seed}, {HARQ_STREAM}))",
        references=REFERENCES, kpi_definitions="docs/link-level.md",
    )
    if olla_offset is not None:
        attrs.update(olla_delta_up_db=link.olla_delta_up_db,
                     olla_delta_down_db=link.olla_delta_up_db * link.bler_target
                     / (1 - link.bler_target),
                     olla_offset_limits_db=list(link.olla_offset_limits_db))
    return xr.Dataset(data, coords=coords, attrs=attrs)
