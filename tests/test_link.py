"""Link level: OFDM response, DFT codebook (sign checked against Sionna RT), SINR with interference,
serving cell, masking, and the KPI store (PHY abstraction pieces: tests/test_link_phy.py)."""

from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from pydantic import ValidationError
from scipy.constants import Boltzmann, speed_of_light

from simart_pipeline.config import Array, BaseStation, Codebook, Link, Ofdm, load_scene_config
from simart_pipeline.link.beams import (beam_gains, dft_codebook, load_codebook,
                                        rotation_local_to_world, scene_codebook_weights,
                                        unit_vector, upa_steering_vectors, world_to_local)
from simart_pipeline.link.kpis import compute_kpis, dbm_to_w
from simart_pipeline.link.ofdm import (allocated_subcarriers, channel_frequency_response,
                                       slot_duration_s, subcarrier_offsets_hz,
                                       thermal_noise_power_w)
from simart_pipeline.link.tbs import transport_block
from simart_pipeline.stores import check_finite, open_store, write_store

ROOT = Path(__file__).resolve().parents[1]
FC = 3.5e9
LAMBDA = speed_of_light / FC
K_SMALL = 48  # 4 resource blocks: enough subcarriers for the KPI tests, fast


def upa_positions(rows, cols, spacing_wavelengths=0.5):
    """[rows*cols, 3] positions of a Sionna-style UPA (y-z plane, column major, z descending)."""
    d = spacing_wavelengths * LAMBDA
    return np.array([(0.0, (c - (cols - 1) / 2) * d, ((rows - 1) / 2 - r) * d)
                     for c in range(cols) for r in range(rows)])


def plane_wave(direction_local, alpha, rows=8, cols=8):
    """Coefficients [N] of one path leaving along ``direction_local`` (Sionna sign convention)."""
    return alpha * np.exp(1j * 2 * np.pi / LAMBDA * upa_positions(rows, cols) @ direction_local)


def make_cfg(rows, cols, num_bs, oversampling=1, num_resource_blocks=K_SMALL // 12,
             visible_only=False, **link):
    base = load_scene_config(ROOT / "scenes" / "demo")
    arr = Array(rows=rows, cols=cols, spacing_wavelengths=0.5, pattern="iso")
    bss = tuple(BaseStation(name=f"bs{i}", position_m=(0.0, 0.0, 10.0), array=arr)
                for i in range(num_bs))
    return base.model_copy(update=dict(
        base_stations=bss, codebook=Codebook(oversampling=oversampling, visible_only=visible_only),
        ofdm=Ofdm(carrier_frequency_hz=FC, numerology_mu=1,
                  num_resource_blocks=num_resource_blocks), link=Link(**link)))


def make_cirs(a, tau_s, valid, tx, rx, power_dbm, tx_rows=8, tx_cols=8, dtype=np.complex64,
              inside=None, near=None):
    """A ``cirs`` dataset per the data contract from ``a [T, L, r, n, P]``, ``tau_s``/``valid``
    ``[T, L, P]``: invalid entries hold a = 0 and tau_s = -1, as the tracer writes them.
    ``dtype=complex128`` keeps exact coefficients for 1e-9 link-budget checks."""
    a = np.asarray(a)
    T, L, r, n, P = a.shape
    valid = np.asarray(valid, bool)
    none = np.zeros((T, L), bool)
    return xr.Dataset(
        dict(a=(("time", "link", "rx_ant", "tx_ant", "path"),
                np.where(valid[:, :, None, None], a, 0).astype(dtype)),
             tau_s=(("time", "link", "path"), np.where(valid, tau_s, -1.0)),
             valid=(("time", "link", "path"), valid),
             los=(("time", "link", "path"), valid),
             num_valid_paths=(("time", "link"), valid.sum(-1).astype(np.int32)),
             link_no_path=(("time", "link"), ~valid.any(-1)),
             link_rx_inside_building=(("time", "link"), none if inside is None else inside),
             link_rx_near_tx=(("time", "link"), none if near is None else near),
             tx_power_dbm=("link", np.broadcast_to(np.asarray(power_dbm, float), (L,)).copy()),
             tx_ant_position_m=(("tx_ant", "axis"), upa_positions(tx_rows, tx_cols)),
             rx_ant_position_m=(("rx_ant", "axis"), upa_positions(1, r))),
        coords=dict(time=np.arange(T, dtype=np.int64) * 100_000_000, link=np.arange(L),
                    tx=("link", list(tx)), rx=("link", list(rx)), path=np.arange(P),
                    axis=["x", "y", "z"]),
        attrs=dict(carrier_frequency_hz=FC))


def noise_per_re(cfg):
    return Boltzmann * 290.0 * cfg.ofdm.subcarrier_spacing_hz * 10 ** (7.0 / 10)


def lin(db):
    return 10 ** (np.asarray(db) / 10)


# --- OFDM -----------------------------------------------------------------------------------------

