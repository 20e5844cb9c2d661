"""PHY abstraction: MCS tables, TBS and segmentation (TS 38.214 / 38.212), EESM, BLER tables,
TBLER, inner- and outer-loop link adaptation. Known answers worked by hand from the standards."""

import json
from importlib import resources

import numpy as np
import pytest

from simart_pipeline.link.bler import BlerTable, bler_table
from simart_pipeline.link.eesm import eesm_beta, effective_sinr
from simart_pipeline.link.link_adaptation import (inner_loop_mcs, select_mcs_inner_loop,
                                                  select_mcs_outer_loop)
from simart_pipeline.link.mcs import mcs_table
from simart_pipeline.link.phy_abstraction import PhyAbstraction, tbler_from_bler
from simart_pipeline.link.tbs import TBS_TABLE, num_re_for_tbs, transport_block

# --- MCS tables -----------------------------------------------------------------------------------

# The spectral-efficiency columns of TS 38.214 Tables 5.1.3.1-1 and -2 (rounded to 4 decimals),
# an independent check of the Q_m and R x 1024 columns typed into mcs.py.
SE_TABLE_1 = [0.2344, 0.3066, 0.3770, 0.4902, 0.6016, 0.7402, 0.8770, 1.0273, 1.1758, 1.3262,
              1.3281, 1.4766, 1.6953, 1.9141, 2.1602, 2.4063, 2.5703, 2.5664, 2.7305, 3.0293,
              3.3223, 3.6094, 3.9023, 4.2129, 4.5234, 4.8164, 5.1152, 5.3320, 5.5547]
SE_TABLE_2 = [0.2344, 0.3770, 0.6016, 0.8770, 1.1758, 1.4766, 1.6953, 1.9141, 2.1602, 2.4063,
              2.5703, 2.7305, 3.0293, 3.3223, 3.6094, 3.9023, 4.2129, 4.5234, 4.8164, 5.1152,
              5.3320, 5.5547, 5.8906, 6.2266, 6.5703, 6.9141, 7.1602, 7.4063]


def test_mcs_tables_match_the_standards_spectral_efficiency():
    for table, se in ((1, SE_TABLE_1), (2, SE_TABLE_2)):
        t = mcs_table(table)
        np.testing.assert_allclose(t.spectral_efficiency, se, atol=5e-5)
    assert [mcs_table(i).num_mcs for i in (1, 2, 3, 4)] == [29, 28, 29, 27]
    assert mcs_table(4).modulation_order.max() == 10 and mcs_table(3).code_rate_x1024[0] == 30
    for i in (1, 2, 3, 4):
        assert np.all(np.diff(mcs_table(i).modulation_order) >= 0)
    with pytest.raises(ValueError, match="tables 1, 2, 3, 4"):
        mcs_table(5)


# --- TBS ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("qm, r1024, n_prb, layers, tbs, c, k_cb, bg", [
    # 1 PRB, 14 symbols, 12 DMRS REs: N_RE = 156; MCS 0 of table 1: N_info = 36.56,
    # n = 3, N' = 32 -> TBS 32 (Table 5.1.3.2-1)
    (2, 120, 1, 1, 32, 1, 48, 2),
    # 4 PRB, MCS 9 of table 1: N_info = 624 * 679/1024 * 2 = 827.5, n = 3, N' = 824 -> 848
    (2, 679, 4, 1, 848, 1, 864, 2),
    # 51 PRB, MCS 16 of table 1: N_info = 20449.4, n = 9, N' = 512 * 40 = 20480 > 8424:
    # C = 3, TBS = 24 ceil(20504 / 24) - 24 = 20496; K' = 20520 / 3 + 24 = 6864, base graph 1
    (4, 658, 51, 1, 20496, 3, 6864, 1),
    # 100 PRB, MCS 2 of table 1 (R <= 1/4): N_info = 5880.5, n = 7, N' = 128 * 46 = 5888:
    # C = ceil(5912 / 3816) = 2, TBS = 16 ceil(5912 / 16) - 24 = 5896; K' = 2984, base graph 2
    (2, 193, 100, 1, 5896, 2, 2984, 2),
    # peak: 273 PRB, table 2 MCS 27 (256QAM, 948), 4 layers: N_info = 1261669.5, n = 15,
    # N' = 32768 * 39, C = 152, TBS = 1216 * 1051 - 24 = 1277992 (the NR maximum)
    (8, 948, 273, 4, 1277992, 152, 8432, 1),
])
def test_tbs_known_cases(qm, r1024, n_prb, layers, tbs, c, k_cb, bg):
    tb = transport_block(qm, r1024, num_re_for_tbs(n_prb, 14, 12), layers)
    assert (tb.tbs_bits, tb.num_code_blocks, tb.code_block_size_bits, tb.ldpc_base_graph) == (
        tbs, c, k_cb, bg)


