"""OFDM radar processing (sensing/radar.py): synthetic echoes through the frame response and the
range-Doppler map, checked against the geometry that made them."""

import numpy as np
import pytest

from simart_pipeline.config import Ofdm
from simart_pipeline.link.ofdm import slot_duration_s, subcarrier_offsets_hz
from simart_pipeline.sensing.radar import (frame_response, peak, radar_truth, range_doppler_map,
                                           symbol_duration_s)
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS as C

OFDM = Ofdm(carrier_frequency_hz=3.5e9, numerology_mu=1, num_resource_blocks=51)
NUM_SYMBOLS = 256
K = OFDM.num_subcarriers
DF = OFDM.subcarrier_spacing_hz
T_SYM = symbol_duration_s(OFDM)
LAMBDA = C / OFDM.carrier_frequency_hz
OFFSETS = subcarrier_offsets_hz(OFDM)
TIMES = np.arange(NUM_SYMBOLS) * T_SYM


def _response(a, tau_s, doppler_hz, valid=None):
    a = np.atleast_1d(np.asarray(a, dtype=np.complex128))
    valid = np.ones(a.shape, bool) if valid is None else np.asarray(valid)
    return frame_response(a, np.atleast_1d(tau_s), np.atleast_1d(doppler_hz), valid,
                          OFDM.carrier_frequency_hz, OFFSETS, TIMES)


def _on_bin(range_bin, velocity_bin_from_zero, range_oversampling=1, doppler_oversampling=1):
    """(tau, f_D) of a path exactly on delay bin ``range_bin`` and on the Doppler bin whose
    radial velocity is ``velocity_bin_from_zero`` bin spacings from 0."""
    tau = range_bin / (K * DF * range_oversampling)
    v_r = velocity_bin_from_zero * LAMBDA / (2 * NUM_SYMBOLS * doppler_oversampling * T_SYM)
    return tau, -2 * v_r / LAMBDA


def _local_maxima(power, floor):
    """Cells strictly above their 8 neighbours (cyclic) and above ``floor``."""
    p = power
    is_max = p > floor
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                is_max &= p > np.roll(np.roll(p, di, axis=0), dj, axis=1)
    return list(zip(*np.nonzero(is_max)))


def test_symbol_duration_is_the_slot_over_its_symbols():
    assert T_SYM * 14 == pytest.approx(slot_duration_s(OFDM), rel=1e-15)
    assert T_SYM == pytest.approx(0.5e-3 / 14, rel=1e-15)


def test_axes_are_the_monostatic_grids():
    rd = range_doppler_map(np.zeros((NUM_SYMBOLS, K)), OFDM, range_oversampling=2,
                           doppler_oversampling=2)
    assert rd.power.shape == (2 * K, 2 * NUM_SYMBOLS) and rd.power.dtype == np.float64
    np.testing.assert_allclose(np.diff(rd.range_m), rd.range_resolution_m / 2, rtol=1e-12)
    assert rd.range_m[0] == 0 and rd.range_m[-1] < rd.max_range_m
    assert rd.range_resolution_m == pytest.approx(C / (2 * OFDM.bandwidth_hz), rel=1e-12)
    assert np.all(np.diff(rd.radial_velocity_mps) > 0)
    np.testing.assert_allclose(np.diff(rd.radial_velocity_mps), rd.velocity_resolution_mps / 2,
                               rtol=1e-9)
    assert -rd.max_radial_velocity_mps <= rd.radial_velocity_mps.min()
    assert rd.radial_velocity_mps.max() <= rd.max_radial_velocity_mps
    assert np.any(rd.radial_velocity_mps == 0)
    assert rd.window == "hann"


def test_a_receding_target_peaks_at_its_range_and_radial_velocity():
    radar = np.array([10.0, -5.0, 25.0])
    u = np.array([2.0, 3.0, -1.0]) / np.sqrt(14.0)
    truth = radar_truth(radar, (radar + 60.0 * u)[None], (7.0 * u + 3.0 * np.cross(u, [0, 0, 1]))[None])
    R, v_r = truth["range_m"][0], truth["radial_velocity_mps"][0]
    assert R == pytest.approx(60.0) and v_r == pytest.approx(7.0)
    a = 1e-4 * np.exp(0.7j)
    H = _response(a, 2 * R / C, -2 * v_r / LAMBDA)
    assert H.shape == (NUM_SYMBOLS, K) and H.dtype == np.complex128
    rd = range_doppler_map(H, OFDM)
    r_pk, v_pk, p_pk = peak(rd)
    assert abs(r_pk - R) <= rd.range_resolution_m
    assert abs(v_pk - v_r) <= rd.velocity_resolution_mps
    assert v_pk > 0  # receding: positive
    # off-bin: the window's scalloping loses power, never adds any
    assert 0.3 * abs(a) ** 2 < p_pk <= abs(a) ** 2 * (1 + 1e-12)


def test_an_approaching_target_has_negative_velocity_in_the_map():
    v_r = -11.0
    H = _response(1.0, 2 * 120.0 / C, -2 * v_r / LAMBDA)
    rd = range_doppler_map(H, OFDM)
    assert abs(peak(rd)[1] - v_r) <= rd.velocity_resolution_mps