def test_subcarrier_offsets_and_thermal_noise():
    ofdm = Ofdm(numerology_mu=1, num_resource_blocks=51)
    f = subcarrier_offsets_hz(ofdm)
    assert f.dtype == np.float64 and f.shape == (612,)
    np.testing.assert_allclose(np.diff(f), 30e3, rtol=0, atol=1e-6)
    assert f.mean() == pytest.approx(0.0, abs=1e-6) and f[0] == -f[-1] == -305.5 * 30e3
    # k_B T at 290 K is -173.98 dBm/Hz; + 7 dB NF + 10 log10(30 kHz) = 44.77 dB.
    assert 10 * np.log10(thermal_noise_power_w(1.0, 290.0, 0.0) * 1e3) == pytest.approx(
        -173.975, abs=1e-3)
    assert 10 * np.log10(thermal_noise_power_w(30e3, 290.0, 7.0) * 1e3) == pytest.approx(
        -173.975 + 7 + 44.771, abs=1e-3)


def test_numerology_slots_cyclic_prefix_and_allocation():
    assert [slot_duration_s(Ofdm(numerology_mu=mu)) for mu in (0, 1, 3)] == [1e-3, 0.5e-3,
                                                                            0.125e-3]
    Ofdm(numerology_mu=2, cyclic_prefix="extended", num_ofdm_symbols=12)
    with pytest.raises(ValidationError, match="only for numerology_mu 2"):
        Ofdm(numerology_mu=1, cyclic_prefix="extended", num_ofdm_symbols=12)
    with pytest.raises(ValidationError, match="at most 12"):
        Ofdm(numerology_mu=2, cyclic_prefix="extended", num_ofdm_symbols=14)
    ofdm = Ofdm(num_resource_blocks=10)
    np.testing.assert_array_equal(allocated_subcarriers(ofdm, Link()), np.arange(120))
    np.testing.assert_array_equal(
        allocated_subcarriers(ofdm, Link(first_resource_block=2, num_allocated_resource_blocks=3)),
        np.arange(24, 60))
    with pytest.raises(ValueError, match="exceed the carrier"):
        allocated_subcarriers(ofdm, Link(first_resource_block=8, num_allocated_resource_blocks=3))


def test_single_path_response_has_constant_magnitude_and_linear_phase():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(2, 3, 1)) + 1j * rng.normal(size=(2, 3, 1))
    tau = np.array([1.2345678e-6])
    f = subcarrier_offsets_hz(Ofdm(num_resource_blocks=51))
    H = channel_frequency_response(a, tau, [True], FC, f)
    assert H.shape == (2, 3, 612) and H.dtype == np.complex128
    np.testing.assert_allclose(np.abs(H), np.abs(a) * np.ones(612), rtol=1e-12)
    expected = a * np.exp(-2j * np.pi * (FC + f) * tau[0])
    # float64 phase of 2 pi f tau ~ 3e4 rad is good to ~1e-11 rad
    np.testing.assert_allclose(H, expected, rtol=1e-10, atol=0)
    slope = np.diff(np.unwrap(np.angle(H[0, 0] / a[0, 0, 0])))
    np.testing.assert_allclose(slope, -2 * np.pi * 30e3 * tau[0], rtol=1e-9)


def test_two_path_power_sum_rule():
    f = subcarrier_offsets_hz(Ofdm(num_resource_blocks=51))
    a = np.array([0.8, 0.6j])
    # delay difference of exactly 10 cycles across the band: the cross term averages to 0 exactly
    dtau = 10 / (612 * 30e3)
    H = channel_frequency_response(a, np.array([0.7e-6, 0.7e-6 + dtau]), [True, True], FC, f)
    assert np.mean(np.abs(H) ** 2) == pytest.approx(1.0, rel=1e-12)
    # any delay difference spanning many cycles: approximately the sum of the path gains
    H = channel_frequency_response(a, np.array([0.7e-6, 0.7e-6 + 3.3e-6]), [True, True], FC, f)
    assert np.mean(np.abs(H) ** 2) == pytest.approx(1.0, rel=0.02)
    assert np.ptp(np.abs(H) ** 2) > 1.0  # while the response itself is frequency selective


