"""Ray-tracing cost on a scene: time per trajectory step, per receiver, and per solver call.

    python -m benchmarks.tracing [SCENE_DIR] [--receivers 50 200 800]

Builds the scene's paired meshes and trajectory in a temporary directory, traces the whole
session in trajectory mode (as the ``cirs`` asset does), then a grid scan with growing receiver
counts, and prints milliseconds per (time step), per (link x time step) and per receiver, plus the
receivers per PathSolver call that the memory budget allows.
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
from simart_pipeline.radio.tracer import RadioScene, receivers_per_call


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir", nargs="?", default=str(DEMO))
    ap.add_argument("--receivers", type=int, nargs="+", default=[50, 200, 800])
    args = ap.parse_args(argv)
    scene_dir = Path(args.scene_dir)
    cfg = load_scene_config(scene_dir)
    variant = engine.init()
    with tempfile.TemporaryDirectory() as tmp:
        geom, scene_xml = build_scene(cfg, scene_dir, Path(tmp) / "pm")
        traj = build_trajectory(cfg, scene_dir, geom=geom)
        t0 = time.perf_counter()
        radio = RadioScene.from_config(scene_xml, cfg)
        load_s = time.perf_counter() - t0
        radio_cirs.trace_trajectory(radio, cfg, traj, geom)  # warm-up: JIT compilation
        t0 = time.perf_counter()
        ds = radio_cirs.trace_trajectory(radio, cfg, traj, geom)
        traj_s = time.perf_counter() - t0
        T, L = ds.sizes["time"], ds.sizes["link"]
        result = {
            "scene": cfg.name, "variant": variant, "scene_load_s": round(load_s, 3),
            "max_depth": cfg.ray_tracing.max_depth, "samples_per_src": cfg.ray_tracing.samples_per_src,
            "receivers_per_call": receivers_per_call(cfg.ray_tracing),
            "trajectory": {"time_steps": T, "links": L, "total_s": round(traj_s, 3),
                           "ms_per_time_step": round(1e3 * traj_s / T, 2),
                           "ms_per_link_step": round(1e3 * traj_s / (T * L), 2)},
            "grid_scan": [],
        }
        rng = np.random.default_rng(0)
        half = np.array(cfg.ckm.size_m) / 2
        for n in args.receivers:
            xy = np.array(cfg.ckm.center_m) + rng.uniform(-half, half, size=(n, 2))
            pts = np.column_stack([xy, np.full(n, cfg.ckm.height_m)])
            tx = np.array([b.position_m for b in cfg.base_stations])
            tx_ori = np.deg2rad([b.orientation_deg for b in cfg.base_stations])
            times = []
            for _ in range(2):  # the first call may compile kernels for a new batch shape
                t0 = time.perf_counter()
                radio.grid_scan(tx, tx_ori, pts)
                times.append(time.perf_counter() - t0)
            result["grid_scan"].append({"receivers": n, "first_call_s": round(times[0], 3),
                                        "warm_s": round(times[1], 3),
                                        "warm_ms_per_receiver": round(1e3 * times[1] / n, 2)})
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
