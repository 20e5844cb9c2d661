"""The lattice rays' second pass on undersampled cells (``one_pass_moments(lattice_resample_factor=f)``):
the bins of launch directions partition the Fibonacci lattice and the sphere alike, the replayed
rays are the first pass's bit for bit (so the swap takes out exactly what they put in), only the
undersampled cells change, and there the finer rays move the gain towards the closed form."""

from dataclasses import fields

import numpy as np
import pytest
import scipy.constants as const

from test_one_pass import _axes, _cfg, _friis_cell_mean, _ground, _wall, _write_scene

from simart_pipeline import engine
from simart_pipeline.ckm import one_pass as op
from simart_pipeline.ckm import shoot_bounce as sb
from simart_pipeline.ckm.moments import CellMoments
from simart_pipeline.radio.tracer import RadioScene

LAM = const.c / 3.5e9


def _bin_of_direction(bins: sb.LatticeBins, u: np.ndarray) -> np.ndarray:
    """The bin a unit direction falls in, from its z and azimuth (independent of the lattice)."""
    bz = np.minimum(((1.0 - u[:, 2]) / 2.0 * bins.num_z).astype(np.int64), bins.num_z - 1)
    frac = np.mod(np.arctan2(u[:, 1], u[:, 0]) / (2 * np.pi), 1.0)
    bp = np.minimum((frac * bins.num_phi).astype(np.int64), bins.num_phi - 1)
    return bz * bins.num_phi + bp