def test_invalid_paths_contribute_exactly_zero():
    rng = np.random.default_rng(2)
    f = subcarrier_offsets_hz(Ofdm(num_resource_blocks=4))
    a = rng.normal(size=(3, 2, 1, 4, 3)) + 1j * rng.normal(size=(3, 2, 1, 4, 3))
    tau = rng.uniform(1e-7, 2e-6, size=(3, 2, 3))
    valid = np.ones((3, 2, 3), bool)
    H_ref = channel_frequency_response(a, tau, valid, FC, f)
    # append an invalid path (placeholders a = 7, tau = -1 must not leak), and invalidate all of
    # link 1 at t = 2
    a2 = np.concatenate([a, np.full(a.shape[:-1] + (1,), 7.0)], axis=-1)
    tau2 = np.concatenate([tau, np.full(tau.shape[:-1] + (1,), -1.0)], axis=-1)
    valid2 = np.concatenate([valid, np.zeros(valid.shape[:-1] + (1,), bool)], axis=-1)
    H = channel_frequency_response(a2, tau2, valid2, FC, f)
    assert H.shape == (3, 2, 1, 4, K_SMALL)
    np.testing.assert_array_equal(H, H_ref)
    valid2[2, 1] = False
    tau2[2, 1] = np.nan
    H = channel_frequency_response(a2, tau2, valid2, FC, f)
    assert not np.isnan(H).any()
    assert np.all(H[2, 1] == 0) and np.array_equal(H[:2], H_ref[:2])


# --- codebook -------------------------------------------------------------------------------------

def test_codebook_is_a_unitary_dft_basis_with_64_beams():
    cb = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8, oversampling=1)
    W = cb.weights
    # 8x8 grid u = -1 + (2i+1)/8 per axis; 12 corner beams have u_y^2 + u_z^2 > 1
    assert W.shape == (64, 64) and cb.visible.sum() == 52
    grid = -1 + (2 * np.arange(8) + 1) / 8
    assert np.all(np.isin(np.round(cb.direction_cosines, 12), np.round(grid, 12)))
    np.testing.assert_allclose(W @ W.conj().T, np.eye(64), atol=1e-12)
    D = cb.directions
    assert np.isnan(D[~cb.visible]).all()
    np.testing.assert_allclose(np.linalg.norm(D[cb.visible], axis=1), 1, rtol=1e-12)
    # weights are the conjugate steering vectors of the beam directions
    vis = np.flatnonzero(cb.visible)
    np.testing.assert_allclose(W[vis], upa_steering_vectors(upa_positions(8, 8), D[vis],
                                                            LAMBDA).conj() / 8, atol=1e-12)
    np.testing.assert_allclose(upa_steering_vectors(upa_positions(8, 8), D[vis[3]], LAMBDA),
                               plane_wave(D[vis[3]], 1.0), atol=1e-12)
    # a plane wave along beam b's direction: gain N on beam b, nothing on the others
    H = np.stack([plane_wave(D[b], 1.0) for b in vis[[0, 20, 51]]])[:, None, :, None]
    g = beam_gains(H, W)
    np.testing.assert_allclose(g[[0, 1, 2], vis[[0, 20, 51]]], 64, rtol=1e-12)
    assert np.sort(g, axis=1)[:, -2].max() < 1e-20

    vo = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8, visible_only=True)
    assert vo.weights.shape == (52, 64) and vo.visible.all()
    np.testing.assert_array_equal(vo.weights, W[vis])
    Wo = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8, oversampling=2).weights
    np.testing.assert_allclose(np.linalg.norm(Wo, axis=1), 1, rtol=1e-12)
    assert Wo.shape[0] == 256 and np.abs(Wo @ Wo.conj().T - np.eye(len(Wo))).max() > 0.1


def test_codebook_rows_and_cols_map_to_z_and_y():
    pos = upa_positions(2, 4)   # 2 rows along z, 4 cols along y
    cb = dft_codebook(pos, LAMBDA, 2, 4)
    D = cb.directions
    assert sorted(set(np.round(D[:, 1], 9))) == pytest.approx([-0.75, -0.25, 0.25, 0.75])
    assert sorted(set(np.round(D[:, 2], 9))) == pytest.approx([-0.5, 0.5])
    H = (np.exp(1j * 2 * np.pi / LAMBDA * pos @ D.T).T)[:, None, :, None]  # [B, 1, 8, 1]
    np.testing.assert_allclose(np.diag(beam_gains(H, cb.weights)), 8, rtol=1e-12)
    with pytest.raises(ValueError):
        dft_codebook(pos, LAMBDA, 4, 2)


