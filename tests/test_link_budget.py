"""One link budget (simart_pipeline/link/budget.py) for the ``kpis`` stage and the CKM link layers:
a KPI instant and a CKM cell at the same position with the same paths give the same values."""

import numpy as np
import pytest

from simart_pipeline.ckm.link_layers import link_layers
from simart_pipeline.link.beams import dft_codebook
from simart_pipeline.link.budget import (dbm_to_w, power_db, serving_station, station_sinr,
                                         w_to_dbm)
from simart_pipeline.link.kpis import compute_kpis
from tests.test_link import LAMBDA, make_cfg, make_cirs, plane_wave, upa_positions

ROWS, COLS = 1, 4          # a 4-element ULA: 4 orthogonal DFT beams
P_DBM = 30.0               # every station's transmit power (the config's default)


def direction(u_y):
    """Unit vector in the array frame with direction cosine ``u_y`` (no elevation)."""
    return np.array([np.sqrt(1 - u_y**2), u_y, 0.0])


def test_power_conversions():
    x = np.array([1e-3, 1.0, 0.0, -2.0, np.nan])
    db = power_db(x)
    np.testing.assert_allclose(db[:2], [-30.0, 0.0], atol=1e-12)
    assert np.isnan(db[2:]).all() and not np.isinf(db).any()
    np.testing.assert_allclose(dbm_to_w([30.0, 0.0]), [1.0, 1e-3], rtol=1e-15)
    np.testing.assert_allclose(w_to_dbm(dbm_to_w([-87.5, 43.0])), [-87.5, 43.0], rtol=1e-12)
    assert np.isnan(w_to_dbm(0.0))


def test_serving_station_and_expected_interference():
    # station 0 is stronger but interferes more (its mean beam power is high)
    signal = np.array([4.0, 3.0])
    mean = np.array([3.0, 1.0])
    sinr = station_sinr(signal, mean, 0.5, axis=0)
    np.testing.assert_allclose(sinr, [4.0 / (1.0 + 0.5), 3.0 / (3.0 + 0.5)])
    served, serving = serving_station(sinr, np.array([True, True]), axis=0)
    assert served and serving == int(np.argmax(sinr)) == 0
    served, serving = serving_station(sinr, np.array([False, True]), axis=0)
    assert served and serving == 1
    served, _ = serving_station(sinr, np.array([False, False]), axis=0)
    assert not served
    # ties: the lowest index
    assert serving_station(np.array([2.0, 2.0]), np.array([True, True]))[1] == 0


def _cases():
    """Instants/cells ``(u_y and amplitude of bs0, of bs1, masked)``; amplitude None: no path."""
    w = dft_codebook(upa_positions(ROWS, COLS), LAMBDA, ROWS, COLS).weights
    # bs0 on a beam (peak = 4 x mean beam power), bs1 between two beams (peak p x mean, p < 4)
    # and stronger overall. Interference limited, with r = a0^2 / a1^2: bs0 has the stronger best
    # beam if 4 r > p, and bs1 the higher SINR (4 r / 1 < p / r) if p > 4 r^2; r = (p / 4)^0.75
    # lies in (p / 4, sqrt(p / 4))
    peak0 = np.max(np.abs(w @ plane_wave(direction(0.25), 1.0, ROWS, COLS)) ** 2)
    peak1 = np.max(np.abs(w @ plane_wave(direction(0.0), 1.0, ROWS, COLS)) ** 2)
    r = (peak1 / 4.0) ** 0.75
    a1 = 2e-5
    cases = [
        ((0.6, 2e-5), (-0.3, 1e-5), False),      # bs0 serves
        ((0.1, 1e-7), (-0.7, 3e-7), False),      # bs1 serves, near noise
        ((0.45, 3e-8), (0.2, 2e-8), False),      # low SINR
        ((0.25, a1 * np.sqrt(r)), (0.0, a1), False),   # the old rules would disagree
        ((-0.5, None), (0.3, 5e-7), False),      # only bs1 reaches
        ((0.2, None), (-0.2, None), False),      # no station reaches: not served
        ((0.3, 1e-5), (0.1, 1e-5), True),        # masked (inside a building)
    ]
    return w, cases, peak0, peak1


def _kpis_and_ckm(link_adaptation="inner_loop"):
    w, cases, _, _ = _cases()
    T = len(cases)
    a = np.zeros((T, 2, 1, ROWS * COLS, 1), complex)
    valid = np.zeros((T, 2, 1), bool)
    for t, (*stations, _) in enumerate(cases):
        for b, (u, amp) in enumerate(stations):
            if amp is not None:
                a[t, b, 0, :, 0] = plane_wave(direction(u), amp, ROWS, COLS)
                valid[t, b, 0] = True
    masked = np.array([c[2] for c in cases])
    inside = np.repeat(masked[:, None], 2, axis=1)
    cfg = make_cfg(ROWS, COLS, 2, link_adaptation=link_adaptation)
    assert all(b.power_dbm == P_DBM for b in cfg.base_stations)
    tau = np.array([0.4e-6, 0.9e-6])[None, :, None] * np.ones((T, 1, 1))
    cirs = make_cirs(a, tau, valid, ["bs0", "bs1"], ["uav0", "uav0"], P_DBM, tx_rows=ROWS,
                     tx_cols=COLS, dtype=np.complex128, inside=inside)
    k = compute_kpis(cirs, cfg)
    # the CKM's cells: one per instant along x, beam gain |w_b^T a|^2 (ckm/moments.py), masked
    # cells hold nothing (as tile_layers leaves them)
    bp = np.abs(np.einsum("bn,tln->ltb", w, a[:, :, 0, :, 0])) ** 2        # [bs, T, beam]
    has = valid[:, :, 0].T & ~masked[None]
    bp = np.where(has[..., None], bp, 0.0)
    ckm = link_layers(cfg, bp[:, None, None], has[:, None, None], ~masked[None, None])
    ckm = ckm.isel(height=0, y=0)
    return k.isel(platform=0), ckm, masked, bp, cfg


