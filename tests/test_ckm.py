"""Channel knowledge maps: analytic cells (two-ray, single path, metal wall), masks, link layers,
and the mosaic store's tile backfill equivalence."""


import numpy as np
import pytest
import scipy.constants as const
import shapely
import trimesh
import xarray as xr
from conftest import scene_config, ground_square, write_radio_scene

from simart_pipeline import provenance
from simart_pipeline.ckm import mosaic
from simart_pipeline.ckm.grid import chunk_shape, scene_tiles, tile_slices
from simart_pipeline.ckm.layers import tile_layers
from simart_pipeline.ckm.maps import map_groups, map_template
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.scene import geometry, meshes

FC = 3.5e9


_cfg = scene_config  # the scene's config after an edit of its raw YAML


def _single_bs_iso(raw, ckm=None, position=(0.0, 0.0, 20.0)):
    raw["base_stations"] = [{"name": "bs0", "position_m": list(position),
                             "array": {"rows": 1, "cols": 1, "pattern": "iso"}, "power_dbm": 30.0}]
    raw["ckm"] = {"center_m": [60.0, 0.0], "size_m": [80.0, 20.0], "cell_size_m": 10.0, "height_m": 1.5,
                  "tiles": [1, 1], **(ckm or {})}
    raw["materials"] = {"thickness_m": 10.0}  # the ground reflects like a half-space


def _fresnel_tm(eps_r, sigma, cos_i):
    eta = eps_r - 1j * sigma / (2 * np.pi * FC * const.epsilon_0)
    root = np.sqrt(eta - (1 - cos_i**2))
    return (eta * cos_i - root) / (eta * cos_i + root)


def test_flat_ground_cells_follow_the_two_ray_model(tiny_scene, tmp_path):
    """Per cell: incoherent gain (lambda/4pi)^2 (1/d1^2 + |Gamma|^2/d2^2), ToA d1/c, mean delay and
    RMS delay spread of two paths in closed form, zero azimuth spread of arrival (both paths come
    from the transmitter's azimuth), and line of sight."""
    cfg = _cfg(tiny_scene, _single_bs_iso)
    xml = write_radio_scene(tmp_path / "flat", {"ground": (ground_square(), "medium_dry_ground")}, FC, 10.0)
    radio = RadioScene.from_config(xml, cfg)
    ds = tile_layers(radio, cfg, geometry.SourceGeometry(), "r0c0").isel(bs=0, height=0)
    eps_r, sigma, _ = radio.material_properties()["ground"]
    xx, yy = np.meshgrid(ds["x"].values, ds["y"].values)
    r = np.hypot(xx, yy)
    d1, d2 = np.hypot(r, 20.0 - 1.5), np.hypot(r, 21.5)
    lam = const.c / FC
    gamma2 = np.abs(_fresnel_tm(eps_r, sigma, 21.5 / d2)) ** 2
    p1, p2 = (lam / (4 * np.pi * d1)) ** 2, gamma2 * (lam / (4 * np.pi * d2)) ** 2
    np.testing.assert_allclose(ds["path_gain_db"].values, 10 * np.log10(p1 + p2), atol=0.01)
    np.testing.assert_allclose(ds["toa_s"].values, d1 / const.c, rtol=1e-6)
    t1, t2 = d1 / const.c, d2 / const.c
    np.testing.assert_allclose(ds["mean_delay_s"].values, (p1 * t1 + p2 * t2) / (p1 + p2), rtol=1e-6)
    np.testing.assert_allclose(ds["rms_delay_spread_s"].values, np.sqrt(p1 * p2) / (p1 + p2) * (t2 - t1),
                               rtol=2e-3)
    np.testing.assert_allclose(ds["asa_deg"].values, 0.0, atol=0.05)
    assert ds["los"].values.all() and (ds["count"].values == 2).all()
    # the coherent sum lies between the destructive and constructive two-ray bounds
    coh = 10 ** (ds["path_gain_coherent_db"].values / 10)
    assert np.all(coh <= (np.sqrt(p1) + np.sqrt(p2)) ** 2 * (1 + 1e-6))
    assert np.all(coh >= (np.sqrt(p1) - np.sqrt(p2)) ** 2 * (1 - 1e-6))


def test_single_path_cells_have_zero_spreads(tiny_scene):
    cfg = _cfg(tiny_scene, _single_bs_iso)
    ds = tile_layers(RadioScene.from_config(None, cfg), cfg, geometry.SourceGeometry(), "r0c0").isel(bs=0, height=0)
    assert (ds["count"].values == 1).all()
    for name in ("rms_delay_spread_s", "asa_deg", "zsa_deg", "asd_deg", "zsd_deg"):
        np.testing.assert_allclose(ds[name].values, 0.0, atol=1e-3 if name.endswith("deg") else 1e-15)
    assert (ds["los_power_fraction"].values == 1).all()
    # free space: the SINR of a lone station is its SNR, and the best beam of one antenna is beam 0
    np.testing.assert_allclose(ds["sinr_db"].values, ds["snr_db"].values)
    assert (ds["best_beam"].values == 0).all()