def test_codebook_file(tmp_path):
    W = dft_codebook(upa_positions(2, 2), LAMBDA, 2, 2).weights[:3]
    np.save(tmp_path / "cb.npy", W)
    np.testing.assert_array_equal(load_codebook(tmp_path / "cb.npy", 4), W)
    with pytest.raises(ValueError, match=r"cb.npy: codebook must be \[num_beams, 8\]"):
        load_codebook(tmp_path / "cb.npy", 8)
    np.save(tmp_path / "bad.npy", 2 * W)
    with pytest.raises(ValueError, match="bad.npy: precoders must have unit norm"):
        load_codebook(tmp_path / "bad.npy", 4)
    (tmp_path / "junk.npy").write_text("not numpy")
    with pytest.raises(ValueError, match="junk.npy: not a readable"):
        load_codebook(tmp_path / "junk.npy", 4)
    # the scene's codebook, as the kpis and CKM stages share it
    cfg = make_cfg(2, 2, 1, visible_only=True)
    np.testing.assert_array_equal(scene_codebook_weights(cfg, upa_positions(2, 2)),
                                  dft_codebook(upa_positions(2, 2), LAMBDA, 2, 2,
                                               visible_only=True).weights)
    cfg = cfg.model_copy(update=dict(codebook=Codebook(path="cb.npy")))
    np.testing.assert_array_equal(scene_codebook_weights(cfg, upa_positions(2, 2), tmp_path), W)
    with pytest.raises(ValueError, match="scene directory is needed"):
        scene_codebook_weights(cfg, upa_positions(2, 2))
    cirs = make_cirs(plane_wave([1.0, 0, 0], 1e-5, 2, 2)[None, None, None, :, None],
                     np.full((1, 1, 1), 1e-7), np.ones((1, 1, 1), bool), ["bs0"], ["uav0"], 30.0,
                     tx_rows=2, tx_cols=2)
    k = compute_kpis(cirs, cfg, codebook_weights=W)
    assert k.sizes["beam"] == 3 and "file codebook.path=cb.npy" in k.attrs["codebook"]


def test_rotation_helpers():
    R = rotation_local_to_world([np.pi / 2, 0, 0])   # yaw 90 deg: local x -> world y
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    R = rotation_local_to_world([0, np.pi / 2, 0])   # pitch 90 deg about y: local x -> world -z
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 0, -1], atol=1e-15)
    ori = [0.4, -0.3, 0.2]
    d = unit_vector(0.9, 2.1)
    np.testing.assert_allclose(rotation_local_to_world(ori) @ world_to_local(d, ori), d, atol=1e-15)


def test_dft_beam_towards_los_wins_in_sionna():
    """Sign convention of Sionna RT's synthetic array: a_n = a_0 exp(+j 2 pi/lambda p_n . d)."""
    import sionna.rt as rt   # a core dependency: a missing install must fail, not skip

    scene = rt.load_scene()
    scene.frequency = FC
    scene.tx_array = rt.PlanarArray(num_rows=8, num_cols=8, vertical_spacing=0.5,
                                    horizontal_spacing=0.5, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    orientation = [0.4, -0.3, 0.2]
    scene.add(rt.Transmitter("tx", position=[1.0, 2.0, 3.0], orientation=orientation))
    wavelength = np.array(scene.wavelength, dtype=np.float64).item()
    pos = np.array(scene.tx_array.positions(scene.wavelength), dtype=np.float64).T  # [64, 3]
    cb = dft_codebook(pos, wavelength, 8, 8)
    D = cb.directions
    R = rotation_local_to_world(orientation)
    targets = [3, 17, 30, 44, 50]   # off-boresight visible beams: a wrong sign picks the mirror
    assert cb.visible[targets].all()
    rng = np.random.default_rng(3)
    for i, b in enumerate(targets):
        d = D[b] + rng.uniform(-0.03, 0.03, 3)
        scene.add(rt.Receiver(f"rx{i}", position=(np.array([1.0, 2.0, 3.0])
                                                  + 60 * R @ (d / np.linalg.norm(d))).tolist()))
    paths = rt.PathSolver()(scene, max_depth=0, synthetic_array=True)
    a = np.array(paths.a[0], np.float64) + 1j * np.array(paths.a[1], np.float64)  # [rx,1,tx,64,p]
    tau = np.array(paths.tau, np.float64)[:, 0]
    valid = np.array(paths.valid, bool)[:, 0]
    los_world = unit_vector(np.array(paths.theta_t)[:, 0, 0], np.array(paths.phi_t)[:, 0, 0])
    los_local = world_to_local(los_world, orientation)                          # [rx, 3]
    assert valid[:, 0].all()
    # phase across the array: +k p_n . d (LoS has phase 0 at the array centre)
    np.testing.assert_allclose(np.angle(a[:, 0, 0, :, 0] * np.exp(
        -1j * 2 * np.pi / wavelength * los_local @ pos.T)), 0, atol=1e-3)
    H = channel_frequency_response(a[:, :, 0], tau, valid, FC,
                                   subcarrier_offsets_hz(Ofdm(num_resource_blocks=4)))
    gains = beam_gains(H, cb.weights)                                            # [rx, B]
    closest = np.argmax(np.where(cb.visible, los_local @ np.nan_to_num(D).T, -np.inf), axis=1)
    np.testing.assert_array_equal(closest, targets)
    np.testing.assert_array_equal(np.argmax(gains, axis=1), closest)


# --- SINR, serving cell, masking ------------------------------------------------------------------

def test_single_path_sinr_equals_link_budget_snr():
    cfg = make_cfg(1, 1, 1)
    alpha = 3e-5 * np.exp(0.7j)
    cirs = make_cirs(np.full((2, 1, 1, 1, 1), alpha), np.full((2, 1, 1), 0.4e-6),
                     np.ones((2, 1, 1), bool), ["bs0"], ["uav0"], 30.0, tx_rows=1, tx_cols=1)
    k = compute_kpis(cirs, cfg)
    stored = abs(complex(cirs["a"].values.ravel()[0])) ** 2   # complex64 as stored
    # link budget: P_tx / K per resource element times the path gain over the noise per RE
    snr = dbm_to_w(30.0) / K_SMALL * stored / noise_per_re(cfg)
    np.testing.assert_allclose(lin(k["sinr_per_subcarrier_db"].values), snr, rtol=1e-9)
    np.testing.assert_allclose(lin(k["sinr_db"].values), snr, rtol=1e-9)
    np.testing.assert_allclose(lin(k["snr_db"].values), snr, rtol=1e-9)
    # EESM of a flat SINR is that SINR, whatever the MCS's beta
    np.testing.assert_allclose(lin(k["effective_sinr_db"].values), snr, rtol=1e-9)
    np.testing.assert_allclose(k["rx_power_per_re_dbm"].values,
                               10 * np.log10(1e3 * dbm_to_w(30.0) / K_SMALL * stored), rtol=1e-12)
    np.testing.assert_allclose(k["shannon_rate_bps"].values,
                               np.log2(1 + snr) * K_SMALL * 30e3, rtol=1e-9)
    assert np.isnan(k["interference_power_per_re_dbm"].values).all()   # no other station


def test_planar_array_link_budget_has_full_array_gain_and_los_beam_wins():
    cfg = make_cfg(8, 8, 1)
    cb = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8)
    alpha = 2e-6
    a = plane_wave(cb.directions[37], alpha)[None, None, None, :, None]
    cirs = make_cirs(a, np.full((1, 1, 1), 1.1e-6), np.ones((1, 1, 1), bool), ["bs0"], ["uav0"],
                     40.0, dtype=np.complex128)
    k = compute_kpis(cirs, cfg)
    snr = dbm_to_w(40.0) / K_SMALL * alpha**2 * 64 / noise_per_re(cfg)
    assert k["best_beam"].item() == 37 and k["serving_beam"].item() == 37
    assert k["beam_sinr_db"].argmax("beam").item() == 37
    assert k["best_beam_gain_db"].item() == pytest.approx(10 * np.log10(64 * alpha**2), rel=1e-12)
    np.testing.assert_allclose(lin(k["sinr_per_subcarrier_db"].values), snr, rtol=1e-9)
    np.testing.assert_allclose(lin(k["sinr_db"].values), snr, rtol=1e-9)
    np.testing.assert_allclose(lin(k["best_beam_sinr_db"].values), snr, rtol=1e-9)


