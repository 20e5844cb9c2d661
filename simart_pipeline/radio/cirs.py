"""Channel impulse responses along the platforms' trajectories (the ``cirs`` asset's dataset).

Trajectory mode: at every instant of the radio clock, every base station transmits to every
platform; all (instant, platform) receivers go to the tracer together, so a whole session costs as
few PathSolver calls as memory allows. Layout: ``docs/data-contract.md``.

The same function replays a recorded trajectory (``mobility.replay``): the tracer sees only the
poses at the radio instants, so a replayed trajectory with the same poses gives the same CIRs.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline import clock, frames
from simart_pipeline.config import SceneConfig
from simart_pipeline.mobility.trajectory import poses_at
from simart_pipeline.radio.tracer import (INVALID_DELAY_S, NO_ACTOR, RX_NEAR_TX_M, RadioScene, TracedPaths,
                                          merge_traced)
from simart_pipeline.scene.actors import ActorPoses, actor_poses
from simart_pipeline.scene.geometry import SourceGeometry, inside_buildings
from simart_pipeline.vocabulary import AXES, LinkStatus, interaction_flag_attrs, link_status_flag_attrs

FILL_NOTE = "where valid is false: {}"


@dataclass
class LinkGeometry:
    """Where every device is at every radio-clock instant (world frame, ENU)."""

    time_ns: np.ndarray         # [T] int64
    rx_position_m: np.ndarray   # [T, P, 3]
    rx_velocity_mps: np.ndarray  # [T, P, 3]
    rx_orientation_rad: np.ndarray  # [T, P, 3] Sionna (yaw, pitch, roll)
    tx_position_m: np.ndarray   # [B, 3]
    tx_orientation_rad: np.ndarray  # [B, 3]

    def sha256(self) -> str:
        h = hashlib.sha256()
        for v in (self.time_ns, self.rx_position_m, self.rx_velocity_mps, self.rx_orientation_rad,
                  self.tx_position_m, self.tx_orientation_rad):
            v = np.ascontiguousarray(v)
            h.update(str((v.dtype.str, v.shape)).encode())
            h.update(v.tobytes())
        return h.hexdigest()


def link_geometry(cfg: SceneConfig, traj: xr.Dataset) -> LinkGeometry:
    """Sample every platform's pose at the radio clock; base stations are static."""
    t_ns = clock.sample_times_ns(cfg.clock.duration_s, cfg.clock.radio_rate_hz)
    T, P = len(t_ns), len(cfg.platforms)
    pos, vel, ori = np.zeros((T, P, 3)), np.zeros((T, P, 3)), np.zeros((T, P, 3))
    for j, p in enumerate(cfg.platforms):
        poses = poses_at(traj, p.name, t_ns)
        pos[:, j], vel[:, j] = poses["position_m"], poses["velocity_mps"]
        ori[:, j] = frames.sionna_orientation(Rotation.from_quat(poses["orientation_xyzw"]))
    bss = cfg.base_stations
    return LinkGeometry(t_ns, pos, vel, ori, np.array([b.position_m for b in bss], np.float64),
                        np.deg2rad(np.array([b.orientation_deg for b in bss], np.float64)))


def cir_content_sha256(radio: RadioScene, cfg: SceneConfig, lg: LinkGeometry) -> str:
    """Hash of everything the CIRs depend on: scene, materials, solver, arrays, device poses and
    powers (stored as ``cir_content_sha256``): two traces with the same hash have the same CIRs."""
    h = hashlib.sha256()
    h.update(radio.content_sha256().encode())
    h.update(lg.sha256().encode())
    h.update(repr([(b.name, b.power_dbm) for b in cfg.base_stations]).encode())
    h.update(repr([p.name for p in cfg.platforms]).encode())
    if radio.actors:  # where they are: the trajectory's poses (in lg) and the static actors' own
        h.update(repr([(p.name, p.body.model_dump()) for p in cfg.platforms]).encode())
        h.update(repr([a.model_dump() for a in cfg.static_actors]).encode())
        h.update(repr(cfg.ray_tracing.actor_max_excess_path_m).encode())
    return h.hexdigest()