@pytest.mark.parametrize("window", ["hann", "rect"])
@pytest.mark.parametrize("ovs", [(1, 1), (2, 3)])
def test_a_path_on_a_bin_gives_its_power_at_its_cell(window, ovs):
    a = 3e-3 * np.exp(-2.1j)
    tau, f_d = _on_bin(13, -5, *ovs)
    rd = range_doppler_map(_response(a, tau, f_d), OFDM, range_oversampling=ovs[0],
                           doppler_oversampling=ovs[1], window=window)
    r_pk, v_pk, p_pk = peak(rd)
    assert p_pk == pytest.approx(abs(a) ** 2, rel=1e-9)
    assert r_pk == pytest.approx(C * tau / 2, rel=1e-9)
    assert v_pk == pytest.approx(f_d * -LAMBDA / 2, rel=1e-9)


def test_two_separated_paths_give_two_separated_peaks():
    # off-bin, 4.4 range bins and 3.3 velocity bins apart
    R = np.array([60.0, 60.0 + 4.4 * C / (2 * K * DF)])
    v = np.array([7.0, 7.0 - 3.3 * LAMBDA / (2 * NUM_SYMBOLS * T_SYM)])
    a = np.array([1.0, 0.6j])
    rd = range_doppler_map(_response(a, 2 * R / C, -2 * v / LAMBDA), OFDM)
    maxima = _local_maxima(rd.power, floor=1e-2 * rd.power.max())
    assert len(maxima) == 2
    found = sorted((rd.range_m[i], rd.radial_velocity_mps[j]) for i, j in maxima)
    for (r_f, v_f), r_t, v_t in zip(found, R, v):
        assert abs(r_f - r_t) <= rd.range_resolution_m
        assert abs(v_f - v_t) <= rd.velocity_resolution_mps


@pytest.mark.parametrize("window", ["rect", "hann"])
def test_parseval_total_energy(window):
    rng = np.random.default_rng(5)
    H = rng.standard_normal((NUM_SYMBOLS, K)) + 1j * rng.standard_normal((NUM_SYMBOLS, K))
    rd = range_doppler_map(H, OFDM, range_oversampling=2, doppler_oversampling=3, window=window)
    if window == "rect":
        expected = (2 * K) * (3 * NUM_SYMBOLS) * np.sum(np.abs(H) ** 2) / (K * NUM_SYMBOLS) ** 2
    else:  # the periodic Hann window, written out
        w = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(K) / K)
        v = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(NUM_SYMBOLS) / NUM_SYMBOLS)
        Hw = H * v[:, None] * w[None, :]
        expected = (2 * K) * (3 * NUM_SYMBOLS) * np.sum(np.abs(Hw) ** 2) / (w.sum() * v.sum()) ** 2
    assert rd.power.sum() == pytest.approx(expected, rel=1e-10)


def test_invalid_paths_change_nothing():
    a = np.array([1.0, 0.3 - 0.2j])
    tau = 2 * np.array([60.0, 300.0]) / C
    f_d = np.array([-160.0, 450.0])
    H = _response(a, tau, f_d)
    H3 = _response(np.append(a, 1e12), np.append(tau, np.nan), np.append(f_d, np.inf),
                   valid=[True, True, False])
    np.testing.assert_array_equal(H3, H)
    np.testing.assert_array_equal(range_doppler_map(H3, OFDM).power, range_doppler_map(H, OFDM).power)


def test_frame_response_is_the_sum_of_its_paths():
    a = np.array([1.0, 0.3 - 0.2j])
    tau = 2 * np.array([60.0, 300.0]) / C
    f_d = np.array([-160.0, 450.0])
    H = _response(a, tau, f_d)
    n, k = 37, 101
    f = OFDM.carrier_frequency_hz + OFFSETS[k]
    expected = np.sum(a * np.exp(-2j * np.pi * f * tau) * np.exp(2j * np.pi * f_d * TIMES[n]))
    assert H[n, k] == pytest.approx(expected, rel=1e-10)


def test_radar_truth_geometry_and_radial_velocity_sign():
    radar = np.array([1.0, 2.0, 30.0])
    u = np.array([3.0, 4.0, 0.0]) / 5.0
    tangential = np.array([-4.0, 3.0, 0.0]) / 5.0
    pos = np.stack([radar + 50 * u, radar + 50 * u, radar + 50 * u, radar + [0.0, 0.0, -20.0]])
    vel = np.stack([12 * u, 9 * tangential, -5 * u, [1.0, 1.0, 0.0]])
    t = radar_truth(radar, pos, vel)
    np.testing.assert_allclose(t["range_m"], [50, 50, 50, 20], rtol=1e-12)
    np.testing.assert_allclose(t["radial_velocity_mps"], [12, 0, -5, 0], atol=1e-12)
    np.testing.assert_allclose(t["azimuth_rad"][:3], np.arctan2(4, 3), rtol=1e-12)
    np.testing.assert_allclose(t["elevation_rad"], [0, 0, 0, -np.pi / 2], atol=1e-12)
    assert np.all(np.isfinite(t["elevation_rad"]))


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="num_subcarriers"):
        range_doppler_map(np.zeros((4, K - 1)), OFDM)
    with pytest.raises(ValueError, match="range_oversampling"):
        range_doppler_map(np.zeros((4, K)), OFDM, range_oversampling=0)