@pytest.mark.parametrize("visible_only", [False, True])
def test_equal_interferers_give_the_expected_sinr(visible_only):
    cfg = make_cfg(8, 8, 3, visible_only=visible_only)
    cb = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8, visible_only=visible_only)
    D, B = cb.directions, cb.weights.shape[0]
    a0, a1 = 4e-6, 1.5e-6
    a = np.stack([plane_wave(D[10], a0), plane_wave(D[25], a1), plane_wave(D[41], a1)])
    cirs = make_cirs(a[None, :, None, :, None], np.array([0.3e-6, 0.9e-6, 1.7e-6])[None, :, None],
                     np.ones((1, 3, 1), bool), ["bs0", "bs1", "bs2"], ["uav0"] * 3, 30.0,
                     dtype=np.complex128)
    k = compute_kpis(cirs, cfg)
    p_re, N = dbm_to_w(30.0) / K_SMALL, noise_per_re(cfg)
    S = p_re * 64 * a0**2
    # a beam drawn uniformly among B orthogonal beams catches the plane wave with probability 1/B
    # (gain 64): with all 64 beams (a unitary basis) the expected interference is p a1^2
    I = p_re * 64 * a1**2 / B
    assert k["serving_tx"].item() == "bs0" and k["serving_link"].item() == 0
    np.testing.assert_allclose(lin(k["sinr_per_subcarrier_db"].values), S / (2 * I + N),
                               rtol=1e-9)
    np.testing.assert_allclose(lin(k["sinr_db"].values), S / (2 * I + N), rtol=1e-9)
    np.testing.assert_allclose(lin(k["snr_db"].values), S / N, rtol=1e-9)
    np.testing.assert_allclose(lin(k["interference_power_per_re_dbm"].values) / 1e3, 2 * I,
                               rtol=1e-9)


