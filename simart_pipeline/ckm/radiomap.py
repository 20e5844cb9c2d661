"""Cross-check: the path-gain layer against Sionna RT's own RadioMapSolver on the same grid.

What to expect (docs/ckm.md): RadioMapSolver shoots rays from each transmitter and averages the
power of the rays that cross each cell, over the cell's area, with an isotropic receiver; the CKM's
reference layer is PathSolver's exact paths at the cell centre. Both are incoherent sums, so they
agree where the field varies slowly across a cell; they differ at shadow and reflection edges (a
cell half in shadow averages to half the power, a point is either lit or not), close to a
transmitter (the 1/d^2 law is convex: the cell average exceeds the centre value), and by
RadioMapSolver's Monte-Carlo noise where few rays reach a cell (cells with no ray read 0).
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.ckm.grid import cell_centres
from simart_pipeline.config import SceneConfig
from simart_pipeline.link.budget import power_db


def radio_map_path_gain_db(radio, cfg: SceneConfig, height_m: float, samples_per_tx: int = 10**6) -> np.ndarray:
    """RadioMapSolver path gain ``[bs, y, x]`` (dB; NaN where no ray reached a cell) on the CKM
    grid at ``height_m``, with the scene's solver switches and base-station arrays."""
    import sionna.rt as rt

    ck, rt_cfg = cfg.ckm, cfg.ray_tracing
    scene = radio.scene
    # Element to element, as the CKM layer: one element of the stations' pattern (without it,
    # RadioMapSolver would steer the whole array to boresight with uniform weights).
    array = cfg.base_stations[0].array
    tx_array, rx_array = scene.tx_array, scene.rx_array
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern=array.pattern, polarization=array.polarization)
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization=array.polarization)
    for i, b in enumerate(cfg.base_stations):
        scene.add(rt.Transmitter(f"rm_tx{i}", position=[float(v) for v in b.position_m],
                                 orientation=[float(v) for v in np.deg2rad(b.orientation_deg)],
                                 power_dbm=float(b.power_dbm)))
    try:
        rows, cols = ck.shape
        rm = rt.RadioMapSolver()(
            scene, center=[float(ck.center_m[0]), float(ck.center_m[1]), float(height_m)],
            orientation=[0.0, 0.0, 0.0], size=[cols * ck.cell_size_m, rows * ck.cell_size_m],
            cell_size=[ck.cell_size_m, ck.cell_size_m], samples_per_tx=samples_per_tx,
            max_depth=rt_cfg.max_depth, los=rt_cfg.los, specular_reflection=rt_cfg.specular_reflection,
            diffuse_reflection=rt_cfg.diffuse_reflection, refraction=rt_cfg.refraction,
            diffraction=rt_cfg.diffraction, edge_diffraction=rt_cfg.edge_diffraction, seed=rt_cfg.seed)
        gain = np.array(rm.path_gain)                     # [tx, cells_y, cells_x]
        centres = np.array(rm.cell_centers)               # [cells_y, cells_x, 3]
    finally:
        for i in range(len(cfg.base_stations)):
            scene.remove(f"rm_tx{i}")
        scene.tx_array, scene.rx_array = tx_array, rx_array
    y, x = cell_centres(ck)
    if gain.shape[1:] != (len(y), len(x)) or not (np.allclose(centres[:, 0, 1], y, atol=1e-3)
                                                   and np.allclose(centres[0, :, 0], x, atol=1e-3)):
        raise AssertionError(f"RadioMapSolver's grid {gain.shape[1:]} does not match the CKM grid "
                             f"{(len(y), len(x))}")
    return power_db(gain)