def test_a_cell_behind_a_metal_wall_has_no_line_of_sight(tiny_scene, tmp_path):
    cfg = _cfg(tiny_scene, _single_bs_iso)
    wall = trimesh.creation.box(extents=[1.0, 60.0, 40.0])
    wall.apply_translation([50.0, 0.0, 20.0])  # between the station (x = 0) and the cells x > 50.5
    xml = write_radio_scene(tmp_path / "wall", {"wall": (wall, "metal"), "ground": (ground_square(), "concrete")},
                            FC, 0.2)
    geom = geometry.SourceGeometry([geometry.Feature("building", shapely.box(49.5, -30, 50.5, 30), 1,
                                                     height_m=40.0, min_height_m=0.0, radio_material="metal")])
    ds = tile_layers(RadioScene.from_config(xml, cfg), cfg, geom, "r0c0").isel(bs=0, height=0)
    x = ds["x"].values
    behind = x > 50.5
    assert behind.any() and (~behind).any()
    assert not ds["los"].values[:, behind].any()
    assert ds["los"].values[:, ~behind].all()


def test_an_alley_narrower_than_a_cell_is_masked_in_fast_mode_and_the_map_says_so(tiny_scene, tmp_path):
    """Two metal blocks 2 m apart, the row of cell centres y = 0 in the alley between them (10 m
    cells): those cells have their centre outdoors and a fifth of their area (one of the outdoor
    mask's 4 sample rows). Fast mode masks them (the one-pass divides a cell's sums by its outdoor
    share); cell_masked and cell_outdoor_fraction say so, where cell_inside_building (the centre)
    cannot."""
    cfg = _cfg(tiny_scene, lambda raw: _single_bs_iso(raw, {"mode": "fast", "num_rays": 200_000,
                                                            "size_m": [80.0, 30.0]}))
    blocks = {}
    for name, y0, y1 in (("south", -20.0, -0.5), ("north", 1.5, 20.0)):
        b = trimesh.creation.box(extents=[60.0, y1 - y0, 30.0])
        b.apply_translation([60.0, (y0 + y1) / 2, 15.0])
        blocks[name] = (b, "metal")
    xml = write_radio_scene(tmp_path / "alley", {**blocks, "ground": (ground_square(), "concrete")}, FC, 0.2)
    geom = geometry.SourceGeometry([geometry.Feature("building", shapely.box(30, y0, 90, y1), i + 1, height_m=30.0,
                                                     min_height_m=0.0, radio_material="metal")
                                    for i, (y0, y1) in enumerate(((-20.0, -0.5), (1.5, 20.0)))])
    ds = tile_layers(RadioScene.from_config(xml, cfg), cfg, geom, "r0c0").isel(height=0)
    x, y = ds["x"].values, ds["y"].values
    row = int(np.argmin(np.abs(y)))
    assert y[row] == 0.0
    alley = (x > 30) & (x < 90)  # the cells along the alley: centres outdoors, 2 m of their 10 m outdoors
    assert alley.sum() == 6 and not ds["cell_inside_building"].values[row, alley].any()
    np.testing.assert_allclose(ds["cell_outdoor_fraction"].values[row, alley], 0.25)  # 1 of 4 sample rows
    assert ds["cell_masked"].values[row, alley].all() and not ds["cell_masked"].values[row, ~alley].any()
    assert not ds["has_path"].values[:, row, alley].any() and np.isnan(ds["rate_bps"].values[row, alley]).all()
    # the cells beside them, inside the blocks, are masked by their centre as before
    assert ds["cell_inside_building"].values[row + 1, alley].all() and ds["cell_masked"].values[row + 1, alley].all()
    # and the open cells before the blocks hold values
    assert ds["has_path"].values[:, row, ~alley].all()


def test_masked_cells_are_never_traced_and_empty_tiles_need_no_scene(tiny_built, tiny_scene):
    cfg, geom, _, out = tiny_built
    cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(
        region_m=[[-10.0, -15.0], [10.0, -15.0], [10.0, 15.0], [-10.0, 15.0]]))
    ds = tile_layers(RadioScene.from_config(meshes.radio_scene_file(out), cfg), cfg, geom, "r0c0")
    inside = ds["cell_inside_building"].values
    outside = ds["cell_outside_region"].values
    assert inside.any() and outside.any()
    masked = inside | outside[None]
    assert ds.attrs["cells_traced"] == int((~masked).sum())
    assert not ds["has_path"].values[:, masked].any()
    assert np.isnan(ds["path_gain_db"].values[:, masked]).all() and (ds["best_bs"].values[masked] == -1).all()
    empty = tile_layers(None, cfg, geom, "r3c3")  # outside the scene's tiling
    assert empty.sizes["y"] == 0 and empty.attrs["in_scene_tiling"] == 0