def test_lattice_bins_partition_the_lattice_and_the_sphere_into_equal_areas():
    n = 100_003
    bins = sb.LatticeBins(n, 16)
    of = bins.bin_of(np.arange(n))
    counts = np.bincount(of, minlength=bins.num_bins)
    assert len(counts) == bins.num_bins and counts.sum() == n
    expected = n / bins.num_bins
    assert 12 <= expected <= 20
    # equal-area bins hold about as many lattice points each (a low-discrepancy lattice)
    assert counts.min() >= 0.5 * expected and counts.max() <= 1.5 * expected, (counts.min(), counts.max())
    # a lattice point's bin is the bin its launch direction falls in (away from the bin edges)
    engine.init()
    d = sb.fibonacci_directions(0, n, n)
    u = np.stack([np.asarray(c, np.float64) for c in (d.x, d.y, d.z)], -1)
    assert np.mean(_bin_of_direction(bins, u) == of) > 0.998
    chosen = np.array([0, 7, bins.num_bins // 2, bins.num_bins - 1])
    np.testing.assert_array_equal(bins.rays_in(chosen), np.flatnonzero(np.isin(of, chosen)))
    # a bin's neighbours: the 8 around it (the azimuth wraps round); a polar band whole
    mid = (bins.num_z // 2) * bins.num_phi  # azimuth sector 0: its left neighbours wrap round
    near = bins.with_neighbours(np.array([mid]))
    assert len(near) == 9 and mid in near and mid + bins.num_phi - 1 in near and mid - 1 in near
    np.testing.assert_array_equal(bins.with_neighbours(np.array([3])),
                                  np.r_[np.arange(bins.num_phi), bins.num_phi + np.array([2, 3, 4])])
    # the finer directions lie in their own bin and are unit vectors
    per_bin = 9
    fine = bins.finer_directions(np.arange(bins.num_bins), per_bin)
    np.testing.assert_allclose(np.linalg.norm(fine, axis=1), 1.0, atol=1e-12)
    assert np.mean(_bin_of_direction(bins, fine) == np.repeat(np.arange(bins.num_bins), per_bin)) > 0.9999
    # ... each standing for 4 pi / (bins x rays per bin): an equal-area quadrature of the sphere
    w = 4 * np.pi / (bins.num_bins * per_bin)
    np.testing.assert_allclose(w * np.sum(fine[:, 2] ** 2), 4 * np.pi / 3, rtol=1e-3)
    np.testing.assert_allclose(w * np.sum(fine[:, 2] > 0.7), 2 * np.pi * 0.3, rtol=1e-2)
    # another seed shifts every bin's rays, inside the same bins
    other = bins.finer_directions(np.arange(bins.num_bins), per_bin, seed=1)
    assert not np.allclose(other, fine)
    assert np.mean(_bin_of_direction(bins, other) == np.repeat(np.arange(bins.num_bins), per_bin)) > 0.9999


@pytest.mark.parametrize("mechanisms", ["specular", "refraction", "diffuse"])
def test_replayed_rays_are_the_first_pass_and_only_undersampled_cells_change(tmp_path, monkeypatch, mechanisms):
    """Ground and a brick wall, few rays: the rays of the bins that reached the undersampled cells,
    traced again, give those cells the very sums the first pass's lattice rays gave them before any
    diffuse reflection (with no diffuse reflection: every deposit, as there is no diffraction);
    after the swap every other cell keeps its moments bit for bit."""
    xml = _write_scene(tmp_path / "gw", {"ground": (_ground(), "medium_dry_ground"),
                                         "wall": (_wall(12.0), "brick")}, 0.3)
    radio = RadioScene.from_config(xml, _cfg())
    if mechanisms == "diffuse":
        for k, s_ in (("wall", 0.5), ("ground", 0.3)):
            radio.scene.objects[k].radio_material.scattering_coefficient = s_
    x, y = _axes(-4.0, 16, -12.0, 12, 2.0)
    args = (radio, np.array([0.0, 1.0, 8.0]), np.zeros(3), x, y, np.array([1.5]), 6_000, 2)
    # host sums (the CPU's, bitwise repeatable; the device's are checked against them below)
    kw = dict(refraction=mechanisms == "refraction", diffuse_reflection=mechanisms == "diffuse",
              rx_polarization="V", codebook=np.ones((1, 1), complex), accumulate_on_device=False)
    # a GPU compiles a replayed ray's set-up in another kernel than the first pass's and may round
    # its float32 direction differently (H200: a cell's replayed sum 2e-9 off); LLVM: the same bits
    rtol = 1e-12 if engine.init().startswith("llvm") else 1e-6
    seen = {}
    original = op._Accumulator.replace

    def replace(self, cells, old, new):
        before = self.summed()
        seen.update(cells=cells.copy(), old=old, new=new, binned=self.binned_power[cells].copy(),
                    before={f: getattr(before, f)[cells].copy() for f in ("count", "power", "p_excess_delay_s")})
        return original(self, cells, old, new)

    monkeypatch.setattr(op._Accumulator, "replace", replace)
    first = op.one_pass_moments(*args, **kw)
    assert first.lattice_second_pass is None and not seen
    second = op.one_pass_moments(*args, **kw, lattice_resample_factor=8)
    info = second.lattice_second_pass
    cells = seen["cells"]
    assert info["cells_swapped"] == len(cells) >= 5 and info["bins"] >= info["bins_reaching"] >= 1
    assert info["new_rays"] >= 8 * 0.5 * info["replayed_rays"]
    np.testing.assert_allclose(seen["old"].power[cells], seen["binned"], rtol=rtol, atol=0)
    if mechanisms == "diffuse":  # the diffused part stays the first pass's
        assert (seen["binned"] < seen["before"]["power"] * (1 - 1e-9)).any()
    else:
        assert info["cells_swapped"] == info["undersampled_cells"]
        np.testing.assert_array_equal(seen["old"].count[cells], seen["before"]["count"])
        for f in ("power", "p_excess_delay_s"):
            np.testing.assert_allclose(getattr(seen["old"], f)[cells], seen["before"][f], rtol=rtol, atol=0)
    flat = np.zeros(first.count.size, bool)
    flat[cells] = True
    other = ~flat.reshape(first.count.shape)
    same = (np.testing.assert_array_equal if rtol < 1e-9 else
            lambda a, b, err_msg: np.testing.assert_allclose(a, b, rtol=rtol, err_msg=err_msg))
    for f in fields(CellMoments):
        same(getattr(second, f.name)[other], getattr(first, f.name)[other], err_msg=f.name)
    assert (second.count[~other] > first.count[~other]).mean() > 0.5
    # the same call again: the same bits (hashed shifts and random streams)
    again = op.one_pass_moments(*args, **kw, lattice_resample_factor=8)
    for f in fields(CellMoments):
        np.testing.assert_array_equal(getattr(again, f.name), getattr(second, f.name), err_msg=f.name)


def test_the_second_pass_with_sums_on_the_device_equals_the_host_sums(tmp_path):
    """``accumulate_on_device`` (the GPU's path) with the lattice second pass, diffuse reflection,
    refraction and connections: the same cells swapped and the same moments as the host's, to
    float32 rounding (``test_one_pass._assert_device_sums_equal_host_sums``)."""
    from test_one_pass import _assert_device_sums_equal_host_sums

    xml = _write_scene(tmp_path / "gw", {"ground": (_ground(), "medium_dry_ground"),
                                         "wall": (_wall(12.0), "brick")}, 0.3)
    radio = RadioScene.from_config(xml, _cfg())
    radio.scene.objects["ground"].radio_material.scattering_coefficient = 0.3
    x, y = _axes(-4.0, 16, -12.0, 12, 2.0)
    kw = dict(refraction=True, diffuse_reflection=True, diffuse_connections=1.0, rx_polarization="V",
              codebook=np.ones((1, 1), complex), lattice_resample_factor=8, batch_rays=3_001)
    host, device = (op.one_pass_moments(radio, np.array([0.0, 1.0, 8.0]), np.zeros(3), x, y, np.array([1.5]),
                                        20_000, 2, accumulate_on_device=on, **kw) for on in (False, True))
    assert host.lattice_second_pass["cells_swapped"] >= 5
    assert device.lattice_second_pass == host.lattice_second_pass
    _assert_device_sums_equal_host_sums(host, device)


def test_finer_rays_move_undersampled_cells_towards_friis():
    """Free space, isotropic element, 4,000 rays: the far cells get 1 to 4 hits, their gain tens of
    percent off the cell-mean Friis gain; the second pass with 16x the rays in their bins brings the
    median error in those cells down by more than half (measured 51 -> 4.8 %) and leaves far fewer
    undersampled."""
    radio = RadioScene.from_config(None, _cfg())
    tx = np.array([0.0, 0.0, 10.0])
    x, y = _axes(-40.0, 40, -40.0, 40, 2.0)
    h = 1.5
    run = lambda **kw: op.one_pass_moments(radio, tx, np.zeros(3), x, y, [h], 4_000, 0, **kw)  # noqa: E731
    first, second = run(), run(lattice_resample_factor=16)
    ref = _friis_cell_mean(tx, x, y, h, 2.0)
    # undersampled: an effective count (Kish) below min_hits_for_power
    eff = first.power[0] ** 2 / np.where(first.power_sq[0] > 0, first.power_sq[0], 1.0)
    under = (first.count[0] >= 1) & (eff < op.DEFAULT_MIN_HITS_FOR_POWER)
    assert under.sum() >= 100
    assert second.lattice_second_pass["undersampled_cells"] == second.lattice_second_pass["cells_swapped"] == under.sum()
    err_first = np.abs(first.power[0][under] / ref[under] - 1)
    err_second = np.abs(second.power[0][under] / ref[under] - 1)
    assert np.median(err_second) < 0.5 * np.median(err_first), (np.median(err_first), np.median(err_second))
    # unbiased: summed over those cells the power stays the closed form's (a few percent of noise)
    assert abs(second.power[0][under].sum() / ref[under].sum() - 1) < 0.03  # measured 0.2 %
    # measured: 160 of 647 stay below 5 effective hits, the far cells where the first pass's one hit
    # was luck (about 0.2 expected there at 4,000 rays, 3 with the 16x finer rays)
    assert second.lattice_second_pass["still_undersampled"] < 0.4 * under.sum()


def test_a_second_pass_beyond_the_random_streams_is_refused(monkeypatch):
    radio = RadioScene.from_config(None, _cfg())
    x, y = _axes(-40.0, 40, -40.0, 40, 2.0)
    run = lambda f: op.one_pass_moments(radio, np.array([0.0, 0.0, 10.0]), np.zeros(3), x, y, [1.5], 2_000, 0,  # noqa: E731
                                        lattice_resample_factor=f)
    monkeypatch.setattr(op, "RANDOM_STREAMS", 10_000)  # as if the lattice's streams ended near 2**32
    with pytest.raises(ValueError, match=r"lattice_resample_factor 64: \d+ new rays after 2000 lattice rays "
                                         r"exceed the 2\*\*32 random streams; lower the factor or num_rays"):
        run(64)
    with pytest.raises(ValueError, match="lattice_resample_factor must be >= 1, got 0"):
        run(0)
