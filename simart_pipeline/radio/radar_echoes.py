"""The base station as a monostatic OFDM radar: sensing CIRs and range-Doppler maps per radar frame.

Each base station with a ``radar`` transmits from its position and receives at its position plus
``receive_offset_m`` (its frame); the radio scene holds the static scene and every actor, placed
at the frame's instant with its velocity (:mod:`simart_pipeline.scene.actors`). One PathSolver call
per frame gives the sensing CIR, with the same path fields as the communication CIRs
(``docs/data-contract.md``). The range-Doppler map of a frame (:mod:`simart_pipeline.sensing.radar`)
takes the first antenna pair of the radar's array, the scene's OFDM numerology, ``num_symbols``
consecutive symbols from the frame's instant (paths held, phases advanced by each path's Doppler)
and the configured window. ``radar.diffuse_reflection`` (on by default) traces diffuse scattering
from every surface whose material scatters: the actors' bodies (``body.scattering_coefficient``,
0.3 by default); the static scene's ITU materials do not scatter, so its echoes are specular. The
direct transmitter-to-receiver coupling (a LoS path, present only
with a receive offset) is left out of the map, as a radar cancels it, but kept in the CIR.

Ground truth per frame and actor: range, radial velocity (positive receding), azimuth and
elevation of the centre of the actor body's bounding box, seen from the transmitter.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from simart_pipeline import clock, frames
from simart_pipeline.config import SceneConfig
from simart_pipeline.link.ofdm import subcarrier_offsets_hz
from simart_pipeline.radio.tracer import INVALID_DELAY_S, NO_ACTOR, RadioScene, merge_traced
from simart_pipeline.scene.actors import actor_poses
from simart_pipeline.sensing import radar
from simart_pipeline.sensing.streams import base_station_rotation
from simart_pipeline.vocabulary import interaction_flag_attrs

RADAR_MODEL_VERSION = 1
POWER_FLOOR_DB = -300.0  # a cell with no energy at all (no path) reads this, not -inf


def radar_base_stations(cfg: SceneConfig):
    return [b for b in cfg.base_stations if b.radar is not None]


def radar_scene(scene_xml, cfg: SceneConfig, weather: str) -> RadioScene:
    """The radio scene the radars trace in (their one array for transmit and receive); without
    actors: add them with :meth:`RadioScene.add_actors`."""
    radar_cfg = radar_base_stations(cfg)[0].radar
    solver = cfg.ray_tracing.model_copy(update={"diffuse_reflection": radar_cfg.diffuse_reflection})
    return RadioScene(scene_xml, frequency_hz=cfg.ofdm.carrier_frequency_hz, bandwidth_hz=cfg.ofdm.bandwidth_hz,
                      tx_array=radar_cfg.array, rx_array=radar_cfg.array, solver=solver, weather=weather,
                      weather_materials=cfg.materials.weather_table()[weather],
                      material_thickness_m=cfg.materials.thickness_m)


def radar_frames(radio: RadioScene | None, cfg: SceneConfig, traj: xr.Dataset | None) -> xr.DataTree:
    """One group ``/<base station>`` per radar: its sensing CIRs, range-Doppler maps and truth. A
    scene without radar traces nothing (``radio`` may then be None) and gets an empty tree."""
    groups = {bs.name: _one_radar(radio, cfg, traj, bs) for bs in radar_base_stations(cfg)}
    tree = xr.DataTree.from_dict({f"/{k}": v for k, v in groups.items()}) if groups else xr.DataTree()
    tree.attrs.update(radar_model_version=RADAR_MODEL_VERSION, radars=",".join(groups) or "none")
    if radio is not None:
        tree.attrs["weather"] = radio.weather
    return tree


def _one_radar(radio: RadioScene, cfg: SceneConfig, traj, bs) -> xr.Dataset:
    rc = bs.radar
    t_ns = clock.sample_times_ns(cfg.clock.duration_s, rc.rate_hz)
    n_t = len(t_ns)
    rot = base_station_rotation(bs)
    tx = np.asarray(bs.position_m, np.float64)
    rx = tx + rot.apply(np.asarray(rc.receive_offset_m, np.float64))
    ori = np.deg2rad(np.asarray(bs.orientation_deg, np.float64))[None]
    poses = actor_poses(radio.actors, traj, t_ns) if radio.actors else None
    parts = []
    for i in range(n_t):
        if poses is not None:
            radio.place_actors(poses, i)
        parts.append((np.array([i]), radio.trace(tx[None], ori, rx[None], rx_orientations_rad=ori)))
    p = merge_traced(parts, n_t)  # [frame, 1, path]

    offsets = subcarrier_offsets_hz(cfg.ofdm)
    symbol_times = np.arange(rc.num_symbols) * radar.symbol_duration_s(cfg.ofdm)
    maps = []
    for i in range(n_t):
        echo = p.valid[i, 0] & ~p.los[i, 0]
        h = radar.frame_response(p.a[i, 0, 0, 0, :], p.tau_s[i, 0], p.doppler_hz[i, 0], echo,
                                 cfg.ofdm.carrier_frequency_hz, offsets, symbol_times)
        maps.append(radar.range_doppler_map(h, cfg.ofdm, window=rc.window))
    rd = maps[0]
    power_db = np.stack([10 * np.log10(np.maximum(m.power, 10 ** (POWER_FLOOR_DB / 10))) for m in maps])

    names = [a.name for a in radio.actors]
    truth = {k: np.full((n_t, len(names)), np.nan) for k in ("range_m", "radial_velocity_mps", "azimuth_rad",
                                                             "elevation_rad")}
    for a, act in enumerate(radio.actors):
        centre = act.body.mesh.bounds.mean(axis=0)
        world = poses.to_world(a, slice(None), centre)  # [frame, 3]
        for k, v in radar.radar_truth(tx, world, poses.velocity_mps[a]).items():
            truth[k][:, a] = v

    zero = "where valid is false: 0"
    d = ("time", "path")
    ds = xr.Dataset({
        "a": (("time", "rx_ant", "tx_ant", "path"), p.a[:, :, 0], dict(
            units="1", long_name="complex path coefficient of the echo per antenna pair (propagation "
            "phase excluded, as in the communication CIRs)", fill_where_invalid=zero)),
        "tau_s": (d, p.tau_s[:, 0], dict(units="s", long_name="two-way propagation delay",
                                         fill_where_invalid=f"where valid is false: {INVALID_DELAY_S}")),
        "theta_t_rad": (d, p.theta_t[:, 0], dict(units="rad", long_name="zenith angle of departure (world)")),
        "phi_t_rad": (d, p.phi_t[:, 0], dict(units="rad", long_name="azimuth angle of departure (world)")),
        "theta_r_rad": (d, p.theta_r[:, 0], dict(units="rad", long_name="zenith angle of arrival (world)")),
        "phi_r_rad": (d, p.phi_r[:, 0], dict(units="rad", long_name="azimuth angle of arrival (world)")),
        "doppler_hz": (d, p.doppler_hz[:, 0], dict(units="Hz", long_name="Doppler shift from the moving "
                                                   "reflectors' velocities (the radar is static)")),
        "interaction": (("time", "depth", "path"), p.interaction[:, 0], dict(
            units="1", long_name="interaction type per bounce (0 after the last bounce)",
            **interaction_flag_attrs())),
        "interaction_actor": (("time", "depth", "path"), p.actor[:, 0], dict(
            units="1", long_name="index into the actor coordinate of the actor each bounce meets",
            fill_value_meaning=f"{NO_ACTOR}: the static scene, or no bounce")),
        "valid": (d, p.valid[:, 0], dict(long_name="the path exists")),
        "los": (d, p.los[:, 0], dict(long_name="direct transmitter-to-receiver coupling (not an echo; "
                                     "left out of the range-Doppler map)")),
        "range_doppler_power_db": (("time", "range_bin", "velocity_bin"), power_db.astype(np.float32), dict(
            units="dB", long_name="range-Doppler map: power relative to a unit transmit power "
            "(a single echo of path gain g exactly on a cell reads 10 log10 g there)",
            window=rc.window, num_symbols=rc.num_symbols, floor_db=POWER_FLOOR_DB,
            range_resolution_m=rd.range_resolution_m, velocity_resolution_mps=rd.velocity_resolution_mps,
            max_range_m=rd.max_range_m, max_radial_velocity_mps=rd.max_radial_velocity_mps,
            antenna_pair="the first receive and the first transmit antenna of the radar array")),
        **{f"actor_{k}": (("time", "actor"), v, dict(
            units={"range_m": "m", "radial_velocity_mps": "m s-1"}.get(k, "rad"),
            long_name=f"ground truth: {k.rsplit('_', 1)[0].replace('_', ' ')} of the centre of the actor "
            "body's bounding box seen from the transmitter" + (" (positive receding)" if "velocity" in k else "")))
           for k, v in truth.items()},
        "tx_position_m": ("axis", tx, dict(units="m", frame_id=frames.WORLD, long_name="transmit array centre")),
        "rx_position_m": ("axis", rx, dict(units="m", frame_id=frames.WORLD, long_name="receive array centre")),
    }, coords={
        "time": ("time", t_ns, {"units": "ns", "long_name": "radar frame start (shared clock)"}),
        "range_m": ("range_bin", rd.range_m, {"units": "m", "long_name": "one-way range c tau / 2"}),
        "radial_velocity_mps": ("velocity_bin", rd.radial_velocity_mps,
                                {"units": "m s-1", "long_name": "radial velocity, positive receding"}),
        "actor": ("actor", np.array(names, dtype=str)),
        "axis": ["x", "y", "z"],
    })
    ds.attrs.update(base_station=bs.name, radar_rate_hz=rc.rate_hz, monostatic=int(not any(rc.receive_offset_m)),
                    carrier_frequency_hz=cfg.ofdm.carrier_frequency_hz, bandwidth_hz=cfg.ofdm.bandwidth_hz,
                    symbol_duration_s=radar.symbol_duration_s(cfg.ofdm))
    return ds