def relevant_actors(radio: RadioScene, poses: ActorPoses, i: int, rx_m: np.ndarray, tx_m: np.ndarray,
                    own: str | None, max_excess_m: float | None) -> tuple[int, ...]:
    """Indices of the actors that matter to a receiver at ``rx_m`` at instant ``i``: not the body of
    its own platform ``own``, and (``max_excess_m`` not None) only those with a path via their
    bounding sphere at most ``max_excess_m`` longer than the direct distance from some transmitter
    of ``tx_m`` [B, 3].

    Why not the own body: the antenna sits on it, within a wavelength of its surface (2 cm above a
    car roof: a quarter wavelength at 3.5 GHz), where ray optics does not hold; that near field is
    what an antenna pattern measured on its platform describes. Traced, the roof would add a
    mirror path 4 cm longer than each direct one and hide every ground reflection."""
    out = []
    for a, act in enumerate(radio.actors):
        if act.platform is not None and act.platform == own:
            continue
        if max_excess_m is not None:
            c, r = poses.position_m[a, i], act.bounding_radius_m
            excess = (np.linalg.norm(tx_m - c, axis=1) + np.linalg.norm(rx_m - c) - 2 * r
                      - np.linalg.norm(tx_m - rx_m, axis=1))
            if excess.min() > max_excess_m:
                continue
        out.append(a)
    return tuple(out)


def trace_trajectory(radio: RadioScene, cfg: SceneConfig, traj: xr.Dataset,
                     geom: SourceGeometry | None = None) -> xr.Dataset:
    """Trace every (radio-clock instant, base station, platform) link.

    Without actors every receiver goes to the tracer at once. With actors in ``radio``, the
    receivers of one instant to which the same actors matter (:func:`relevant_actors`: never a
    platform's own body) share a call with those actors placed at that instant; every receiver to
    which none matters joins one call of the static scene.
    """
    lg = link_geometry(cfg, traj)
    T, P = lg.rx_position_m.shape[:2]
    store_points = cfg.ray_tracing.store_interaction_points
    rx_pos, rx_vel = lg.rx_position_m.reshape(-1, 3), lg.rx_velocity_mps.reshape(-1, 3)
    rx_ori = lg.rx_orientation_rad.reshape(-1, 3)
    calls: dict[tuple, list[int]] = {}  # (instant, actors shown) or () for the static scene -> receivers
    poses = actor_poses(radio.actors, traj, lg.time_ns) if radio.actors else None
    for i in range(T):
        for j, p in enumerate(cfg.platforms):
            seen = () if poses is None else relevant_actors(
                radio, poses, i, lg.rx_position_m[i, j], lg.tx_position_m, p.name,
                cfg.ray_tracing.actor_max_excess_path_m)
            calls.setdefault((i, seen) if seen else (), []).append(i * P + j)
    parts = []
    for key, idx in sorted(calls.items(), key=lambda kv: kv[1][0]):
        if radio.actors:
            radio.place_actors(poses, key[0] if key else 0,
                               hidden=set(range(len(radio.actors))) - set(key[1] if key else ()))
        idx = np.asarray(idx)
        parts.append((idx, radio.trace(lg.tx_position_m, lg.tx_orientation_rad, rx_pos[idx], rx_vel[idx],
                                       rx_ori[idx], with_vertices=store_points)))
    paths = merge_traced(parts, T * P)
    ds = cir_dataset(radio, cfg, lg, paths, geom)
    ds.attrs["cir_content_sha256"] = cir_content_sha256(radio, cfg, lg)
    ds.attrs["trace_calls"] = len(parts)
    return ds