def test_tbs_uses_exact_arithmetic_at_rounding_ties():
    # table 1 MCS 23 (64QAM, 719), N_RE = 27958: N_info = 117783.99609375, so
    # (N_info - 24) / 2^11 = 57.49999981: rounds to 57 -> N' = 116736, C = 14, TBS = 116792.
    # float32 evaluates N_info as 117784.0 exactly and rounds the tie up (TBS 118896).
    tb = transport_block(6, 719, 27958)
    assert tb.n_info == 117783.99609375
    assert (tb.tbs_bits, tb.num_code_blocks) == (116792, 14)


def test_tbs_table_segmentation_invariants_and_monotonicity():
    assert TBS_TABLE.size == 93 and np.all(np.diff(TBS_TABLE) > 0) and np.all(TBS_TABLE % 8 == 0)
    assert num_re_for_tbs(10, 14, 0) == 1560 and num_re_for_tbs(10, 12, 12, 6) == 1260
    n_re = np.arange(1, 42900, 7)
    for table in (1, 2, 3, 4):
        t = mcs_table(table)
        for m in range(t.num_mcs):
            tb = transport_block(t.modulation_order[m], t.code_rate_x1024[m], n_re)
            a, c, k = tb.tbs_bits, tb.num_code_blocks, tb.code_block_size_bits
            # every information and CRC bit lands in exactly one code block
            np.testing.assert_array_equal(c * k, a + tb.tb_crc_bits + c * tb.cb_crc_bits)
            assert np.all(k <= np.where(tb.ldpc_base_graph == 1, 8448, 3840))
            assert np.all(a % 8 == 0) and np.all(np.diff(a) >= 0)
            # the TBS tracks N_info: within the quantisation of the standard's steps
            assert np.all(np.abs(a - tb.n_info) <= np.maximum(0.1 * tb.n_info, 32))
    with pytest.raises(ValueError, match="must be > 0"):
        transport_block(2, 120, 0)
    with pytest.raises(ValueError, match="multiple of 1/2"):
        transport_block(2, 120.25, 10)


# --- EESM -----------------------------------------------------------------------------------------

def test_eesm_of_a_flat_sinr_is_that_sinr_even_where_float64_underflows():
    sinr_db = np.array([-20.0, 0.0, 13.0, 30.0, 45.0, 60.0])
    flat = np.repeat(10 ** (sinr_db / 10)[:, None], 612, axis=1)
    for beta in (1.6, 6.5, 34.28, 132.54):
        np.testing.assert_allclose(effective_sinr(flat, beta), flat[:, 0], rtol=1e-12)
    with np.errstate(divide="ignore"):
        naive = -1.6 * np.log(np.mean(np.exp(-flat / 1.6), axis=-1))
    assert np.isinf(naive[-2:]).all()   # the textbook form breaks at 45 and 60 dB