def test_equal_interferers_give_the_expected_sinr(tiny_scene):
    """Two identical stations at mirrored positions: at the midline each is the other's interferer,
    so SINR = S / (S_mean + N) with S_mean the mean beam gain (one antenna: the same gain)."""
    def edit(raw):
        _single_bs_iso(raw, ckm={"center_m": [0.0, 0.0], "size_m": [10.0, 10.0], "cell_size_m": 10.0})
        raw["base_stations"] = [dict(raw["base_stations"][0], name="a", position_m=[-50.0, 0.0, 20.0]),
                                dict(raw["base_stations"][0], name="b", position_m=[50.0, 0.0, 20.0])]
    cfg = _cfg(tiny_scene, edit)
    ds = tile_layers(RadioScene.from_config(None, cfg), cfg, geometry.SourceGeometry(), "r0c0")
    snr = 10 ** (float(ds["snr_db"].values.ravel()[0]) / 10)
    sinr = 10 ** (float(ds["sinr_db"].values.ravel()[0]) / 10)
    np.testing.assert_allclose(sinr, 1 / (1 + 1 / snr), rtol=1e-4)
    assert 0 <= int(ds["mcs_index"].values.ravel()[0]) and float(ds["rate_bps"].values.ravel()[0]) > 0


def _write_map(path, cfg, geom, radio, tiles):
    for t in tiles:
        ds = tile_layers(radio, cfg, geom, t)
        spec, coords, attrs = map_template(cfg, ds, ["sunny", "night"], provenance.attrs(cfg, "ckm_layers"))
        mosaic.ensure_template(path, cfg.ckm, spec, coords, attrs)
        mosaic.write_tile(path, cfg.ckm, t, ds)


def test_tile_backfills_in_any_order_equal_one_full_run(tiny_built, tiny_scene, tmp_path):
    """Random subsets of tiles, twice, in different orders, fill the same mosaic as one full run
    (a single tile with other chunking); a failed tile leaves the others intact and is rerun."""
    cfg, geom, _, out = tiny_built
    cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[3, 2], size_m=[45.0, 35.0]))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), cfg)
    tiles = scene_tiles(cfg.ckm)
    assert len(tiles) == 6 and chunk_shape(cfg.ckm) == (4, 3)
    rng = np.random.default_rng(7)
    first = list(rng.permutation(tiles))
    _write_map(tmp_path / "a.zarr", cfg, geom, radio, first[:3])
    partial = mosaic.open_map(tmp_path / "a.zarr").load()
    assert int(partial["tile_complete"].sum()) == 3
    _write_map(tmp_path / "a.zarr", cfg, geom, radio, first[3:] + first[:1])  # the rest, one twice
    _write_map(tmp_path / "b.zarr", cfg, geom, radio, list(rng.permutation(tiles)))
    full_cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[45.0, 35.0]))
    _write_map(tmp_path / "full.zarr", full_cfg, geom, RadioScene.from_config(meshes.radio_scene_file(out), full_cfg), ["r0c0"])
    a, b, full = (mosaic.open_map(tmp_path / f"{n}.zarr").load() for n in ("a", "b", "full"))
    assert a["tile_complete"].all() and b["tile_complete"].all()
    layers = [v for v in full.data_vars if v not in ("tile_complete", "tile_data_version")]
    xr.testing.assert_identical(a[layers].drop_attrs(), full[layers].drop_attrs())
    xr.testing.assert_identical(b[layers].drop_attrs(), full[layers].drop_attrs())
    assert np.isfinite(a["path_gain_db"].values).sum() > 20

    # A tile that fails after marking itself incomplete leaves every other chunk as it was.
    class Boom(RuntimeError):
        pass

    victim = tiles[4]
    ds = tile_layers(radio, cfg, geom, victim)
    bad = ds.assign(path_gain_db=ds["path_gain_db"] * np.nan)
    original = xr.Dataset.to_zarr

    def failing(self, *args, **kwargs):
        raise Boom("disk full")

    xr.Dataset.to_zarr = failing
    try:
        with pytest.raises(Boom):
            mosaic.write_tile(tmp_path / "a.zarr", cfg.ckm, victim, bad)
    finally:
        xr.Dataset.to_zarr = original
    after = mosaic.open_map(tmp_path / "a.zarr").load()
    sl = tile_slices(cfg.ckm, victim)
    others = np.ones(cfg.ckm.shape, bool)
    others[sl] = False
    assert not after["tile_complete"].values.all()
    np.testing.assert_array_equal(after["path_gain_db"].values[..., others], full["path_gain_db"].values[..., others])
    mosaic.write_tile(tmp_path / "a.zarr", cfg.ckm, victim, ds)  # simply rerun
    xr.testing.assert_identical(mosaic.open_map(tmp_path / "a.zarr").load()[layers].drop_attrs(),
                                full[layers].drop_attrs())