def test_interference_is_taken_after_the_mrc_combiner():
    cfg = make_cfg(1, 1, 2)
    alpha, beta = 5e-5, 3e-5
    p_re, N = dbm_to_w(30.0) / K_SMALL, noise_per_re(cfg)
    for interferer, expected_i in (([0, beta], 0.0), ([beta, 0], p_re * beta**2)):
        a = np.array([[alpha, 0], interferer])[None, :, :, None, None]   # [1, 2, r=2, 1, 1]
        cirs = make_cirs(a, np.full((1, 2, 1), 0.5e-6), np.ones((1, 2, 1), bool),
                         ["bs0", "bs1"], ["uav0", "uav0"], 30.0, tx_rows=1, tx_cols=1,
                         dtype=np.complex128)
        k = compute_kpis(cirs, cfg)
        np.testing.assert_allclose(lin(k["sinr_db"].values),
                                   p_re * alpha**2 / (expected_i + N), rtol=1e-9)


def test_best_beam_maximises_sinr_not_gain_with_two_receive_antennas():
    """Two rx antennas: beam 0 is stronger but shares its combiner with the interferer; beam 1 is
    weaker and orthogonal to it, so it wins on SINR."""
    cfg = make_cfg(1, 2, 2)
    cb = dft_codebook(upa_positions(1, 2), LAMBDA, 1, 2)
    W = cb.weights                                  # 2 orthogonal beams of a 2-element array
    g0, g1, gi = 1e-4, 0.6e-4, 3e-4
    # serving channel: beam 0 -> rx antenna 0, beam 1 -> rx antenna 1 (H = sum_b y_b w_b^H)
    Hs = g0 * np.outer([1, 0], W[0].conj()) + g1 * np.outer([0, 1], W[1].conj())
    Hi = gi * np.outer([1, 0], [1, 0])              # interferer: only onto rx antenna 0
    a = np.stack([Hs, Hi])[None, :, :, :, None]      # [1, 2, r=2, n=2, 1]
    cirs = make_cirs(a, np.full((1, 2, 1), 0.5e-6), np.ones((1, 2, 1), bool), ["bs0", "bs1"],
                     ["uav0", "uav0"], 30.0, tx_rows=1, tx_cols=2, dtype=np.complex128)
    k = compute_kpis(cirs, cfg)
    p_re, N = dbm_to_w(30.0) / K_SMALL, noise_per_re(cfg)
    gains = lin(k["beam_gain_db"].values[0, 0])
    np.testing.assert_allclose(gains, [g0**2, g1**2], rtol=1e-9)
    i_beam0 = p_re * gi**2 / 2                       # uniform over 2 beams, combiner on antenna 0
    np.testing.assert_allclose(lin(k["beam_sinr_db"].values[0, 0]),
                               [p_re * g0**2 / (i_beam0 + N), p_re * g1**2 / N], rtol=1e-9)
    assert k["serving_link"].item() == 0 and k["serving_beam"].item() == 1


def test_serving_cell_is_the_strongest_station_per_receiver():
    cfg = make_cfg(1, 1, 2)
    # two platforms; uav0 hears bs1 better, uav1 hears bs0 better; links base station major
    amp = np.array([1e-5, 3e-5, 4e-5, 2e-5])           # (bs0,uav0) (bs0,uav1) (bs1,uav0) ...
    cirs = make_cirs(amp[None, :, None, None, None], np.full((1, 4, 1), 0.5e-6),
                     np.ones((1, 4, 1), bool), ["bs0", "bs0", "bs1", "bs1"],
                     ["uav0", "uav1", "uav0", "uav1"], 30.0, tx_rows=1, tx_cols=1,
                     dtype=np.complex128)
    k = compute_kpis(cirs, cfg)
    assert list(k["platform"].values) == ["uav0", "uav1"]
    np.testing.assert_array_equal(k["serving_tx"].values, [["bs1", "bs0"]])
    np.testing.assert_array_equal(k["serving_link"].values, [[2, 1]])
    p_re, N = dbm_to_w(30.0) / K_SMALL, noise_per_re(cfg)
    np.testing.assert_allclose(lin(k["sinr_db"].values),
                               [[p_re * 16e-10 / (p_re * 1e-10 + N),
                                 p_re * 9e-10 / (p_re * 4e-10 + N)]], rtol=1e-9)


