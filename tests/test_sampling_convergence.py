"""PathSolver's sampling checked by tracing again with more samples (radio/convergence.py): a far
plate that the configured samples cannot hit is found by the finer trace, and the check names the
delay spread it adds (a closed form) and the setting to raise; a near plate that both find passes."""

import numpy as np
import pytest
import trimesh

from conftest import LOS_SPECULAR, write_radio_scene
from simart_pipeline.config import Array, RayTracing
from simart_pipeline.radio.convergence import sampling_convergence, spread_receivers
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS

FC = 3.5e9
TX = np.array([[0.0, 0.0, 10.0]])
RX = np.array([[0.0, 5.0, 10.0]])


def _plate(distance_m: float, side_m: float) -> trimesh.Trimesh:
    """A square plate in the plane x = distance, centred on the specular point of the devices
    (y = 2.5 m, midway between them, at their height)."""
    h = side_m / 2
    v = [[distance_m, 2.5 - h, 10 - h], [distance_m, 2.5 + h, 10 - h], [distance_m, 2.5 + h, 10 + h],
         [distance_m, 2.5 - h, 10 + h]]
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def _radio(tmp_path, distance_m: float, side_m: float, samples: int) -> RadioScene:
    xml = write_radio_scene(tmp_path, {"plate": (_plate(distance_m, side_m), "metal")}, FC, 0.01)
    iso = Array(rows=1, cols=1, pattern="iso", polarization="V")
    solver = RayTracing(max_depth=1, samples_per_src=samples, **LOS_SPECULAR)
    return RadioScene(xml, frequency_hz=FC, bandwidth_hz=20e6, tx_array=iso, rx_array=iso, solver=solver)


def test_a_far_plate_missed_by_the_configured_samples_fails_with_its_delay_spread(tmp_path):
    # a 4 m plate 300 m away subtends 1.8e-4 sr: 0.01 of 1,000 rays' share, 14 of 1e6
    radio = _radio(tmp_path, 300.0, 4.0, 1000)
    conv = sampling_convergence(radio, TX, np.zeros((1, 3)), RX, factor=1000)
    assert radio.solver_config.samples_per_src == 1000  # restored
    assert conv.check_samples_per_src == 10**6
    lam = SPEED_OF_LIGHT_MPS / FC
    d_los = 5.0
    d_far = 2 * np.hypot(300.0, 2.5)  # the mirror image of the transmitter
    friis_db = 20 * np.log10(lam / (4 * np.pi * d_los))
    # at 1,000 samples the line of sight alone: Friis, no spread
    assert conv.path_gain_db[0, 0, 0] == pytest.approx(friis_db, abs=0.05)
    assert conv.rms_delay_spread_s[0, 0, 0] == pytest.approx(0.0, abs=1e-12)
    # at 1e6 the plate's reflection (a metal plate at normal incidence: |R| = 1 within 0.1 dB) too:
    # two paths, the spread of a two-point distribution tau sqrt(a (1 - a))
    p_los, p_far = (lam / (4 * np.pi * d_los)) ** 2, (lam / (4 * np.pi * d_far)) ** 2
    share = p_far / (p_los + p_far)
    spread = (d_far - d_los) / SPEED_OF_LIGHT_MPS * np.sqrt(share * (1 - share))
    assert conv.rms_delay_spread_s[1, 0, 0] == pytest.approx(spread, rel=0.03)
    assert spread > 15e-9  # beyond the tolerance (10 ns), though the gain moves 0.001 dB
    assert conv.path_gain_db[1, 0, 0] - conv.path_gain_db[0, 0, 0] < 0.01
    r = conv.result("receiver")
    assert not r.passed and r.metadata["links_compared"] == 1
    assert r.metadata["worst_delay_spread_change_ns"] == pytest.approx(1e9 * spread, rel=0.03)
    assert "RMS delay spread 0.0 ->" in r.description and "from 1,000 to 1,000,000 samples" in r.description
    assert "raise ray_tracing.samples_per_src (now 1,000)" in r.description


def test_a_near_plate_that_both_traces_find_passes(tmp_path):
    # a 20 m plate 20 m away: 0.9 sr, some 70 of 1,000 rays
    radio = _radio(tmp_path, 20.0, 20.0, 1000)
    conv = sampling_convergence(radio, TX, np.zeros((1, 3)), RX)
    assert conv.check_samples_per_src == 10_000
    np.testing.assert_allclose(conv.path_gain_db[0], conv.path_gain_db[1], atol=1e-3)
    np.testing.assert_allclose(conv.rms_delay_spread_s[0], conv.rms_delay_spread_s[1], rtol=1e-3)
    assert conv.rms_delay_spread_s[0, 0, 0] > 10e-9  # the reflection is there in both
    r = conv.result("receiver")
    assert r.passed and r.metadata["worst_path_gain_change_db"] == pytest.approx(0.0, abs=1e-3)


def test_a_receiver_that_only_the_far_plate_reaches_has_no_path_at_the_configured_samples(tmp_path):
    # a metal wall between the devices (the plane y = 2.5, x from -5 to 2 m) blocks the line of sight
    # and not the far plate's path, which crosses that plane only at the plate
    wall = trimesh.Trimesh([[-5, 2.5, 0], [2, 2.5, 0], [2, 2.5, 20], [-5, 2.5, 20]], [[0, 1, 2], [0, 2, 3]],
                           process=False)
    xml = write_radio_scene(tmp_path, {"plate": (_plate(300.0, 4.0), "metal"), "wall": (wall, "metal")}, FC, 0.01)
    iso = Array(rows=1, cols=1, pattern="iso", polarization="V")
    radio = RadioScene(xml, frequency_hz=FC, bandwidth_hz=20e6, tx_array=iso, rx_array=iso,
                       solver=RayTracing(max_depth=1, samples_per_src=1000, **LOS_SPECULAR))
    conv = sampling_convergence(radio, TX, np.zeros((1, 3)), RX, factor=1000)
    lam = SPEED_OF_LIGHT_MPS / FC
    assert conv.path_gain_db[0, 0, 0] == -np.inf and np.isnan(conv.rms_delay_spread_s[0, 0, 0])
    assert conv.path_gain_db[1, 0, 0] == pytest.approx(20 * np.log10(lam / (4 * np.pi * 2 * np.hypot(300.0, 2.5))),
                                                       abs=0.1)
    r = conv.result("receiver")
    assert not r.passed and "no path at 1,000 samples" in r.description
    assert r.metadata["worst_path_gain_change_db"] is None  # no gain to compare on the one link


def test_receivers_spread_over_the_candidates_in_order():
    pts = np.arange(30.0).reshape(10, 3)
    np.testing.assert_array_equal(spread_receivers(pts, 4), [0, 3, 6, 9])
    np.testing.assert_array_equal(spread_receivers(pts[:3], 8), [0, 1, 2])
    assert len(spread_receivers(pts[:0], 8)) == 0