def test_tiles_with_the_default_diffraction_fill_one_map_in_any_order(tiny_built, tiny_scene, tmp_path):
    """With the default diffraction (wedge and edge on; the tiny scene turns them off): the same
    tiles in two orders, and one tile for the whole map, give the same map bit for bit. Two things
    moved the last bit of a few cells' delays before: paths of equal delay and interaction types
    (the scene's symmetric wedges) in the order Sionna's candidate generator returned them, which
    varies between runs on several threads (now sorted by object, primitive and vertices too), and
    the sums over a cell's paths, whose pairwise grouping followed the row's padding to the
    longest row of its PathSolver call, i.e. the tiling (now summed in path order)."""
    cfg, geom, _, out = tiny_built

    def tiled(raw, tiles):
        raw["ckm"].update(tiles=tiles, size_m=[45.0, 35.0])
        raw["ray_tracing"].update(diffraction=True, edge_diffraction=True)

    cfg = _cfg(tiny_scene, lambda raw: tiled(raw, [3, 2]))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), cfg)
    tiles = scene_tiles(cfg.ckm)
    _write_map(tmp_path / "a.zarr", cfg, geom, radio, tiles)
    _write_map(tmp_path / "b.zarr", cfg, geom, radio, list(np.random.default_rng(3).permutation(tiles)))
    full_cfg = _cfg(tiny_scene, lambda raw: tiled(raw, [1, 1]))
    _write_map(tmp_path / "full.zarr", full_cfg, geom, RadioScene.from_config(meshes.radio_scene_file(out), full_cfg),
               ["r0c0"])
    a, b, full = (mosaic.open_map(tmp_path / f"{n}.zarr").load() for n in ("a", "b", "full"))
    layers = [v for v in full.data_vars if v not in ("tile_complete", "tile_data_version")]
    for other in (b, full):
        xr.testing.assert_equal(a[layers].drop_attrs(), other[layers].drop_attrs())
    plain = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[45.0, 35.0]))
    without = tile_layers(RadioScene.from_config(meshes.radio_scene_file(out), plain), plain, geom, "r0c0")
    # diffraction reaches cells that LoS and reflections leave empty, and keeps every one they reach
    with_, plain_cells = np.isfinite(full["path_gain_db"].values), np.isfinite(without["path_gain_db"].values)
    assert (with_ | ~plain_cells).all()
    assert with_.sum() > plain_cells.sum()


def test_misaligned_regions_are_refused_and_weathers_share_maps(tiny_scene):
    cfg = _cfg(tiny_scene)
    assert map_groups(cfg) == {"sunny": ["sunny", "night"], "rainy": ["rainy"]}
    cfg2 = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[3, 2], size_m=[45.0, 35.0]))
    rows, cols = cfg2.ckm.shape
    covered = np.zeros((rows, cols), int)
    for t in scene_tiles(cfg2.ckm):
        sl = tile_slices(cfg2.ckm, t)
        covered[sl] += 1
        cy, cx = chunk_shape(cfg2.ckm)
        assert sl[0].start % cy == 0 and sl[1].start % cx == 0
    assert (covered == 1).all()


def test_path_gain_agrees_with_sionna_radio_map_solver_where_the_field_is_smooth(tiny_built, tiny_scene):
    """RadioMapSolver averages over each cell with an isotropic receiver; the layer is exact at the
    cell centre. Both are incoherent sums: the median difference is a fraction of a dB, with no
    bias; larger differences sit at shadow edges (docs/ckm.md)."""
    from simart_pipeline.ckm.radiomap import radio_map_path_gain_db

    cfg, geom, _, out = tiny_built
    cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[80.0, 60.0], cell_size_m=4.0))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), cfg)
    layer = tile_layers(radio, cfg, geom, "r0c0")["path_gain_db"].values[:, 0]
    rm = radio_map_path_gain_db(radio, cfg, cfg.ckm.heights[0], samples_per_tx=2 * 10**6)
    both = np.isfinite(layer) & np.isfinite(rm)
    assert both.mean() > 0.5
    diff = (rm - layer)[both]
    assert np.median(np.abs(diff)) < 0.5, np.median(np.abs(diff))
    assert abs(np.mean(diff)) < 0.5, np.mean(diff)


def test_radio_map_cross_check_follows_the_scenes_diffraction_switches(tiny_built, tiny_scene):
    """With ray_tracing.diffraction on, RadioMapSolver is asked for diffraction too: it reaches
    cells in the buildings' shadows that LoS and reflections leave empty, and keeps every cell
    they reach (where the scene's switches were dropped, both maps would be the same)."""
    from simart_pipeline.ckm.radiomap import radio_map_path_gain_db

    cfg, geom, _, out = tiny_built
    size = lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[80.0, 60.0], cell_size_m=4.0)  # noqa: E731
    plain = _cfg(tiny_scene, size)
    diffracting = _cfg(tiny_scene, lambda raw: (size(raw), raw.setdefault("ray_tracing", {}).update(
        diffraction=True, edge_diffraction=True)))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), plain)
    without = np.isfinite(radio_map_path_gain_db(radio, plain, plain.ckm.heights[0], samples_per_tx=10**6))
    with_ = np.isfinite(radio_map_path_gain_db(radio, diffracting, plain.ckm.heights[0], samples_per_tx=10**6))
    assert (with_ | ~without).all()          # nothing lost
    assert with_.sum() > without.sum()       # shadowed cells reached


