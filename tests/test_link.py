"""Link-level KPIs: OFDM response, DFT codebook (sign checked against Sionna RT), SINR budget."""

from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.constants import Boltzmann, speed_of_light

from simart_pipeline.config import Array, BaseStation, Codebook, Ofdm, load_scene_config
from simart_pipeline.link.beams import (beam_gains, dft_codebook, rotation_local_to_world,
                                        unit_vector, world_to_local)
from simart_pipeline.link.kpis import compute_kpis, dbm_to_w
from simart_pipeline.link.ofdm import (channel_frequency_response, subcarrier_offsets_hz,
                                       thermal_noise_power_w)
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


def make_cfg(rows, cols, num_bs, oversampling=1, num_resource_blocks=K_SMALL // 12):
    base = load_scene_config(ROOT / "scenes" / "demo")
    arr = Array(rows=rows, cols=cols, spacing_wavelengths=0.5, pattern="iso")
    bss = tuple(BaseStation(name=f"bs{i}", position_m=(0.0, 0.0, 10.0), array=arr)
                for i in range(num_bs))
    return base.model_copy(update=dict(
        base_stations=bss, codebook=Codebook(oversampling=oversampling),
        ofdm=Ofdm(carrier_frequency_hz=FC, numerology_mu=1,
                  num_resource_blocks=num_resource_blocks)))


def make_cirs(a, tau_s, valid, tx, rx, power_dbm, tx_rows=8, tx_cols=8, dtype=np.complex64):
    """A ``cirs`` dataset per the data contract from ``a [T, L, r, n, P]``, ``tau_s``/``valid``
    ``[T, L, P]``. ``dtype=complex128`` keeps exact coefficients for 1e-9 link-budget checks."""
    a = np.asarray(a)
    T, L, r, n, P = a.shape
    valid = np.asarray(valid, bool)
    tau_s = np.where(valid, tau_s, np.nan)
    return xr.Dataset(
        dict(a=(("time", "link", "rx_ant", "tx_ant", "path"),
                np.where(valid[:, :, None, None], a, 0).astype(dtype)),
             tau_s=(("time", "link", "path"), tau_s),
             valid=(("time", "link", "path"), valid),
             los=(("time", "link", "path"), valid),
             num_valid_paths=(("time", "link"), valid.sum(-1).astype(np.int32)),
             link_no_path=(("time", "link"), ~valid.any(-1)),
             tx_power_dbm=("link", np.broadcast_to(np.asarray(power_dbm, float), (L,)).copy()),
             tx_ant_position_m=(("tx_ant", "axis"), upa_positions(tx_rows, tx_cols)),
             rx_ant_position_m=(("rx_ant", "axis"), upa_positions(1, r))),
        coords=dict(time=np.arange(T, dtype=np.int64) * 100_000_000, link=np.arange(L),
                    tx=("link", list(tx)), rx=("link", list(rx)), path=np.arange(P),
                    axis=["x", "y", "z"]),
        attrs=dict(carrier_frequency_hz=FC))


def noise_per_re(cfg):
    return Boltzmann * 290.0 * cfg.ofdm.subcarrier_spacing_hz * 10 ** (7.0 / 10)


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
    # append an invalid path (a = 0, tau = NaN) everywhere, and invalidate all of link 1 at t = 2
    a2 = np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)
    tau2 = np.concatenate([tau, np.full(tau.shape[:-1] + (1,), np.nan)], axis=-1)
    valid2 = np.concatenate([valid, np.zeros(valid.shape[:-1] + (1,), bool)], axis=-1)
    H = channel_frequency_response(a2, tau2, valid2, FC, f)
    assert H.shape == (3, 2, 1, 4, K_SMALL)
    np.testing.assert_array_equal(H, H_ref)
    valid2[2, 1] = False
    tau2[2, 1] = np.nan
    a2[2, 1] = 0
    H = channel_frequency_response(a2, tau2, valid2, FC, f)
    assert not np.isnan(H).any()
    assert np.all(H[2, 1] == 0) and np.array_equal(H[:2], H_ref[:2])


# --- codebook -------------------------------------------------------------------------------------

