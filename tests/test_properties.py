"""Property tests (hypothesis) of the pure link-level science over extreme but legal inputs
(part of issue 16). Bounded and derandomized so CI is reproducible."""

import numpy as np
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from simart_pipeline.link import budget, eesm
from simart_pipeline.link.bler import bler_table

BOUNDED = settings(max_examples=60, deadline=None, derandomize=True)

sinr_db = st.floats(-50.0, 60.0)


@BOUNDED
@given(hnp.arrays(np.float64, st.integers(1, 64), elements=sinr_db))
def test_eesm_effective_sinr_finite_between_min_and_max_and_order_free(db):
    x = 10.0 ** (db / 10.0)
    beta = eesm.eesm_beta(1)[10]
    out = eesm.effective_sinr(x, beta)
    assert np.isfinite(out)
    assert x.min() * (1 - 1e-9) <= out <= x.max() * (1 + 1e-9)
    assert np.isclose(eesm.effective_sinr(x[::-1], beta), out, rtol=1e-12)


@BOUNDED
@given(st.integers(1, 16))
def test_eesm_no_used_element_is_nan(k):
    out = eesm.effective_sinr(np.ones(k), 1.0, where=np.zeros(k, bool))
    assert np.isnan(out)


@BOUNDED
@given(hnp.arrays(np.float64, st.integers(1, 32),
                  elements=st.one_of(st.floats(0.0, 1e6), st.just(0.0), st.floats(1e-30, 1e-25))))
def test_power_db_never_inf(x):
    out = budget.power_db(x)
    assert not np.any(np.isinf(out))
    assert np.array_equal(np.isnan(out), ~(x > 0))


@BOUNDED
@given(st.integers(0, 27), st.integers(24, 8448), sinr_db)
def test_bler_in_unit_interval(mcs, cbs, db):
    table = bler_table("pdsch", 1)
    out = table.bler(mcs, cbs, 10.0 ** (db / 10.0))
    if table.available[mcs]:
        assert 0.0 <= out <= 1.0


from simart_pipeline.ckm.moments import layers_from_moments, path_moments  # noqa: E402


@BOUNDED
@given(st.integers(0, 300), st.integers(0, 2**32 - 1))
def test_cell_layers_zero_one_many_paths_finite_nonnegative_and_order_free(n, seed):
    rng = np.random.default_rng(seed)
    power = 10.0 ** (rng.uniform(-300.0, 0.0, (1, n)) / 10.0)
    delay = rng.uniform(1e-11, 20e3 / 3e8, (1, n))
    valid = np.ones((1, n), bool)
    los = np.zeros((1, n), bool)
    ang = rng.uniform(-np.pi, np.pi, (1, n, 4))
    tau0 = np.min(delay, axis=-1) if n else np.zeros(1)
    a = layers_from_moments(path_moments(power, delay, valid, los, ang, tau0))
    perm = rng.permutation(n)
    b = layers_from_moments(path_moments(power[:, perm], delay[:, perm], valid, los,
                                         ang[:, perm], tau0))
    for key, v in a.items():
        v = np.asarray(v, dtype=np.float64)
        if n == 0:
            assert not a["has_path"][0]
            continue
        assert np.all(np.isfinite(v)), key
        assert np.allclose(v, np.asarray(b[key], np.float64), rtol=1e-9, atol=1e-12), key
    if n:
        assert a["rms_delay_spread_s"][0] >= 0.0