def test_the_config_asks_for_the_second_pass_and_the_tile_says_what_it_did(tiny_built, tiny_scene):
    """ckm.diffraction_resample_factor reaches the solver through the tile: with diffraction on and
    few rays (point deposits), the tile records each station's second pass, the cells that had enough hits keep their
    gain, and only undersampled cells gain a value (most of them here)."""
    cfg, geom, _, out = tiny_built

    def fast(factor):
        return _cfg(tiny_scene, lambda raw: (raw["ckm"].update(tiles=[1, 1], cell_size_m=2.0, mode="fast", num_rays=5_000,
                                                                max_footprint_cells=1, diffraction_resample_factor=factor),
                                             raw["ray_tracing"].update(diffraction=True)))

    radio = RadioScene.from_config(meshes.radio_scene_file(out), fast(1))
    once, twice = tile_layers(radio, fast(1), geom, "r0c0"), tile_layers(radio, fast(4), geom, "r0c0")
    assert "second_pass_per_bs" not in once.attrs
    done = twice.attrs["second_pass_per_bs"]
    assert len(done) == len(cfg.base_stations) and all(p["factor"] == 4 for p in done)
    assert sum(p["undersampled_cells"] for p in done) > 0 and sum(p["new_samples"] for p in done) > 0
    kept = once["enough_hits"].values
    np.testing.assert_array_equal(twice["path_gain_db"].values[kept], once["path_gain_db"].values[kept])
    few = once["has_path"].values & ~kept
    assert not (twice["enough_hits"].values & ~kept & ~few).any()
    assert (twice["enough_hits"].values & few).sum() > 0  # measured: 60 of 76


def test_the_config_asks_for_the_lattice_second_pass_and_the_tile_says_what_it_did(tiny_built, tiny_scene):
    """ckm.lattice_resample_factor reaches the solver through the tile: with few rays the tile
    records each station's lattice second pass, the cells that had enough effective hits keep
    their gain bit for bit, and the undersampled ones get more hits."""
    cfg, geom, _, out = tiny_built

    def fast(factor):
        return _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], cell_size_m=2.0, mode="fast",
                                                              num_rays=5_000, lattice_resample_factor=factor))

    radio = RadioScene.from_config(meshes.radio_scene_file(out), fast(1))
    once, twice = tile_layers(radio, fast(1), geom, "r0c0"), tile_layers(radio, fast(8), geom, "r0c0")
    assert "lattice_second_pass_per_bs" not in once.attrs
    done = twice.attrs["lattice_second_pass_per_bs"]
    assert len(done) == len(cfg.base_stations) and all(p["factor"] == 8 for p in done)
    assert sum(p["undersampled_cells"] for p in done) > 0 and sum(p["new_rays"] for p in done) > 0
    eff = once["effective_count"].values
    kept = once["has_path"].values & (eff >= cfg.ckm.min_hits_for_power)
    np.testing.assert_array_equal(twice["path_gain_db"].values[kept], once["path_gain_db"].values[kept])
    few = once["has_path"].values & ~kept
    assert (twice["count"].values[few] > once["count"].values[few]).mean() > 0.5
    with pytest.raises(ValueError, match="lattice_resample_factor"):
        _cfg(tiny_scene, lambda raw: raw["ckm"].update(lattice_resample_factor=0))


def test_the_config_asks_for_the_diffuse_gather_and_the_tile_says_what_it_did(tiny_built, tiny_scene):
    """ckm.diffuse_gather reaches the solver through the tile with diffuse reflection on (every
    material given S = 0.3, as the benchmark's every-mechanism set): with few
    rays the tile records each station's gather (cells, photons, pairs), the cells with enough
    effective hits keep their gain bit for bit (the gather touches only the few-hit ones), and the
    gathered ones get more hits."""
    cfg, geom, _, out = tiny_built

    def fast(gather):
        def edit(raw):
            raw["ckm"].update(tiles=[1, 1], cell_size_m=2.0, mode="fast", num_rays=20_000, diffuse_gather=gather)
            raw.setdefault("ray_tracing", {})["diffuse_reflection"] = True
        return _cfg(tiny_scene, edit)

    radio = RadioScene.from_config(meshes.radio_scene_file(out), fast(False))
    for obj in radio.scene.objects.values():  # the ITU materials scatter nothing (S = 0)
        obj.radio_material.scattering_coefficient = 0.3
    off, on = tile_layers(radio, fast(False), geom, "r0c0"), tile_layers(radio, fast(True), geom, "r0c0")
    assert "diffuse_gather_per_bs" not in off.attrs
    done = on.attrs["diffuse_gather_per_bs"]
    assert len(done) == len(cfg.base_stations)
    assert sum(p["cells"] for p in done) > 0 and sum(p["pairs"] for p in done) > 0
    eff = off["effective_count"].values
    kept = off["has_path"].values & (eff >= 10.0)
    np.testing.assert_array_equal(on["path_gain_db"].values[kept], off["path_gain_db"].values[kept])
    few = off["has_path"].values & ~kept
    assert few.any() and (on["count"].values[few] > off["count"].values[few]).mean() > 0.5


