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


@BOUNDED
@given(st.integers(1, 300), st.integers(1, 64), st.integers(0, 2**32 - 1))
def test_cell_moments_do_not_depend_on_the_invalid_paths_that_pad_a_row(n, pad, seed):
    """A PathSolver call pads every receiver's row of paths to the call's longest (with invalid
    entries), so a CKM cell's row length depends on the receivers traced beside it. The moments
    are the same bits with any padding after the valid paths (mutant: numpy's pairwise ``sum``,
    whose grouping follows the row length, moved the last bit of a cell's delay spread)."""
    from dataclasses import fields

    rng = np.random.default_rng(seed)
    m = n + pad
    power = 10.0 ** (rng.uniform(-200.0, 0.0, (2, m)) / 10.0)
    delay = rng.uniform(1e-9, 2e-6, (2, m))
    valid = np.zeros((2, m), bool)
    valid[:, :n] = True
    los = rng.random((2, m)) < 0.1
    ang = rng.uniform(-np.pi, np.pi, (2, m, 4))
    beam = rng.uniform(0.0, 1.0, (2, m, 8))
    tau0 = np.full(2, 1e-9)
    a = path_moments(power[:, :n], delay[:, :n], valid[:, :n], los[:, :n], ang[:, :n], tau0, beam[:, :n])
    b = path_moments(power, delay, valid, los, ang, tau0, beam)
    for f in fields(a):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


# --- channel frequency response, free space, noise, materials, grids, meshes, MCS -------------

FC_HZ = st.floats(1.01e8, 9.9e11)  # the config's carrier range (config.radio: 1e8 < f < 1e12)
DISTANCE_M = st.floats(0.01, 20_000.0)


@BOUNDED
@given(st.integers(0, 2000), st.integers(0, 2**32 - 1), FC_HZ)
def test_frequency_response_of_zero_one_or_thousands_of_paths_is_finite_and_order_free(n, seed, fc):
    from simart_pipeline.link.ofdm import channel_frequency_response

    rng = np.random.default_rng(seed)
    gain_db = rng.uniform(-300.0, 0.0, n)
    a = (10 ** (gain_db / 20) * np.exp(2j * np.pi * rng.random(n)))[None, None, :]
    tau = rng.uniform(0.0, 20_000.0 / 299_792_458.0, n)
    valid = rng.random(n) < 0.9
    tau[~valid] = -1.0  # the store's placeholder must never leak
    offsets = np.arange(-6, 6) * 30e3
    H = channel_frequency_response(a, tau, valid, fc, offsets)
    assert H.shape == (1, 1, 12) and np.all(np.isfinite(H))
    p = rng.permutation(n)
    np.testing.assert_allclose(channel_frequency_response(a[..., p], tau[p], valid[p], fc, offsets), H,
                               rtol=1e-9, atol=1e-9 * max(np.abs(a).sum(), 1e-300))
    # power: never more than the coherent sum of the valid paths' amplitudes
    assert np.all(np.abs(H) <= np.abs(a[0, 0, valid]).sum() * (1 + 1e-9) + 1e-300)


@BOUNDED
@given(DISTANCE_M, FC_HZ)
def test_a_milliradian_of_delay_at_20_km_keeps_its_phase(d, fc):
    """Absolute delays and phases are float64: the delay change that turns the carrier by 1 mrad
    (1.6e-16 s at 1 THz) does so at any range up to 20 km (in float32 a 67 us delay has 4 ps steps,
    ~2 rad at 100 GHz)."""
    from simart_pipeline.link.ofdm import channel_frequency_response

    tau = d / 299_792_458.0
    step_s = 1e-3 / (2 * np.pi * fc)
    h = [channel_frequency_response(np.ones((1, 1, 1)), [t], [True], fc, [0.0])[0, 0, 0] for t in (tau, tau + step_s)]
    assert abs(np.angle(h[0] / h[1]) - 1e-3) < 1e-5
    assert abs(abs(h[0]) - 1.0) < 1e-12  # one unit path: unit magnitude at every range


@BOUNDED
@given(DISTANCE_M, FC_HZ)
def test_free_space_gain_is_finite_and_falls_6_db_per_doubling(d, fc):
    from simart_pipeline.quality import free_space_gain_db

    g = free_space_gain_db(d, fc)
    assert np.isfinite(g)
    assert (g < 0) == (d > 299_792_458.0 / fc / (4 * np.pi))  # above 0 dB only closer than lambda / 4 pi
    assert abs(free_space_gain_db(2 * d, fc) - g + 20 * np.log10(2)) < 1e-9


@BOUNDED
@given(st.floats(1e3, 1e10), st.floats(1.0, 1000.0), st.floats(0.0, 20.0))
def test_thermal_noise_is_positive_and_proportional_to_bandwidth(bw, temp_k, nf_db):
    from simart_pipeline.link.ofdm import thermal_noise_power_w

    n = thermal_noise_power_w(bw, temp_k, nf_db)
    assert np.isfinite(n) and n > 0
    assert abs(thermal_noise_power_w(2 * bw, temp_k, nf_db) / n - 2.0) < 1e-12