def test_no_path_flagged_receivers_and_the_store(tmp_path):
    cfg = make_cfg(8, 8, 2)
    cb = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8)
    T, L = 3, 6
    a = np.zeros((T, L, 1, 64, 2), complex)
    vis = np.flatnonzero(cb.visible)
    for link in (0, 3, 4, 5):
        a[:, link, 0, :, 0] = plane_wave(cb.directions[vis[5 + link]], 1e-5)
    valid = np.zeros((T, L, 2), bool)
    valid[:, [0, 3, 4, 5], 0] = True
    inside = np.zeros((T, L), bool)
    near = np.zeros((T, L), bool)
    inside[1, [1, 4]] = True      # uav1 inside a building at t = 1 (its links to bs0 and bs1)
    near[2, 5] = True             # uav2 within 1 cm of bs1 at t = 2
    # links: bs0 -> uav0, uav1, uav2; bs1 -> uav0, uav1, uav2
    cirs = make_cirs(a, np.full((T, L, 2), 0.2e-6), valid, ["bs0"] * 3 + ["bs1"] * 3,
                     ["uav0", "uav1", "uav2"] * 2, 30.0, inside=inside, near=near)
    k = compute_kpis(cirs, cfg)
    ok = k["link_kpis_valid"].values
    assert ok.tolist() == [[1, 0, 0, 1, 1, 1], [1, 0, 0, 1, 0, 1], [1, 0, 0, 1, 1, 0]]
    for name in ("beam_gain_db", "beam_sinr_db", "best_beam_gain_db", "rx_power_per_re_dbm"):
        v = k[name].values
        assert "nan_means" in k[name].attrs
        assert np.isnan(v[~ok]).all() and np.isfinite(v[ok]).all()
    assert (k["best_beam"].values[~ok] == -1).all()
    served = k["rx_served"].values
    assert served.tolist() == [[True] * 3, [True, False, True], [True, True, False]]
    np.testing.assert_array_equal(k["rx_inside_building"].values[:, 1], [False, True, False])
    np.testing.assert_array_equal(k["rx_near_tx"].values[:, 2], [False, False, True])
    masked = k["rx_inside_building"].values | k["rx_near_tx"].values
    for name in ("sinr_db", "snr_db", "effective_sinr_db", "bler", "tbler", "code_rate"):
        assert np.isnan(k[name].values[~served]).all() and np.isfinite(k[name].values[served]).all()
    for name in ("mcs_index", "tbs_bits", "serving_beam", "serving_link", "modulation_order"):
        assert (k[name].values[~served] == -1).all() and (k[name].values[served] >= 0).all()
    for name in ("mcs_rate_bps", "shannon_rate_bps", "shannon_spectral_efficiency_bpshz"):
        assert np.isnan(k[name].values[masked]).all() and (k[name].values[~masked] > 0).all()
    assert not k["harq_ack"].values[~served].any()
    # uav1 is served by bs1 alone (no path from bs0): no interference, SINR = SNR
    np.testing.assert_array_equal(k["sinr_db"].values[[0, 2], 1], k["snr_db"].values[[0, 2], 1])
    # a receiver with no path at all is unserved with zero rates (not masked)
    cirs0 = make_cirs(np.zeros((1, 2, 1, 64, 1)), np.zeros((1, 2, 1)), np.zeros((1, 2, 1), bool),
                      ["bs0", "bs1"], ["uav0"] * 2, 30.0)
    k0 = compute_kpis(cirs0, cfg)
    assert not k0["rx_served"].any() and k0["mcs_rate_bps"].item() == 0.0
    assert k0["shannon_rate_bps"].item() == 0.0 and np.isnan(k0["sinr_db"].item())

    for name, var in k.variables.items():
        assert "long_name" in var.attrs, name
        if var.dtype.kind in "fiu":
            assert "units" in var.attrs, name
        if var.dtype.kind == "f":
            assert not np.isinf(var.values).any(), name
    for name, var in k.data_vars.items():   # every numeric KPI says how it is defined
        if var.dtype.kind in "fiu":
            assert var.attrs["definition"], name
    check_finite(k)
    back = open_store(write_store(k, tmp_path / "kpis.zarr")).load()
    # uav0: equal stations, the lowest link wins the tie; uav1, uav2: only bs1 has a path
    assert list(back["serving_tx"].values[0]) == ["bs0", "bs1", "bs1"]
    np.testing.assert_array_equal(back["time"].values, cirs["time"].values)
    xr.testing.assert_identical(back.drop_vars("serving_tx"), k.drop_vars("serving_tx"))


def test_bad_cirs_get_clear_errors():
    cfg = make_cfg(1, 1, 1)
    good = make_cirs(np.full((1, 1, 1, 1, 1), 1e-5), np.full((1, 1, 1), 1e-7),
                     np.ones((1, 1, 1), bool), ["bs0"], ["uav0"], 30.0, tx_rows=1, tx_cols=1)
    with pytest.raises(ValueError, match="cirs/x.zarr: .*'link_rx_near_tx' missing"):
        compute_kpis(good.drop_vars("link_rx_near_tx"), cfg, source="cirs/x.zarr")
    bad = good.copy(deep=True)
    bad["link_no_path"][:] = True
    with pytest.raises(ValueError, match="link_no_path disagrees with valid at 1"):
        compute_kpis(bad, cfg)
    bad = good.copy(deep=True)
    bad["tau_s"][:] = np.nan
    with pytest.raises(ValueError, match="valid paths with a non-finite or negative tau_s"):
        compute_kpis(bad, cfg)
    bad = good.copy(deep=True)
    bad.attrs["carrier_frequency_hz"] = 28e9
    with pytest.raises(ValueError, match="differs from the config's ofdm.carrier_frequency_hz"):
        compute_kpis(bad, cfg)
    with pytest.raises(ValueError, match="exceed the carrier's ofdm.num_resource_blocks"):
        compute_kpis(good, make_cfg(1, 1, 1, first_resource_block=4))