def test_the_config_sets_the_fast_modes_ray_batch_and_the_layers_do_not_depend_on_it(tiny_built, tiny_scene,
                                                                                     monkeypatch):
    """ckm.batch_rays (memory), ckm.diffuse_connections and ckm.diffuse_gather reach the one-pass
    solver through the tile (null: the solver's own default), and the tile's layers are those of
    one batch: hit counts and masks equal, values to float64 summation order (the tiny scene's ray
    tracing has no diffuse reflection, so the connections and the gather change nothing)."""
    from simart_pipeline.ckm import one_pass as op

    _, geom, _, out = tiny_built
    seen = []
    solve = op.one_pass_moments
    monkeypatch.setattr(op, "one_pass_moments", lambda *a, **k: seen.append(
        (k["batch_rays"], k["diffuse_connections"], k["diffuse_gather"])) or solve(*a, **k))

    def fast(batch, connections=0.0, gather=False):
        return _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], cell_size_m=2.0, mode="fast",
                                                              num_rays=50_000, batch_rays=batch,
                                                              diffuse_connections=connections,
                                                              diffuse_gather=gather))

    radio = RadioScene.from_config(meshes.radio_scene_file(out), fast(None))
    one = tile_layers(radio, fast(None), geom, "r0c0")
    many = tile_layers(radio, fast(7_001, 2.0, True), geom, "r0c0")
    assert set(seen) == {(None, 0.0, False), (7_001, 2.0, True)}
    for name in ("has_path", "enough_hits", "count"):
        np.testing.assert_array_equal(many[name].values, one[name].values, err_msg=name)
    for name in ("path_gain_db", "rms_delay_spread_s", "toa_s"):
        np.testing.assert_allclose(many[name].values, one[name].values, rtol=1e-9, atol=0, err_msg=name)
    with pytest.raises(ValueError, match="batch_rays"):
        _cfg(tiny_scene, lambda raw: raw["ckm"].update(batch_rays=10))
    from simart_pipeline.config.ckm import Ckm

    assert Ckm().diffuse_connections == op.DEFAULT_DIFFUSE_CONNECTIONS  # the front's choice, in both places
    # the front's choice: where few-hit cells are many (the solver's own default is off: a direct
    # call gets what it asks for)
    assert Ckm().diffuse_gather == "auto" and _cfg(tiny_scene, lambda raw: None).ckm.diffuse_gather == "auto"
    assert _cfg(tiny_scene, lambda raw: raw["ckm"].update(diffuse_gather=False)).ckm.diffuse_gather is False
    with pytest.raises(ValueError, match="diffuse_gather"):
        _cfg(tiny_scene, lambda raw: raw["ckm"].update(diffuse_gather="sometimes"))
    with pytest.raises(ValueError, match="diffuse_connections"):
        _cfg(tiny_scene, lambda raw: raw["ckm"].update(diffuse_connections=-1))


def test_fast_mode_writes_the_same_layers_and_agrees_with_the_reference(tiny_built, tiny_scene):
    """ckm.mode: fast (one shoot-and-bounce pass) gives the same layers, names, units and
    definitions as the reference mode, and the same path gain to within ray-tube sampling."""
    cfg, geom, _, out = tiny_built
    ref_cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], cell_size_m=2.0))
    fast_cfg = _cfg(tiny_scene, lambda raw: raw["ckm"].update(tiles=[1, 1], cell_size_m=2.0, mode="fast",
                                                              num_rays=1_000_000))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), ref_cfg)
    ref = tile_layers(radio, ref_cfg, geom, "r0c0")
    fast = tile_layers(radio, fast_cfg, geom, "r0c0")
    assert set(ref.data_vars) == set(fast.data_vars)
    for name in ref.data_vars:
        assert ref[name].dims == fast[name].dims and ref[name].attrs.get("units") == fast[name].attrs.get("units"), name
    assert fast.attrs["mode"] == "fast" and np.isnan(fast["path_gain_coherent_db"].values).all()
    assert list(fast.attrs["rays_per_bs"]) == [1_000_000] * len(fast_cfg.base_stations)  # no adaptive rule
    both = np.isfinite(ref["path_gain_db"].values) & np.isfinite(fast["path_gain_db"].values)
    assert both.sum() > 50
    diff = np.abs(ref["path_gain_db"].values - fast["path_gain_db"].values)[both]
    assert np.median(diff) < 1.0, np.median(diff)
    assert (ref["los"].values == fast["los"].values)[both].mean() > 0.9
    indoor = ref["cell_inside_building"].values
    assert not fast["has_path"].values[:, indoor].any()
    # cell_masked is every mask the mode applied: the tile's in both; fast mode adds the cells less
    # than half outdoors (centre outdoors or not), which hold nothing; reference mode has no share
    tile_mask = indoor | ref["cell_outside_region"].values[None]
    np.testing.assert_array_equal(ref["cell_masked"].values, tile_mask)
    assert np.isnan(ref["cell_outdoor_fraction"].values).all()
    share = fast["cell_outdoor_fraction"].values
    assert ((share >= 0) & (share <= 1)).all()
    np.testing.assert_array_equal(fast["cell_masked"].values, tile_mask | (share < 0.5))
    assert not fast["has_path"].values[:, fast["cell_masked"].values].any()