def test_eesm_bounds_limits_masks_and_reference_form():
    rng = np.random.default_rng(5)
    x = rng.exponential(size=(7, 96)) * 10 ** rng.uniform(-1, 2, (7, 1))
    for beta in (0.5, 3.0, 30.0):
        eff = effective_sinr(x, beta)
        assert np.all(eff >= x.min(-1) * (1 - 1e-12)) and np.all(eff <= x.mean(-1))
        # textbook form in float64 where nothing underflows
        np.testing.assert_allclose(eff, -beta * np.log(np.mean(np.exp(-x / beta), -1)),
                                   rtol=1e-12)
        np.testing.assert_allclose(eff, effective_sinr(x[:, ::-1], beta), rtol=1e-12)
    # beta -> infinity: the mean; -beta ln E exp(-x/beta) >= E x - E x^2 / (2 beta)
    big = effective_sinr(x, 1e5)
    assert np.all(big <= x.mean(-1)) and np.all(big >= x.mean(-1) - np.mean(x**2, -1) / 2e5)
    # beta -> 0: the smallest SINR, up to beta ln N
    assert np.all(np.abs(effective_sinr(x, 1e-3) - x.min(-1)) <= 1e-3 * np.log(96) + 1e-12)
    # axis and a per-row beta
    np.testing.assert_allclose(effective_sinr(x.T, np.arange(1.0, 8.0), axis=0),
                               [effective_sinr(x[i], i + 1.0) for i in range(7)], rtol=1e-12)
    # a mask equals taking the used elements; a row without any is NaN
    used = rng.uniform(size=x.shape) < 0.5
    used[3] = False
    eff = effective_sinr(x, 4.0, where=used)
    for i in range(7):
        if i == 3:
            assert np.isnan(eff[i])
        else:
            assert eff[i] == pytest.approx(effective_sinr(x[i][used[i]], 4.0), rel=1e-12)
    assert eesm_beta(1).size == 29 and eesm_beta(2).size == 28
    with pytest.raises(ValueError, match="no EESM beta values for MCS table 3"):
        eesm_beta(3)


# --- BLER tables ----------------------------------------------------------------------------------

def _raw(category, table):
    path = (resources.files("simart_pipeline.link") / "data" / "bler_tables"
            / f"{category.upper()}_table{table}.json")
    key = {"pusch": "0", "pdsch": "1"}[category]
    return json.loads(path.read_text())["category"][key]["index"][str(table)]["MCS"]


def test_bler_lookup_is_bilinear_in_log_bler_and_clamped():
    t = bler_table("pdsch", 1)
    raw = _raw("pdsch", 1)
    assert t.available.tolist() == [False] * 3 + [True] * 26
    assert np.isnan(t.bler(1, 24, 10.0))
    for m in (3, 6, 12):
        snr = np.asarray(raw[str(m)]["SNR_db"])
        cbs = np.array(sorted(map(int, raw[str(m)]["CBS"])))
        with np.errstate(divide="ignore"):
            log = np.log10([raw[str(m)]["CBS"][str(c)]["BLER"] for c in cbs])
        for ci in (0, 1, 4, 30, 84):        # grid CBS 24, 124, 424, 3024, 8424 bit
            for si in (0, 37, 101, 180):    # grid SNR -5, -1.3, 5.1, 13 dB
                c_bits, s_db = t.cbs_bits[ci], t.snr_db[si]
                # reference: separable linear interpolation, clamped at the simulated edges
                along_snr = np.array([np.interp(s_db, snr, row) for row in log])
                expected = 10 ** np.interp(min(c_bits, cbs[-1]), cbs, along_snr)
                if np.isfinite(log).all() or expected > 1e-6:
                    got = t.bler(m, c_bits, 10 ** (s_db / 10))
                    assert got == pytest.approx(expected, rel=1e-9), (m, c_bits, s_db)
    # the exact table entry where the grids meet: CBS 24, -5 dB
    assert t.bler(3, 24, 10 ** (-5 / 10)) == pytest.approx(raw["3"]["CBS"]["24"]["BLER"][0],
                                                           rel=1e-12)
    # nearest grid point: 0.04 dB off the grid gives the grid value
    assert t.bler(6, 500, 10 ** (5.14 / 10)) == t.bler(6, 524, 10 ** (5.1 / 10))


def test_bler_curves_fall_with_sinr_and_span_zero_to_one():
    for category, tables in (("pdsch", (1, 2, 3, 4)), ("pusch", (1, 2))):
        for i in tables:
            t = bler_table(category, i)
            tab = t.table[t.available]
            assert np.all((tab >= 0) & (tab <= 1))
            # non-increasing in SINR up to the Monte-Carlo noise of the simulated tables
            assert np.diff(tab, axis=-1).max() < 1e-3
            # every curve starts near 1 at -5 dB; the lowest MCS is error-free at 30 dB
            assert tab[..., 0].min() > 0.9 and tab[0, :, -1].max() < 1e-3
    with pytest.raises(ValueError, match="no BLER table for PUSCH MCS table 3"):
        BlerTable("pusch", 3)
    with pytest.raises(ValueError, match="MCS index outside"):
        bler_table("pdsch", 1).bler(29, 100, 1.0)