@BOUNDED
@given(FC_HZ)
def test_materials_are_passive_across_the_carrier_range(fc):
    """Every radio material's permittivity at any carrier of the config's range: finite, real part
    at least 1 (no material is 'thinner' than vacuum), conductivity >= 0 (no gain)."""
    from simart_pipeline.radio import materials
    from simart_pipeline.vocabulary import CUSTOM_MATERIAL_NAMES

    for name in sorted(set(CUSTOM_MATERIAL_NAMES) | set(materials.ITU_P2040_TABLE3)):
        eps = materials.permittivity(name, fc) if name in CUSTOM_MATERIAL_NAMES else materials.itu_permittivity(name, fc)
        assert np.isfinite(eps.real) and np.isfinite(eps.imag), name
        assert eps.real >= 1.0 - 1e-12 and eps.imag <= 0.0, (name, fc, eps)


@BOUNDED
@given(st.floats(0.5, 50.0), st.integers(1, 40), st.integers(1, 40), st.integers(1, 4), st.integers(1, 4))
def test_ckm_tiles_cover_every_cell_once_down_to_one_cell_grids(cell, nx, ny, tx, ty):
    from simart_pipeline.ckm import grid
    from simart_pipeline.config import Ckm

    ckm = Ckm(center_m=(0.0, 0.0), size_m=(nx * cell, ny * cell), cell_size_m=cell, height_m=1.5, tiles=(tx, ty))
    rows, cols = ckm.shape
    seen = np.zeros((rows, cols), np.int64)
    for key in grid.scene_tiles(ckm):
        r, c = grid.tile_slices(ckm, key)
        assert r.stop > r.start and c.stop > c.start  # no empty tile is listed
        seen[r, c] += 1
    assert np.all(seen == 1)
    y, x = grid.cell_centres(ckm)
    assert len(y) == rows and len(x) == cols and np.all(np.diff(x) > 0) and np.all(np.diff(y) > 0)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.integers(0, 2**32 - 1), st.integers(0, 30), st.integers(0, 30))
def test_decimation_removes_degenerate_triangles_and_duplicate_vertices(seed, n_degenerate, n_duplicate):
    import trimesh

    from simart_pipeline.scene import simplify

    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(extents=rng.uniform(0.01, 200.0, 3))
    v, f = box.vertices.copy(), box.faces.copy()
    dup = rng.integers(0, len(v), n_duplicate)
    v = np.concatenate([v, v[dup]])  # duplicate vertices, each used by some of the faces of its original
    for k, j in enumerate(dup):
        use = (f == j) & (rng.random(f.shape) < 0.5)
        f[use] = len(box.vertices) + k
    i = rng.integers(0, len(v), (n_degenerate, 2))
    f = np.concatenate([f, np.stack([i[:, 0], i[:, 0], i[:, 1]], -1)])  # zero-area triangles
    uv, inv = simplify.merge_vertices(v, 1e-9 * max(1.0, float(np.ptp(v))))
    faces = inv[f]
    keep = ~simplify.degenerate_faces(uv, faces)
    mesh = simplify.decimate(trimesh.Trimesh(uv, faces[keep], process=False), "lossless")
    assert np.all(np.isfinite(mesh.vertices)) and len(mesh.faces) > 0
    assert not simplify.degenerate_faces(mesh.vertices, mesh.faces).any()
    assert np.isclose(mesh.area, box.area, rtol=1e-9)  # the surface is unchanged
    assert len(np.unique(mesh.vertices.round(9), axis=0)) == len(mesh.vertices)


@BOUNDED
@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 4), st.integers(1, 24)), elements=sinr_db))
def test_mcs_selection_bler_and_rate_are_bounded_for_any_sinr(db):
    from simart_pipeline.link.link_adaptation import select_mcs_inner_loop
    from simart_pipeline.link.phy_abstraction import PhyAbstraction

    phy = PhyAbstraction(num_re=12 * 12 * 4)
    mcs, eff, bler, tbler = select_mcs_inner_loop(phy, 10 ** (db / 10), 0.1)
    assert np.all((mcs >= 0) & (mcs < phy.num_mcs)) and np.all(phy.available[mcs])
    assert np.all(np.isfinite(eff)) and np.all(eff > 0)
    for x in (bler, tbler):
        assert np.all((x >= 0) & (x <= 1))
    # more SINR on every element never lowers the chosen MCS
    mcs_up = select_mcs_inner_loop(phy, 10 ** ((db + 3.0) / 10), 0.1)[0]
    assert np.all(mcs_up >= mcs)


@BOUNDED
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_station_sinr_nonnegative_finite_and_order_invariant(seed, n_bs):
    from simart_pipeline.link.budget import power_db, station_sinr

    rng = np.random.default_rng(seed)
    gain = 10 ** (rng.uniform(-300, 0, (n_bs, 5)) / 10) * (rng.random((n_bs, 5)) < 0.8)  # 0: no path
    p_re = 10 ** ((rng.uniform(-10, 50) - 30) / 10) / 1000
    noise = 10 ** ((-174 + 10 * np.log10(30e3) + 7 - 30) / 10)
    sinr = station_sinr(p_re * gain, p_re * gain * 0.5, noise)
    assert np.all(np.isfinite(sinr)) and np.all(sinr >= 0)
    perm = rng.permutation(n_bs)
    # one dominant station must not turn the others' interference into rounding noise (total - own did)
    np.testing.assert_allclose(station_sinr(p_re * gain[perm], p_re * gain[perm] * 0.5, noise), sinr[perm],
                               rtol=1e-12)
    db = power_db(gain)
    assert np.array_equal(np.isnan(db), gain <= 0) and np.all(db[gain > 0] >= -300 - 1e-9)