def test_fast_mode_follows_the_scenes_diffraction_switch(tiny_built, tiny_scene):
    """ray_tracing.diffraction reaches the one-pass solver in fast mode (it was dropped once, so
    fast maps ignored the switch): the diffracting map keeps every cell of the plain one and
    reaches shadowed cells besides."""
    cfg, geom, _, out = tiny_built
    fast = lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[80.0, 60.0], cell_size_m=4.0, mode="fast",  # noqa: E731
                                         num_rays=1_000_000, min_hits_for_power=1)
    plain = _cfg(tiny_scene, fast)
    diffracting = _cfg(tiny_scene, lambda raw: (fast(raw), raw.setdefault("ray_tracing", {}).update(diffraction=True)))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), plain)
    without = np.isfinite(tile_layers(radio, plain, geom, "r0c0")["path_gain_db"].values)
    with_ = np.isfinite(tile_layers(radio, diffracting, geom, "r0c0")["path_gain_db"].values)
    assert (with_ | ~without).all()
    assert with_.sum() > without.sum()


def test_ckm_min_effective_hits_for_power_masks_by_the_effective_count_layer(tiny_built, tiny_scene):
    """ckm.min_effective_hits_for_power reaches the fast-mode layers: the masked map keeps a gain
    exactly where the default one does and the stored effective_count reaches the minimum (set
    to mask about a third of the cells), which never exceeds the hit count."""
    cfg, geom, _, out = tiny_built
    fast = lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[80.0, 60.0], cell_size_m=4.0, mode="fast",  # noqa: E731
                                         num_rays=300_000)
    plain = _cfg(tiny_scene, fast)
    radio = RadioScene.from_config(meshes.radio_scene_file(out), plain)
    a = tile_layers(radio, plain, geom, "r0c0")
    assert a["effective_count"].attrs["units"] == "1"
    ess = a["effective_count"].values
    minimum = float(np.percentile(ess[a["enough_hits"].values], 30))  # masks about a third
    strict = _cfg(tiny_scene, lambda raw: (fast(raw), raw["ckm"].update(min_effective_hits_for_power=minimum)))
    b = tile_layers(radio, strict, geom, "r0c0")
    expected = a["enough_hits"].values & (ess >= minimum)
    np.testing.assert_array_equal(b["enough_hits"].values, expected)
    np.testing.assert_array_equal(np.isfinite(b["path_gain_db"].values), expected)
    assert expected.sum() > 20 and (a["enough_hits"].values & ~expected).sum() > 0
    assert (ess[a["has_path"].values] <= a["count"].values[a["has_path"].values] + 1e-6).all()


def test_cells_with_few_ray_hits_hold_no_gain_toa_or_beams():
    """Fast-mode moments of three cells reached by 1, 4 and 5 ray hits: with min_count_for_power 5
    only the third keeps gain, ToA, LoS and beams; the others keep has_path and their count."""
    from simart_pipeline.ckm import moments as mom

    m = mom.CellMoments.zeros((3,), num_beams=2)
    m.count[:] = [1, 4, 5]
    m.power[:] = [1e-3, 1e-9, 1e-9]  # the one-hit cell: a single tube far above its neighbours
    m.los_power[:] = m.power
    m.min_delay_s[:] = 1e-6
    m.tau0_s[:] = 1e-6
    m.p_cos[:, :] = m.power[:, None]
    m.beam_power[:] = m.power[:, None] * [1.0, 2.0]
    L = mom.layers_from_moments(m, min_count_for_spread=10, min_count_for_power=5)
    assert L["has_path"].tolist() == [True, True, True]
    assert L["enough_hits"].tolist() == [False, False, True]
    assert L["count"].tolist() == [1, 4, 5]
    for name in ("path_gain_db", "path_loss_db", "toa_s", "mean_delay_s", "los_power_fraction",
                 "best_beam_gain_db"):
        assert np.isnan(L[name][:2]).all() and np.isfinite(L[name][2]), name
    assert np.isnan(L["beam_gain_db"][:2]).all() and np.isfinite(L["beam_gain_db"][2]).all()
    assert L["best_beam"].tolist() == [-1, -1, 1] and L["los"].tolist() == [False, False, True]
    assert L["path_gain_db"][2] == pytest.approx(-90.0)
    assert np.isnan(L["asa_deg"]).all()  # 5 hits: still below min_count_for_spread
    # The default keeps every cell that something reached (reference mode: each count is a path).
    assert np.isfinite(mom.layers_from_moments(m)["path_gain_db"]).all()