def test_codebook_unit_norm_orthogonal_and_on_grid():
    W, D = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8, oversampling=1)
    # 8x8 grid u = -1 + (2i+1)/8 per axis; 12 corner beams have u_y^2 + u_z^2 > 1
    assert W.shape == (52, 64) and D.shape == (52, 3)
    grid = -1 + (2 * np.arange(8) + 1) / 8
    assert np.all(np.isin(np.round(D[:, 1:], 12), np.round(grid, 12)))
    np.testing.assert_allclose(np.linalg.norm(D, axis=1), 1, rtol=1e-12)
    assert np.all(D[:, 0] > 0)
    np.testing.assert_allclose(W @ W.conj().T, np.eye(52), atol=1e-12)
    # a plane wave along beam b's direction: gain N on beam b, nothing on the others
    H = np.stack([plane_wave(D[b], 1.0) for b in (0, 20, 51)])[:, None, :, None]  # [3, 1, 64, 1]
    g = beam_gains(H, W)
    np.testing.assert_allclose(g[[0, 1, 2], [0, 20, 51]], 64, rtol=1e-12)
    assert np.sort(g, axis=1)[:, -2].max() < 1e-20

    Wo, Do = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8, oversampling=2)
    np.testing.assert_allclose(np.linalg.norm(Wo, axis=1), 1, rtol=1e-12)
    assert Wo.shape[0] > 4 * 52 - 40 and np.abs(Wo @ Wo.conj().T - np.eye(len(Wo))).max() > 0.1


def test_codebook_rows_and_cols_map_to_z_and_y():
    pos = upa_positions(2, 4)   # 2 rows along z, 4 cols along y
    W, D = dft_codebook(pos, LAMBDA, 2, 4)
    assert sorted(set(np.round(D[:, 1], 9))) == pytest.approx([-0.75, -0.25, 0.25, 0.75])
    assert sorted(set(np.round(D[:, 2], 9))) == pytest.approx([-0.5, 0.5])
    H = (np.exp(1j * 2 * np.pi / LAMBDA * pos @ D.T).T)[:, None, :, None]  # [B, 1, 8, 1]
    np.testing.assert_allclose(np.diag(beam_gains(H, W)), 8, rtol=1e-12)
    with pytest.raises(ValueError):
        dft_codebook(pos, LAMBDA, 4, 2)


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
    rt = pytest.importorskip("sionna.rt")
    scene = rt.load_scene()
    scene.frequency = FC
    scene.tx_array = rt.PlanarArray(num_rows=8, num_cols=8, vertical_spacing=0.5,
                                    horizontal_spacing=0.5, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    orientation = [0.4, -0.3, 0.2]
    scene.add(rt.Transmitter("tx", position=[1.0, 2.0, 3.0], orientation=orientation))
    wavelength = np.array(scene.wavelength, dtype=np.float64).item()
    pos = np.array(scene.tx_array.positions(scene.wavelength), dtype=np.float64).T  # [64, 3]
    W, D = dft_codebook(pos, wavelength, 8, 8)
    R = rotation_local_to_world(orientation)
    targets = [3, 17, 30, 44, 50]   # off-boresight beams: a wrong sign picks the mirror beam
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
    gains = beam_gains(H, W)                                                    # [rx, B]
    closest = np.argmax(los_local @ D.T, axis=1)
    np.testing.assert_array_equal(closest, targets)
    np.testing.assert_array_equal(np.argmax(gains, axis=1), closest)


# --- KPIs -----------------------------------------------------------------------------------------

def test_single_antenna_link_budget():
    cfg = make_cfg(1, 1, 1)
    alpha = 3e-5 * np.exp(0.7j)
    cirs = make_cirs(np.full((2, 1, 1, 1, 1), alpha), np.full((2, 1, 1), 0.4e-6),
                     np.ones((2, 1, 1), bool), ["bs0"], ["uav0"], 30.0, tx_rows=1, tx_cols=1)
    k = compute_kpis(cirs, cfg)
    stored = abs(complex(cirs["a"].values.ravel()[0])) ** 2   # complex64 as stored
    snr = dbm_to_w(30.0) / K_SMALL * stored / noise_per_re(cfg)
    sinr = 10 ** (k["sinr_per_subcarrier_db"].values / 10)
    np.testing.assert_allclose(sinr, snr, rtol=1e-9)
    np.testing.assert_allclose(10 ** (k["sinr_db"].values / 10), snr, rtol=1e-9)
    np.testing.assert_allclose(10 ** (k["snr_db"].values / 10), snr, rtol=1e-9)
    np.testing.assert_allclose(k["rx_power_per_re_dbm"].values,
                               10 * np.log10(1e3 * dbm_to_w(30.0) / K_SMALL * stored), rtol=1e-12)
    np.testing.assert_allclose(k["shannon_rate_bps"].values,
                               np.log2(1 + snr) * K_SMALL * 30e3, rtol=1e-9)


def test_planar_array_link_budget_has_full_array_gain():
    cfg = make_cfg(8, 8, 1)
    _, D = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8)
    alpha = 2e-6
    a = plane_wave(D[37], alpha)[None, None, None, :, None]
    cirs = make_cirs(a, np.full((1, 1, 1), 1.1e-6), np.ones((1, 1, 1), bool), ["bs0"], ["uav0"],
                     40.0, dtype=np.complex128)
    k = compute_kpis(cirs, cfg)
    snr = dbm_to_w(40.0) / K_SMALL * alpha**2 * 64 / noise_per_re(cfg)
    assert k["best_beam"].item() == 37 and k["serving_beam"].item() == 37
    assert k["best_beam_gain_db"].item() == pytest.approx(10 * np.log10(64 * alpha**2), rel=1e-12)
    np.testing.assert_allclose(10 ** (k["sinr_per_subcarrier_db"].values / 10), snr, rtol=1e-9)
    np.testing.assert_allclose(10 ** (k["sinr_db"].values / 10), snr, rtol=1e-9)


