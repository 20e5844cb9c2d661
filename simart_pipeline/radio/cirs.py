"""Channel impulse responses along the platforms' trajectories (the ``cirs`` asset's dataset).

Trajectory mode: at every instant of the radio clock, every base station transmits to every
platform; all (instant, platform) receivers go to the tracer together, so a whole session costs as
few PathSolver calls as the receiver batch size allows. Layout: ``docs/data-contract.md``.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import clock, frames
from simart_pipeline.config import SceneConfig
from simart_pipeline.mobility.trajectory import poses_at
from simart_pipeline.radio.tracer import RX_NEAR_TX_M, RadioScene
from simart_pipeline.scene.geometry import SourceGeometry, inside_buildings

INTERACTION_FLAGS = {"none": 0, "specular": 1, "diffuse": 2, "refraction": 4, "diffraction": 8}


def trace_trajectory(radio: RadioScene, cfg: SceneConfig, traj: xr.Dataset,
                     geom: SourceGeometry | None = None) -> xr.Dataset:
    """Trace every (radio-clock instant, base station, platform) link."""
    t_ns = clock.sample_times_ns(cfg.clock.duration_s, cfg.clock.radio_rate_hz)
    bss, plats = cfg.base_stations, cfg.platforms
    T, B, P = len(t_ns), len(bss), len(plats)
    pos = np.zeros((T, P, 3))
    vel = np.zeros((T, P, 3))
    ori = np.zeros((T, P, 3))
    for j, p in enumerate(plats):
        poses = poses_at(traj, p.name, t_ns)
        pos[:, j], vel[:, j] = poses["position_m"], poses["velocity_mps"]
        ori[:, j] = frames.sionna_orientation(Rotation.from_quat(poses["orientation_xyzw"]))
    tx_pos = np.array([b.position_m for b in bss], dtype=np.float64)
    tx_ori = np.deg2rad(np.array([b.orientation_deg for b in bss], dtype=np.float64))
    paths = radio.trace(tx_pos, tx_ori, pos.reshape(-1, 3), vel.reshape(-1, 3), ori.reshape(-1, 3))
    n_path = paths.tau_s.shape[-1]

    def per_link(v):  # [T*P, B, ...] -> [T, B*P, ...]
        v = v.reshape(T, P, B, *v.shape[2:])
        return np.swapaxes(v, 1, 2).reshape(T, B * P, *v.shape[3:])

    a = paths.a.reshape(T, P, paths.a.shape[1], B, paths.a.shape[3], n_path)
    a = a.transpose(0, 3, 1, 2, 4, 5).reshape(T, B * P, paths.a.shape[1], paths.a.shape[3], n_path)
    link_tx = np.repeat(np.arange(B), P)
    link_rx = np.tile(np.arange(P), B)
    rx_pos_l = pos[:, link_rx]                      # [T, L, 3]
    tx_pos_l = np.broadcast_to(tx_pos[link_tx], rx_pos_l.shape)
    valid = per_link(paths.valid)
    num_valid = valid.sum(-1).astype(np.int32)
    near = np.linalg.norm(rx_pos_l - tx_pos_l, axis=-1) < RX_NEAR_TX_M
    if geom is not None:
        inside = inside_buildings(geom, rx_pos_l[..., 0], rx_pos_l[..., 1], rx_pos_l[..., 2])
    else:
        inside = np.zeros(near.shape, bool)
    angle_attrs = dict(units="rad", nan_means="no path (valid is false)")
    d3 = ("time", "link", "path")
    ds = xr.Dataset(
        {
            "a": (("time", "link", "rx_ant", "tx_ant", "path"), a,
                  dict(units="1", long_name="path coefficient per antenna pair, excluding the "
                       "propagation phase exp(-j 2 pi f tau); abs(a)**2 is the path gain")),
            "tau_s": (d3, per_link(paths.tau_s), dict(units="s", long_name="propagation delay",
                                                      nan_means="no path (valid is false)")),
            "theta_t_rad": (d3, per_link(paths.theta_t), dict(long_name="zenith angle of departure (world)", **angle_attrs)),
            "phi_t_rad": (d3, per_link(paths.phi_t), dict(long_name="azimuth angle of departure (world)", **angle_attrs)),
            "theta_r_rad": (d3, per_link(paths.theta_r), dict(long_name="zenith angle of arrival (world)", **angle_attrs)),
            "phi_r_rad": (d3, per_link(paths.phi_r), dict(long_name="azimuth angle of arrival (world)", **angle_attrs)),
            "doppler_hz": (d3, per_link(paths.doppler_hz), dict(units="Hz", long_name="Doppler shift",
                                                                nan_means="no path (valid is false)")),
            "interaction": (("time", "link", "depth", "path"), per_link(paths.interaction),
                            dict(units="1", long_name="interaction type per bounce",
                                 flag_values=np.array(list(INTERACTION_FLAGS.values()), np.uint8),
                                 flag_meanings=" ".join(INTERACTION_FLAGS))),
            "valid": (d3, valid, dict(long_name="the path exists")),
            "los": (d3, per_link(paths.los), dict(long_name="valid line-of-sight path")),
            "num_valid_paths": (("time", "link"), num_valid, dict(units="1", long_name="number of valid paths")),
            "link_no_path": (("time", "link"), num_valid == 0, dict(long_name="the link has no valid path")),
            "link_rx_near_tx": (("time", "link"), near, dict(
                long_name=f"receiver within {RX_NEAR_TX_M} m of the transmitter (Sionna drops LoS)")),
            "link_rx_inside_building": (("time", "link"), inside, dict(
                long_name="receiver inside a building's volume")),
            "tx_position_m": (("time", "link", "axis"), np.ascontiguousarray(tx_pos_l),
                              dict(units="m", long_name="transmit array centre", frame_id="world")),
            "rx_position_m": (("time", "link", "axis"), rx_pos_l,
                              dict(units="m", long_name="receive array centre", frame_id="world")),
            "rx_velocity_mps": (("time", "link", "axis"), vel[:, link_rx],
                                dict(units="m s-1", long_name="receiver velocity", frame_id="world")),
            "tx_orientation_rad": (("link", "euler"), tx_ori[link_tx],
                                   dict(units="rad", long_name="transmitter orientation (Sionna: yaw about z, "
                                        "pitch about y, roll about x)")),
            "tx_power_dbm": ("link", np.array([bss[i].power_dbm for i in link_tx], np.float64),
                             dict(units="dBm", long_name="transmit power")),
            "tx_ant_position_m": (("tx_ant", "axis"), radio.array_positions_m("tx"),
                                  dict(units="m", long_name="antenna positions in the transmitter's frame")),
            "rx_ant_position_m": (("rx_ant", "axis"), radio.array_positions_m("rx"),
                                  dict(units="m", long_name="antenna positions in the receiver's frame")),
        },
        coords={
            "time": ("time", t_ns, {"units": "ns", "long_name": "simulated time (radio clock)"}),
            "link": np.arange(B * P),
            "tx": ("link", [bss[i].name for i in link_tx]),
            "rx": ("link", [plats[j].name for j in link_rx]),
            "path": np.arange(n_path),
            "depth": np.arange(paths.interaction.shape[2]),
            "axis": ["x", "y", "z"],
            "euler": ["yaw", "pitch", "roll"],
        },
    )
    rt = cfg.ray_tracing
    ds.attrs.update(
        carrier_frequency_hz=cfg.ofdm.carrier_frequency_hz, bandwidth_hz=cfg.ofdm.bandwidth_hz,
        radio_rate_hz=cfg.clock.radio_rate_hz, weather=radio.weather,
        radio_materials=str(radio.radio_materials()),
        weather_material_overrides=str(radio.material_overrides),
        solver="sionna.rt.PathSolver (synthetic_array=True)", solver_max_depth=rt.max_depth,
        solver_samples_per_src=rt.samples_per_src, solver_seed=rt.seed,
        solver_los=int(rt.los), solver_specular_reflection=int(rt.specular_reflection),
        solver_diffuse_reflection=int(rt.diffuse_reflection), solver_refraction=int(rt.refraction),
        path_order="valid first, then delay, then interaction sequence",
        **{f"tx_array_{k}": str(v) for k, v in bss[0].array.model_dump().items()},
        **{f"rx_array_{k}": str(v) for k, v in plats[0].array.model_dump().items()},
    )
    return ds