def test_a_kpi_instant_and_a_ckm_cell_give_the_same_link_budget():
    k, ckm, masked, bp, cfg = _kpis_and_ckm()
    served = k["rx_served"].values
    np.testing.assert_array_equal(ckm["served"].values, served)
    np.testing.assert_array_equal(ckm["best_bs"].values, k["serving_link"].values)
    for kpi_name, ckm_name in (("mcs_index", "mcs_index"), ("tbs_bits", "tbs_bits")):
        np.testing.assert_array_equal(ckm[ckm_name].values, k[kpi_name].values, kpi_name)
    for kpi_name, ckm_name in (("sinr_db", "sinr_db"), ("snr_db", "snr_db"),
                               ("effective_sinr_db", "effective_sinr_db"), ("bler", "bler"),
                               ("tbler", "tbler"), ("mcs_rate_bps", "rate_bps"),
                               ("shannon_rate_bps", "shannon_rate_bps")):
        c, v = ckm[ckm_name].values, k[kpi_name].values
        assert c.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(c), np.isnan(v), kpi_name)
        np.testing.assert_allclose(c, v.astype(np.float32), rtol=2e-7, atol=1e-6,
                                   err_msg=kpi_name)
    # the cases exercise several MCS and both stations
    assert len(set(k["mcs_index"].values[served])) >= 3
    assert set(k["serving_link"].values[served]) == {0, 1}


def test_not_served_and_masked_mean_the_same_in_both():
    k, ckm, masked, bp, _ = _kpis_and_ckm()
    unreached = ~masked & (bp.max(-1) == 0).all(0)
    assert unreached.sum() == 1 and masked.sum() == 1
    for sel, rate in ((unreached, 0.0), (masked, np.nan)):
        for name in ("rate_bps", "shannon_rate_bps"):
            np.testing.assert_array_equal(ckm[name].values[sel], rate)
        for name in ("mcs_rate_bps", "shannon_rate_bps"):
            np.testing.assert_array_equal(k[name].values[sel], rate)
        for ds, names in ((ckm, ("sinr_db", "effective_sinr_db", "bler", "tbler")),
                          (k, ("sinr_db", "effective_sinr_db", "bler", "tbler"))):
            for name in names:
                assert np.isnan(ds[name].values[sel]).all(), name
        for ds, names in ((ckm, ("mcs_index", "tbs_bits", "best_bs")),
                          (k, ("mcs_index", "tbs_bits", "serving_link"))):
            for name in names:
                assert (ds[name].values[sel] == -1).all(), name
    assert "0 where" in ckm["rate_bps"].attrs["long_name"]
    assert "masked" in ckm["rate_bps"].attrs["nan_means"]


def test_serving_is_the_highest_sinr_not_the_strongest_beam():
    """Case 3: bs0's best beam is the stronger, but bs1 has more power in all and spreads it over
    every beam, so it interferes more with bs0 than bs0 (one sharp beam, little mean power) with
    it: bs1 gives the higher SINR and serves, in the KPIs and in the map."""
    k, ckm, masked, bp, cfg = _kpis_and_ckm()
    _, _, peak0, peak1 = _cases()
    assert peak1 < peak0                        # bs1 sits between two beams
    t = 3
    p_re = dbm_to_w(P_DBM) / k.sizes["subcarrier"]
    best = p_re * bp[:, t].max(-1)
    assert best[0] > best[1]                    # the old CKM rule would pick bs0
    assert k["serving_link"].values[t] == 1 and ckm["best_bs"].values[t] == 1
    beam_sinr = 10 ** (k["best_beam_sinr_db"].values[t] / 10)
    assert beam_sinr[1] > beam_sinr[0]


@pytest.mark.parametrize("loop", ["inner_loop", "outer_loop"])
def test_rates_follow_from_the_mcs_in_the_kpis(loop):
    """The shared TBS/rate code turns each stage's MCS (outer loop in the KPIs included) into
    TBS (1 - TBLER) / slot."""
    k, *_ = _kpis_and_ckm(loop)
    served = k["rx_served"].values
    tbs = k["mcs_tbs_bits"].values[k["mcs_index"].values[served]]
    np.testing.assert_array_equal(k["tbs_bits"].values[served], tbs)
    np.testing.assert_allclose(k["mcs_rate_bps"].values[served],
                               tbs * (1 - k["tbler"].values[served]) / k.attrs["slot_duration_s"],
                               rtol=1e-12)
