"""The cost of moving actors, and the error of the rule that leaves far actors out of a trace.

    python -m benchmarks.actors [SCENE_DIR] [--out results.json] [--parked 12] [--thresholds M ...]

On one scene (default: the demo), measured side by side in one process after a warm-up of each:

- sensing: every rendered camera and LiDAR with the scene's actors and without any (bodies off),
  seconds per frame and the ratio, all together in the first weather and one sensor at a time in
  every weather of the scene (frames per second per sensor and weather);
- ray tracing: the ``cirs`` trace of the whole session with actors and without, seconds per radio
  instant, solver calls and the ratio;
- the skip rule (``ray_tracing.actor_max_excess_path_m``): on the scene plus ``--parked`` parked
  cars at seeded random outdoor spots of the CKM area, traces with several thresholds against the
  trace that keeps every actor in every call (but each platform's own body, never in its links); per link and instant, the difference of the total path
  gain (dB, p50 / p95 / max over links with paths), the links that gain or lose every path, and
  the time of each.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DEMO, build_scene
from simart_pipeline import engine
from simart_pipeline.config import load_scene_config
from simart_pipeline.mobility.trajectory import build_trajectory
from simart_pipeline.radio import cirs as radio_cirs
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.scene import actors, meshes
from simart_pipeline.sensing.sensor_frames import render_sensor_frames


def _without_bodies(cfg):
    off = lambda d: d.model_copy(update={"body": d.body.model_copy(update={"mesh": "none"})})  # noqa: E731
    return cfg.model_copy(update={"platforms": tuple(off(p) for p in cfg.platforms),
                                  "static_actors": tuple(off(a) for a in cfg.static_actors)})


def _with_parked_cars(cfg, geom, n: int):
    """``cfg`` with ``n`` parked cars at seeded random spots of the CKM area outside buildings."""
    from simart_pipeline.config import StaticActor
    from simart_pipeline.scene.geometry import inside_buildings

    rng = np.random.default_rng(0)
    half = np.array(cfg.ckm.size_m) / 2
    cars = []
    while len(cars) < n:
        x, y = np.array(cfg.ckm.center_m) + rng.uniform(-half, half)
        if not inside_buildings(geom, np.array([x]), np.array([y]), np.array([1.0]))[0]:
            cars.append(StaticActor(name=f"parked{len(cars)}", kind="ground_vehicle", position_m=(x, y, 0.0),
                                    yaw_deg=float(rng.uniform(0, 360))))
    return cfg.model_copy(update={"static_actors": cfg.static_actors + tuple(cars)})


def _only_sensor(cfg, device: str, sensor: str):
    """``cfg`` keeping one camera or LiDAR (``device``/``sensor``) and no other rendered sensor."""
    def keep(d):
        return d.model_copy(update={"sensors": tuple(s for s in d.sensors if s.kind not in ("camera", "lidar")
                                                     or (d.name, s.name) == (device, sensor))})
    return cfg.model_copy(update={"platforms": tuple(keep(p) for p in cfg.platforms),
                                  "base_stations": tuple(keep(b) for b in cfg.base_stations)})


def _rendered_frames(tree, stream: str | None = None) -> int:
    return sum(node.sizes["time"] for node in tree.subtree
               if node.has_data and ("rgb" in node.data_vars or "range_m" in node.data_vars)
               and (stream is None or node.path == stream))


def _sensing(scene_meshes, traj, cfg, bare, scene_dir) -> dict:
    """Every rendered sensor in every weather of the scene, with the actors and without (bodies
    off), one sensor at a time: ms per frame, frames per second and the with/without ratio; and all
    sensors together in the first weather (the ``sensor_frames`` asset's work)."""
    rendered = [(d.name, s.name, s.kind) for d in (*cfg.platforms, *cfg.base_stations) for s in d.sensors
                if s.kind in ("camera", "lidar")]
    weather0 = cfg.weathers[0]
    with_s, tree = _timed(lambda: render_sensor_frames(scene_meshes, traj, cfg, weather0, scene_dir))
    without_s, _ = _timed(lambda: render_sensor_frames(scene_meshes, traj, bare, weather0, scene_dir))
    n_frames = _rendered_frames(tree)
    out = {"camera_and_lidar_streams": len(rendered), "frames": n_frames, "weather": weather0,
           "with_actors_s": round(with_s, 3), "without_actors_s": round(without_s, 3),
           "ms_per_frame_with": round(1e3 * with_s / max(n_frames, 1), 2),
           "ms_per_frame_without": round(1e3 * without_s / max(n_frames, 1), 2),
           "ratio": round(with_s / without_s, 3), "per_sensor": []}
    for device, sensor, kind in rendered:
        one, one_bare = _only_sensor(cfg, device, sensor), _only_sensor(bare, device, sensor)
        for weather in cfg.weathers:
            w_s, t = _timed(lambda: render_sensor_frames(scene_meshes, traj, one, weather, scene_dir))
            wo_s, _ = _timed(lambda: render_sensor_frames(scene_meshes, traj, one_bare, weather, scene_dir))
            n = max(_rendered_frames(t, f"/{device}/{sensor}"), 1)
            out["per_sensor"].append({
                "stream": f"/{device}/{sensor}", "kind": kind, "weather": weather, "frames": n,
                "ms_per_frame_with": round(1e3 * w_s / n, 2), "ms_per_frame_without": round(1e3 * wo_s / n, 2),
                "frames_per_s_with": round(n / w_s, 1), "frames_per_s_without": round(n / wo_s, 1),
                "ratio": round(w_s / wo_s, 3)})
    return out


def _mean_placed(cfg, traj, scene_xml, scene_dir, threshold) -> float:
    """Actors that matter to a receiver at an instant under the skip rule, on average."""
    radio = RadioScene.from_config(scene_xml, cfg)
    radio.add_actors(actors.scene_actors(cfg, scene_dir))
    lg = radio_cirs.link_geometry(cfg, traj)
    poses = actors.actor_poses(radio.actors, traj, lg.time_ns)
    counts = [len(radio_cirs.relevant_actors(radio, poses, i, lg.rx_position_m[i, j], lg.tx_position_m, p.name,
                                             threshold))
              for i in range(len(lg.time_ns)) for j, p in enumerate(cfg.platforms)]
    return float(np.mean(counts))


def _timed(fn, repeat=2):
    fn()  # warm-up: kernel compilation
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _gain_db(ds):
    g = (np.abs(ds["a"].values) ** 2).sum(axis=(2, 3, 4))  # [time, link]
    return np.where(g > 0, 10 * np.log10(np.maximum(g, 1e-300)), np.nan)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir", nargs="?", default=str(DEMO))
    ap.add_argument("--out", type=Path)
    ap.add_argument("--parked", type=int, default=12, help="parked cars added for the skip rule")
    ap.add_argument("--thresholds", type=float, nargs="+", metavar="M",
                    help="skip-rule thresholds to measure (m; default: the config's, 50, 10 and 1)")
    args = ap.parse_args(argv)
    scene_dir = Path(args.scene_dir)
    cfg = load_scene_config(scene_dir)
    bare = _without_bodies(cfg)
    variant = engine.init()
    with tempfile.TemporaryDirectory() as tmp:
        geom, scene_xml = build_scene(cfg, scene_dir, Path(tmp) / "pm")
        scene_meshes = meshes.load(Path(tmp) / "pm")
        traj = build_trajectory(cfg, scene_dir, geom=geom)
        result = {"scene": cfg.name, "variant": variant,
                  "actors": [a.name for a in actors.scene_actors(cfg, scene_dir)]}

        result["sensing"] = _sensing(scene_meshes, traj, cfg, bare, scene_dir)

        def trace(c, max_excess="config"):
            if max_excess != "config":
                c = c.model_copy(update={"ray_tracing": c.ray_tracing.model_copy(
                    update={"actor_max_excess_path_m": max_excess})})
            radio = RadioScene.from_config(scene_xml, c)
            radio.add_actors(actors.scene_actors(c, scene_dir))
            return radio_cirs.trace_trajectory(radio, c, traj, geom)

        with_s, ds_rule = _timed(lambda: trace(cfg), repeat=1)
        without_s, ds_bare = _timed(lambda: trace(bare), repeat=1)
        T = ds_rule.sizes["time"]
        result["ray_tracing"] = {
            "instants": T, "links": ds_rule.sizes["link"],
            "with_actors_s": round(with_s, 3), "without_actors_s": round(without_s, 3),
            "ms_per_instant_with": round(1e3 * with_s / T, 1), "ms_per_instant_without": round(1e3 * without_s / T, 1),
            "solver_calls_with": int(ds_rule.attrs["trace_calls"]), "solver_calls_without": int(ds_bare.attrs["trace_calls"]),
            "ratio": round(with_s / without_s, 3),
            "paths_via_actors": int((ds_rule["interaction_actor"].values >= 0).any(axis=2).sum()),
        }
        parked = _with_parked_cars(cfg, geom, args.parked)
        all_s, ds_all = _timed(lambda: trace(parked, None), repeat=1)
        ref = _gain_db(ds_all)
        result["skip_rule"] = {"every_actor_s": round(all_s, 3),
                               "solver_calls_every_actor": int(ds_all.attrs["trace_calls"]), "thresholds": []}
        result["skip_rule"]["parked_cars"] = args.parked
        for threshold in args.thresholds or (cfg.ray_tracing.actor_max_excess_path_m, 50.0, 10.0, 1.0):
            t_s, ds_t = _timed(lambda: trace(parked, threshold), repeat=1)
            # A link that has paths in one trace and none in the other counts as an infinite error.
            g = _gain_db(ds_t)
            both = np.isfinite(g) & np.isfinite(ref)
            diff = np.abs(g - ref)[both]
            result["skip_rule"]["thresholds"].append({
                "actor_max_excess_path_m": threshold, "s": round(t_s, 3),
                "mean_actors_per_receiver": round(_mean_placed(parked, traj, scene_xml, scene_dir, threshold), 2),
                "actors": len(parked.platforms) + len(parked.static_actors),
                "solver_calls": int(ds_t.attrs["trace_calls"]),
                "links_gaining_or_losing_every_path": int((np.isfinite(g) != np.isfinite(ref)).sum()),
                "link_gain_error_db": {"p50": round(float(np.percentile(diff, 50)), 4) if diff.size else 0.0,
                                       "p95": round(float(np.percentile(diff, 95)), 4) if diff.size else 0.0,
                                       "max": round(float(diff.max()), 4) if diff.size else 0.0,
                                       "links": int(diff.size)}})
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