def test_invalid_path_placeholders_change_nothing():
    cfg = make_cfg(8, 8, 2)
    rng = np.random.default_rng(7)
    shape = (3, 2, 1, 64, 4)
    a = (rng.normal(size=shape) + 1j * rng.normal(size=shape)) * 1e-6
    tau = rng.uniform(1e-7, 2e-6, (3, 2, 4))
    ref = compute_kpis(make_cirs(a, tau, np.ones((3, 2, 4), bool), ["bs0", "bs1"],
                                 ["uav0"] * 2, 30.0), cfg)
    a6 = np.concatenate([a, rng.normal(size=shape[:-1] + (2,))], axis=-1)
    tau6 = np.concatenate([tau, np.full((3, 2, 2), 5e-6)], axis=-1)
    valid6 = np.concatenate([np.ones((3, 2, 4), bool), np.zeros((3, 2, 2), bool)], axis=-1)
    more = compute_kpis(make_cirs(a6, tau6, valid6, ["bs0", "bs1"], ["uav0"] * 2, 30.0), cfg)
    xr.testing.assert_identical(ref, more)


def test_phy_kpis_follow_the_mcs_and_the_tbs():
    cfg = make_cfg(8, 8, 2)
    rng = np.random.default_rng(4)
    shape = (6, 2, 2, 64, 6)
    a = (rng.normal(size=shape) + 1j * rng.normal(size=shape)) * 1e-6
    cirs = make_cirs(a, rng.uniform(1e-7, 2e-6, (6, 2, 6)), rng.uniform(size=(6, 2, 6)) < 0.7,
                     ["bs0", "bs1"], ["uav0", "uav0"], [30.0, 33.0])
    k = compute_kpis(cirs, cfg)
    assert k["rx_served"].all()
    n_re = (12 * 14 - 12) * 4
    assert k.attrs["num_re_for_tbs"] == n_re
    m = k["mcs_index"].values
    tb = transport_block(k["mcs_modulation_order"].values[m], k["mcs_code_rate"].values[m] * 1024,
                         n_re)
    np.testing.assert_array_equal(k["tbs_bits"].values, tb.tbs_bits)
    np.testing.assert_array_equal(k["num_code_blocks"].values, tb.num_code_blocks)
    np.testing.assert_allclose(k["mcs_rate_bps"].values,
                               tb.tbs_bits * (1 - k["tbler"].values) / 0.5e-3, rtol=1e-12)
    np.testing.assert_allclose(k["mcs_spectral_efficiency_bpshz"].values,
                               k["mcs_rate_bps"].values / (K_SMALL * 30e3), rtol=1e-12)
    assert (k["tbler"].values <= 0.1).all()
    # EESM lies between the smallest and the mean per-RE SINR (Jensen), below Shannon's rate
    s = lin(k["sinr_per_subcarrier_db"].values)
    eff = lin(k["effective_sinr_db"].values)
    assert (eff >= s.min(-1) * (1 - 1e-12)).all() and (eff <= s.mean(-1) * (1 + 1e-12)).all()
    assert (k["mcs_rate_bps"].values < k["shannon_rate_bps"].values).all()

    ol = compute_kpis(cirs, make_cfg(8, 8, 2, link_adaptation="outer_loop"))
    assert "olla_offset_db" in ol and ol.attrs["link_adaptation"] == "outer_loop"
    np.testing.assert_array_equal(ol["mcs_index"].values[0], k["mcs_index"].values[0])
    assert ol["olla_offset_db"].values[0, 0] == 0.0


def test_chunking_over_time_does_not_change_results():
    cfg = make_cfg(8, 8, 2)
    rng = np.random.default_rng(4)
    shape = (5, 2, 2, 64, 6)
    a = (rng.normal(size=shape) + 1j * rng.normal(size=shape)) * 1e-6
    valid = rng.uniform(size=(5, 2, 6)) < 0.7
    cirs = make_cirs(a, rng.uniform(1e-7, 2e-6, (5, 2, 6)), valid, ["bs0", "bs1"],
                     ["uav0", "uav0"], [30.0, 33.0])
    whole = compute_kpis(cirs, cfg)
    chunked = compute_kpis(cirs, cfg, max_chunk_bytes=1)   # one time step per chunk
    xr.testing.assert_allclose(whole, chunked, rtol=1e-12)
    assert whole["sinr_per_subcarrier_db"].dims == ("time", "platform", "subcarrier")
    # a sub-band allocation: the KPI grid holds the allocated subcarriers only
    sub = compute_kpis(cirs, make_cfg(8, 8, 2, first_resource_block=1,
                                      num_allocated_resource_blocks=2))
    np.testing.assert_array_equal(sub["subcarrier"].values, np.arange(12, 36))
    assert sub.attrs["allocated_bandwidth_hz"] == 24 * 30e3