def test_tbler_from_bler():
    assert tbler_from_bler(0.1, 1) == pytest.approx(0.1, rel=1e-15)
    assert tbler_from_bler(0.1, 3) == pytest.approx(1 - 0.9**3, rel=1e-14)
    # no cancellation at small BLER: C * BLER to first order
    assert tbler_from_bler(1e-14, 10) == pytest.approx(1e-13, rel=1e-9)
    assert tbler_from_bler(1.0, 4) == 1.0 and tbler_from_bler(0.0, 4) == 0.0


# --- link adaptation ------------------------------------------------------------------------------

def test_inner_loop_picks_the_highest_mcs_under_the_target():
    avail = np.array([False, True, True, True, True])
    tbler = np.array([[np.nan, 0.01, 0.05, 0.3, 0.9],     # -> 2
                      [np.nan, 0.2, 0.3, 0.4, 0.5],       # none -> lowest available, 1
                      [np.nan, 0.0, 0.0, 0.0, 0.1]])      # -> 4 (<= target)
    np.testing.assert_array_equal(inner_loop_mcs(tbler, avail, 0.1), [2, 1, 4])
    phy = PhyAbstraction(num_re_for_tbs(20, 14, 12), 1)
    rng = np.random.default_rng(8)
    sinr = rng.exponential(size=(50, 240)) * 10 ** rng.uniform(-0.5, 2.5, (50, 1))
    mcs, eff, bler, tbler = select_mcs_inner_loop(phy, sinr, 0.1)
    for i in range(50):
        per_mcs = [phy.bler(phy.effective_sinr(sinr[i], m), m)[1] for m in range(29)]
        above = [m for m in range(mcs[i] + 1, 29) if phy.available[m]]
        assert all(per_mcs[m] > 0.1 for m in above)
        assert tbler[i] <= 0.1 or mcs[i] == 3
        assert tbler[i] == per_mcs[mcs[i]] and eff[i] == phy.effective_sinr(sinr[i], mcs[i])
    assert len(set(mcs)) > 10


def test_outer_loop_converges_to_the_target_and_conserves_its_steps():
    phy = PhyAbstraction(num_re_for_tbs(4, 14, 12), 1)
    rng = np.random.default_rng(9)
    T, R, K = 1000, 3, 24
    mean_db = np.array([4.0, 10.0, 16.0])
    sinr = rng.exponential(size=(T, R, K)) * 10 ** (mean_db[None, :, None] / 10)
    u = rng.random((T, R))
    target, up = 0.1, 1.0
    mcs, eff, bler, tbler, ack, off = select_mcs_outer_loop(phy, sinr, u, target, up)
    down = up * target / (1 - target)
    # the offset applied at the last transmission is the sum of all earlier steps (no clipping)
    assert np.all(np.abs(off) < 20)
    nack = (~ack[:-1]).sum(0)
    np.testing.assert_allclose(off[-1], up * nack - down * ack[:-1].sum(0), atol=1e-9)
    # hence the NACK rate approaches the target: |rate - target| <= (1 - target)|offset| / (up T)
    np.testing.assert_allclose(nack / (T - 1), target, atol=0.02)
    assert np.all(mcs[0] == select_mcs_inner_loop(phy, sinr[0], target)[0])   # first: inner loop
    # a gap in the schedule freezes the loop: same decisions as the schedule without the gap
    sched = np.ones((T, R), bool)
    sched[100:130] = False
    g = select_mcs_outer_loop(phy, sinr, u, target, up, scheduled=sched)
    keep = np.r_[0:100, 130:T]
    c = select_mcs_outer_loop(phy, sinr[keep], u[keep], target, up)
    np.testing.assert_array_equal(g[0][keep], c[0])
    np.testing.assert_array_equal(g[0][100:130], -1)
    assert np.isnan(g[1][100:130]).all() and not g[4][100:130].any()