def cir_dataset(radio: RadioScene, cfg: SceneConfig, lg: LinkGeometry, paths: TracedPaths,
                geom: SourceGeometry | None = None) -> xr.Dataset:
    """Arrange traced paths of receivers ``[T*P]`` x transmitters ``[B]`` as (time, link, path)."""
    bss, plats = cfg.base_stations, cfg.platforms
    T, P = lg.rx_position_m.shape[:2]
    B = len(bss)
    n_path = paths.tau_s.shape[-1]

    def per_link(v):  # [T*P, B, ...] -> [T, B*P, ...]
        v = v.reshape(T, P, B, *v.shape[2:])
        return np.swapaxes(v, 1, 2).reshape(T, B * P, *v.shape[3:])

    a = paths.a.reshape(T, P, paths.a.shape[1], B, paths.a.shape[3], n_path)
    a = a.transpose(0, 3, 1, 2, 4, 5).reshape(T, B * P, paths.a.shape[1], paths.a.shape[3], n_path)
    link_tx = np.repeat(np.arange(B), P)
    link_rx = np.tile(np.arange(P), B)
    rx_pos_l = lg.rx_position_m[:, link_rx]                      # [T, L, 3]
    tx_pos_l = np.ascontiguousarray(np.broadcast_to(lg.tx_position_m[link_tx], rx_pos_l.shape))
    valid = per_link(paths.valid)
    num_valid = valid.sum(-1).astype(np.int32)
    no_path = num_valid == 0
    near = np.linalg.norm(rx_pos_l - tx_pos_l, axis=-1) < RX_NEAR_TX_M
    if geom is not None:
        inside = inside_buildings(geom, rx_pos_l[..., 0], rx_pos_l[..., 1], rx_pos_l[..., 2])
    else:
        inside = np.zeros(near.shape, bool)
    usable = ~(no_path | near | inside)
    status = (no_path * LinkStatus.NO_PATH | inside * LinkStatus.RX_INSIDE_BUILDING
              | near * LinkStatus.RX_NEAR_TX).astype(np.uint8)

    zero_fill = FILL_NOTE.format(0)
    angle = dict(units="rad", fill_where_invalid=zero_fill)
    d3 = ("time", "link", "path")
    data = {
        "a": (("time", "link", "rx_ant", "tx_ant", "path"), a, dict(
            units="1", long_name="complex path coefficient per antenna pair, excluding the "
            "propagation phase exp(-j 2 pi f tau); abs(a)**2 is the path gain",
            fill_where_invalid=zero_fill)),
        "tau_s": (d3, per_link(paths.tau_s), dict(
            units="s", long_name="absolute propagation delay",
            fill_where_invalid=FILL_NOTE.format(INVALID_DELAY_S))),
        "theta_t_rad": (d3, per_link(paths.theta_t), dict(long_name="zenith angle of departure (world)", **angle)),
        "phi_t_rad": (d3, per_link(paths.phi_t), dict(long_name="azimuth angle of departure (world)", **angle)),
        "theta_r_rad": (d3, per_link(paths.theta_r), dict(long_name="zenith angle of arrival (world)", **angle)),
        "phi_r_rad": (d3, per_link(paths.phi_r), dict(long_name="azimuth angle of arrival (world)", **angle)),
        "doppler_hz": (d3, per_link(paths.doppler_hz), dict(
            units="Hz", long_name="Doppler shift from the devices' velocities", fill_where_invalid=zero_fill)),
        "interaction": (("time", "link", "depth", "path"), per_link(paths.interaction), dict(
            units="1", long_name="interaction type per bounce (0 after the last bounce)",
            **interaction_flag_attrs())),
        "valid": (d3, valid, dict(long_name="the path exists (every other per-path value is a fill "
                                  "where this is false)")),
        "los": (d3, per_link(paths.los), dict(long_name="valid line-of-sight path")),
        "num_valid_paths": (("time", "link"), num_valid, dict(units="1", long_name="number of valid paths")),
        "link_no_path": (("time", "link"), no_path, dict(long_name="the link has no valid path")),
        "link_rx_near_tx": (("time", "link"), near, dict(
            long_name=f"receiver within {RX_NEAR_TX_M} m of the transmitter (Sionna RT drops the "
            "line of sight there: paths incomplete)")),
        "link_rx_inside_building": (("time", "link"), inside, dict(
            long_name="receiver inside a building's volume (paths, if any, cross walls)")),
        "link_usable": (("time", "link"), usable, dict(
            long_name="the link has paths and none of the flags above: KPIs use only these")),
        "link_status": (("time", "link"), status, dict(
            units="1", long_name="why a link is not usable (bit flags; 0: usable)",
            **link_status_flag_attrs())),
        "tx_position_m": (("time", "link", "axis"), tx_pos_l,
                          dict(units="m", long_name="transmit array centre", frame_id="world")),
        "rx_position_m": (("time", "link", "axis"), rx_pos_l,
                          dict(units="m", long_name="receive array centre", frame_id="world")),
        "tx_velocity_mps": (("time", "link", "axis"), np.zeros_like(tx_pos_l),
                            dict(units="m s-1", long_name="transmitter velocity (base stations are "
                                 "static)", frame_id="world")),
        "rx_velocity_mps": (("time", "link", "axis"), lg.rx_velocity_mps[:, link_rx],
                            dict(units="m s-1", long_name="receiver velocity", frame_id="world")),
        "tx_orientation_rad": (("link", "euler"), lg.tx_orientation_rad[link_tx], dict(
            units="rad", long_name="transmitter orientation (Sionna: yaw about z, pitch about y, "
            "roll about x)")),
        "rx_orientation_rad": (("time", "link", "euler"), lg.rx_orientation_rad[:, link_rx], dict(
            units="rad", long_name="receiver orientation (Sionna: yaw about z, pitch about y, "
            "roll about x)")),
        "tx_power_dbm": ("link", np.array([bss[i].power_dbm for i in link_tx], np.float64),
                         dict(units="dBm", long_name="transmit power")),
        "tx_ant_position_m": (("tx_ant", "axis"), radio.array_positions_m("tx"),
                              dict(units="m", long_name="antenna positions in the transmitter's frame")),
        "rx_ant_position_m": (("rx_ant", "axis"), radio.array_positions_m("rx"),
                              dict(units="m", long_name="antenna positions in the receiver's frame")),
    }
    if paths.actor is not None:
        data["interaction_actor"] = (("time", "link", "depth", "path"), per_link(paths.actor), dict(
            units="1", long_name="index into the actor coordinate of the actor each bounce interacts "
            "with (its kind: interaction)", fill_value_meaning=f"{NO_ACTOR}: the static scene, or no "
            "bounce"))
    if paths.vertices_m is not None:
        data["interaction_point_m"] = (("time", "link", "depth", "path", "axis"), per_link(paths.vertices_m), dict(
            units="m", long_name="interaction point of each bounce", frame_id="world",
            fill_where_invalid=FILL_NOTE.format(0) + ", and after the path's last bounce"))
    ds = xr.Dataset(data, coords={
        "time": ("time", lg.time_ns, {"units": "ns", "long_name": "simulated time (radio clock)"}),
        "link": np.arange(B * P),
        "tx": ("link", [bss[i].name for i in link_tx]),
        "rx": ("link", [plats[j].name for j in link_rx]),
        "path": np.arange(n_path),
        "depth": np.arange(paths.interaction.shape[2]),
        "axis": AXES,
        "euler": ["yaw", "pitch", "roll"],
        "actor": ("actor", np.array([a.name for a in radio.actors], dtype=str),
                  dict(long_name="actors in the radio scene (scene.actors order)")),
    })
    rt = cfg.ray_tracing
    ds.attrs.update(
        carrier_frequency_hz=cfg.ofdm.carrier_frequency_hz, bandwidth_hz=cfg.ofdm.bandwidth_hz,
        radio_rate_hz=cfg.clock.radio_rate_hz, weather=radio.weather,
        radio_materials=str(radio.radio_materials()),
        weather_material_overrides=str(radio.material_overrides),
        solver="sionna.rt.PathSolver(deterministic=True), synthetic_array=True",
        solver_max_depth=rt.max_depth, solver_samples_per_src=rt.samples_per_src,
        solver_seed=rt.seed, solver_los=int(rt.los),
        solver_specular_reflection=int(rt.specular_reflection),
        solver_diffuse_reflection=int(rt.diffuse_reflection), solver_refraction=int(rt.refraction),
        solver_diffraction=int(rt.diffraction), solver_edge_diffraction=int(rt.edge_diffraction),
        path_order="valid first, then delay, then interaction sequence",
        channel_reconstruction="H_ij(f) = sum_p a[i, j, p] exp(-j 2 pi f tau_p), f the absolute "
        "frequency; build it in float64 (simart_pipeline.link.ofdm)",
        **{f"tx_array_{k}": str(v) for k, v in bss[0].array.model_dump().items()},
        **{f"rx_array_{k}": str(v) for k, v in plats[0].array.model_dump().items()},
    )
    return ds