def test_two_equal_interferers_use_expected_power_over_beams():
    cfg = make_cfg(8, 8, 3)
    _, D = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8)
    a0, a1 = 4e-6, 1.5e-6
    a = np.stack([plane_wave(D[10], a0), plane_wave(D[25], a1), plane_wave(D[41], a1)])
    cirs = make_cirs(a[None, :, None, :, None], np.array([0.3e-6, 0.9e-6, 1.7e-6])[None, :, None],
                     np.ones((1, 3, 1), bool), ["bs0", "bs1", "bs2"], ["uav0"] * 3, 30.0,
                     dtype=np.complex128)
    k = compute_kpis(cirs, cfg)
    p_re, N = dbm_to_w(30.0) / K_SMALL, noise_per_re(cfg)
    S = p_re * 64 * a0**2
    I = p_re * 64 * a1**2 / 52   # one beam of 52 catches the whole plane wave (orthogonal beams)
    assert k["serving_tx"].item() == "bs0" and k["serving_link"].item() == 0
    np.testing.assert_allclose(10 ** (k["sinr_per_subcarrier_db"].values / 10), S / (2 * I + N),
                               rtol=1e-9)
    np.testing.assert_allclose(10 ** (k["sinr_db"].values / 10), S / (2 * I + N), rtol=1e-9)
    np.testing.assert_allclose(10 ** (k["snr_db"].values / 10), S / N, rtol=1e-9)


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
        np.testing.assert_allclose(10 ** (k["sinr_db"].values / 10),
                                   p_re * alpha**2 / (expected_i + N), rtol=1e-9)


def test_no_path_link_and_unserved_receiver(tmp_path):
    cfg = make_cfg(8, 8, 2)
    _, D = dft_codebook(upa_positions(8, 8), LAMBDA, 8, 8)
    a = np.zeros((2, 4, 1, 64, 2), complex)
    a[:, 0, 0, :, 0] = plane_wave(D[5], 1e-5)
    valid = np.zeros((2, 4, 2), bool)
    valid[:, 0, 0] = True   # only bs0 -> uav0 has a path; uav1 has none at all
    cirs = make_cirs(a, np.full((2, 4, 2), 0.2e-6), valid, ["bs0", "bs0", "bs1", "bs1"],
                     ["uav0", "uav1", "uav0", "uav1"], 30.0)
    k = compute_kpis(cirs, cfg)
    np.testing.assert_array_equal(k["link_has_path"].values, [[True, False, False, False]] * 2)
    for name in ("beam_gain_db", "best_beam_gain_db", "rx_power_per_re_dbm"):
        v = k[name].values
        assert "nan_means" in k[name].attrs
        assert np.isnan(v[:, 1:]).all() and np.isfinite(v[:, 0]).all()
    assert list(k["platform"].values) == ["uav0", "uav1"]
    np.testing.assert_array_equal(k["rx_served"].values, [[True, False]] * 2)
    np.testing.assert_array_equal(k["serving_tx"].values, [["bs0", ""]] * 2)
    assert np.isnan(k["sinr_db"].values[:, 1]).all()
    assert np.isfinite(k["sinr_db"].values[:, 0]).all()
    np.testing.assert_array_equal(k["sinr_db"].values, k["snr_db"].values)  # no interferer path
    np.testing.assert_array_equal(k["shannon_rate_bps"].values[:, 1], 0.0)
    for name, var in k.variables.items():
        assert "long_name" in var.attrs, name
        if var.dtype.kind in "fiub":
            assert "units" in var.attrs, name
        if var.dtype.kind == "f":
            assert not np.isinf(var.values).any(), name
    check_finite(k)
    back = open_store(write_store(k, tmp_path / "kpis.zarr")).load()
    assert list(back["serving_tx"].values[0]) == ["bs0", ""]
    np.testing.assert_array_equal(back["time"].values, cirs["time"].values)


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