def test_spreads_need_effective_hits_where_one_ray_carries_the_cell():
    """Known answer: two cells of 12 ray hits each with the same delays, one of equal powers
    (effective count 12), one where a single hit carries 99 % of the power (effective count about
    1.02). With min_count_for_spread 10 both hold a delay spread (the second one's nearly that one
    ray's: a tenth of the first's); with min_effective_count_for_spread 10 only the first does,
    and its delay spread is the closed form; path gain, ToA and beams stay in both."""
    from simart_pipeline.ckm import moments as mom

    delays = 1e-6 + 1e-9 * np.arange(12)  # 12 hits 1 ns apart
    powers = np.array([np.full(12, 1e-10), np.r_[0.99e-9, np.full(11, 0.01e-9 / 11)]])
    m = mom.CellMoments.zeros((2,), num_beams=2)
    m.count[:] = 12
    m.power[:] = powers.sum(1)
    m.power_sq[:] = (powers**2).sum(1)
    m.min_delay_s[:] = delays[0]
    m.tau0_s[:] = delays[0]
    m.p_excess_delay_s[:] = (powers * (delays - delays[0])).sum(1)
    m.p_excess_delay2_s2[:] = (powers * (delays - delays[0]) ** 2).sum(1)
    m.p_cos[:, :] = m.power[:, None]
    m.beam_power[:] = m.power[:, None] * [1.0, 2.0]
    eff = m.power**2 / m.power_sq
    assert eff[0] == pytest.approx(12.0) and eff[1] == pytest.approx(1.0 / (0.99**2 + 0.01**2 / 11))
    loose = mom.layers_from_moments(m, min_count_for_spread=10, min_count_for_power=5)
    assert np.isfinite(loose["rms_delay_spread_s"]).all()
    assert loose["rms_delay_spread_s"][1] < 0.2 * loose["rms_delay_spread_s"][0]
    L = mom.layers_from_moments(m, min_count_for_spread=10, min_count_for_power=5,
                                min_effective_count_for_spread=10.0)
    assert L["rms_delay_spread_s"][0] == pytest.approx(1e-9 * np.sqrt((12**2 - 1) / 12))  # uniform, 1 ns apart
    for name in ("rms_delay_spread_s", "asa_deg", "zsd_deg", "mean_azimuth_arrival_deg"):
        assert np.isfinite(L[name][0]) and np.isnan(L[name][1]), name
    for name in ("path_gain_db", "toa_s", "mean_delay_s", "best_beam_gain_db"):
        assert np.isfinite(L[name]).all(), name
    assert L["enough_hits"].all() and L["best_beam"].tolist() == [1, 1]


def test_ckm_min_effective_hits_for_spread_masks_the_spreads_by_the_effective_count_layer(tiny_built, tiny_scene):
    """ckm.min_effective_hits_for_spread reaches the fast-mode layers: with the config's default
    (10) the delay and angle spreads and mean angles hold a value exactly where the hit count
    reaches min_hits_for_spread and the stored effective_count reaches 10; with 1 wherever the hit
    count does; gain and ToA are the same either way; the layer's attrs name both settings."""
    cfg, geom, _, out = tiny_built
    fast = lambda raw: raw["ckm"].update(tiles=[1, 1], size_m=[80.0, 60.0], cell_size_m=4.0, mode="fast",  # noqa: E731
                                         num_rays=300_000)
    default = _cfg(tiny_scene, fast)
    from simart_pipeline.ckm import one_pass as op

    assert default.ckm.min_effective_hits_for_spread == 10.0 == op.DEFAULT_MIN_EFFECTIVE_HITS_FOR_SPREAD
    loose = _cfg(tiny_scene, lambda raw: (fast(raw), raw["ckm"].update(min_effective_hits_for_spread=1.0)))
    radio = RadioScene.from_config(meshes.radio_scene_file(out), default)
    a, b = tile_layers(radio, default, geom, "r0c0"), tile_layers(radio, loose, geom, "r0c0")
    enough, count, ess = a["enough_hits"].values, a["count"].values, a["effective_count"].values
    by_count = enough & (count >= default.ckm.min_hits_for_spread)
    expected = by_count & (ess >= 10.0)
    assert expected.sum() > 20 and (by_count & ~expected).sum() > 0  # the rule bites on this scene
    for name in ("rms_delay_spread_s", "asa_deg", "zsa_deg", "mean_azimuth_arrival_deg"):
        np.testing.assert_array_equal(np.isfinite(a[name].values), expected, err_msg=name)
        np.testing.assert_array_equal(np.isfinite(b[name].values), by_count, err_msg=name)
    np.testing.assert_array_equal(a["path_gain_db"].values, b["path_gain_db"].values)
    assert "min_effective_hits_for_spread" in a["rms_delay_spread_s"].attrs["nan_means"]
    assert "min_effective_hits_for_spread" in a["mean_azimuth_arrival_deg"].attrs["nan_means"]
