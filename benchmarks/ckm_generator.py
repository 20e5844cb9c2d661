"""The CKM generator (reference mode) against a SimART-style loop of one PathSolver call per cell.

    python -m benchmarks.ckm_generator [SCENE_DIR] [--loop-cells 60] [--cell-size M] [--samples N] [--out DIR]

On the same scene, grid and solver settings, in one run:

- the generator: every cell of the scene's grid through ``ckm.layers.tile_layers`` (cells batched
  per tile into as few PathSolver calls as memory allows, every layer vectorised), tile by tile;
- the loop: a random subset of the same traced cells, one cell at a time through the same
  ``tile_layers`` on a one-cell grid: one ``PathSolver`` call with one receiver and that cell's
  layers, link layers included (SimART's way: trace a cell, reduce it, go on).

It prints (and writes to ``DIR/results.json``) cells per second of both, the speed-up, and the
largest difference between the two on the looped cells for every layer (they must agree: the
solver's paths for a receiver do not depend on the other receivers of the call).

It also reads Dr.Jit's kernel history of one call with one receiver and one with many: the
shoot-and-bounce kernel tests every ray's interaction points for visibility of every receiver, so
its time is ``fixed + per_receiver x receivers``. A call with one receiver costs ``fixed +
per_receiver`` plus Python; batching removes everything but ``per_receiver``. The ratio
``one_receiver_call_s / per_receiver_kernel_s`` (``solver_batching_speedup_bound``) bounds what
batching the solver alone can gain over one call per cell on this machine; the rest of the
generator's lead comes from computing the layers for a whole tile at once.
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
from simart_pipeline.ckm.grid import scene_tiles
from simart_pipeline.ckm.layers import TileGrid, tile_grid, tile_layers
from simart_pipeline.config import load_scene_config
from simart_pipeline.radio.tracer import RadioScene

COMPARED = ("path_gain_db", "path_gain_coherent_db", "rx_power_dbm", "toa_s", "mean_delay_s",
            "rms_delay_spread_s", "asa_deg", "asd_deg", "zsa_deg", "zsd_deg", "los_power_fraction",
            "count", "best_beam", "best_beam_gain_db", "beam_gain_db", "best_bs", "sinr_db", "effective_sinr_db",
            "mcs_index", "bler", "tbler", "rate_bps", "shannon_rate_bps")


def one_cell(grids: dict, tile: str, h: int, i: int, j: int) -> TileGrid:
    """Cell (h, i, j) of ``tile`` as a grid of its own (traced, nothing masked)."""
    g = grids[tile]
    return TileGrid(tile, g.rows[i:i + 1], g.cols[j:j + 1], g.y[i:i + 1], g.x[j:j + 1], g.heights[h:h + 1],
                    np.zeros((1, 1, 1), bool), np.zeros((1, 1), bool))


def kernel_costs(radio: RadioScene, cfg, grids: dict, many: int = 200) -> dict[str, float]:
    """Wall time of a one-receiver call, and the shoot-and-bounce kernel's fixed and per-receiver
    time (Dr.Jit kernel history of calls with 1 and ``many`` receivers)."""
    import drjit as dr

    pts = np.concatenate([np.stack(np.broadcast_arrays(*np.meshgrid(g.x, g.y, indexing="xy"),
                                                       g.heights[0]), -1)[g.traced[0]] for g in grids.values()])
    pts = pts[np.random.default_rng(1).choice(len(pts), min(many, len(pts)), replace=False)]
    tx = np.array([b.position_m for b in cfg.base_stations], np.float64)
    ori = np.deg2rad(np.array([b.orientation_deg for b in cfg.base_stations], np.float64))
    det = cfg.ckm.deterministic_solver
    out = {}
    for n in (1, len(pts)):
        radio.grid_scan(tx, ori, pts[:n], deterministic=det)  # compiled before timing
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        t0 = time.perf_counter()
        radio.grid_scan(tx, ori, pts[:n], deterministic=det)
        wall = time.perf_counter() - t0
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        out[n] = (wall, max(k.get("execution_time", 0.0) for k in hist) / 1e3)  # ms -> s
    (wall1, k1), (_, kn) = out[1], out[len(pts)]
    per_rx = (kn - k1) / (len(pts) - 1)
    return {"one_receiver_call_s": round(wall1, 4), "shoot_bounce_kernel_fixed_s": round(k1 - per_rx, 4),
            "per_receiver_kernel_s": round(per_rx, 5), "kernel_receivers": int(len(pts))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir", nargs="?", default=str(DEMO))
    ap.add_argument("--loop-cells", type=int, default=60, help="cells traced one call each (a random subset)")
    ap.add_argument("--samples", type=int, help="override ray_tracing.samples_per_src (Sionna's default is 1e6)")
    ap.add_argument("--cell-size", type=float, help="override ckm.cell_size_m (finer grids batch more cells per call)")
    ap.add_argument("--out", help="directory for results.json")
    args = ap.parse_args(argv)
    scene_dir = Path(args.scene_dir)
    cfg = load_scene_config(scene_dir)
    cfg = cfg.model_copy(update={"ckm": cfg.ckm.model_copy(update={"mode": "reference"})})
    if args.cell_size:
        cfg = cfg.model_copy(update={"ckm": cfg.ckm.model_copy(update={"cell_size_m": args.cell_size})})
    if args.samples:
        cfg = cfg.model_copy(update={"ray_tracing": cfg.ray_tracing.model_copy(update={"samples_per_src": args.samples})})
    variant = engine.init()
    with tempfile.TemporaryDirectory() as tmp:
        geom, scene_xml = build_scene(cfg, scene_dir, Path(tmp) / "pm")
        radio = RadioScene.from_config(scene_xml, cfg)
        tiles = scene_tiles(cfg.ckm)
        tile_layers(radio, cfg, geom, tiles[0])  # warm-up: kernel compilation, for both sides
        t0 = time.perf_counter()
        maps = {t: tile_layers(radio, cfg, geom, t) for t in tiles}
        gen_s = time.perf_counter() - t0
        traced = sum(int(ds.attrs["cells_traced"]) for ds in maps.values())

        # The loop: one cell at a time (one PathSolver call each), on a random subset of the traced cells.
        rng = np.random.default_rng(0)
        grids = {t: tile_grid(cfg, geom, t) for t in tiles}
        cells = [(t, h, i, j) for t, g in grids.items() for h, i, j in zip(*np.nonzero(g.traced))]
        pick = rng.choice(len(cells), size=min(args.loop_cells, len(cells)), replace=False)
        tile_layers(radio, cfg, geom, cells[pick[0]][0], grid=one_cell(grids, *cells[pick[0]]))  # warm-up
        t0 = time.perf_counter()
        looped = [tile_layers(radio, cfg, geom, cells[k][0], grid=one_cell(grids, *cells[k])) for k in pick]
        loop_s = time.perf_counter() - t0
        kernels = kernel_costs(radio, cfg, grids)
    worst = {}
    for one, k in zip(looped, pick):
        t, h, i, j = cells[k]
        for name in COMPARED:
            a = one[name].isel(height=0, y=0, x=0).values.astype(np.float64)
            b = maps[t][name].isel(height=h, y=i, x=j).values.astype(np.float64)
            both = np.isfinite(a) & np.isfinite(b)
            if (np.isfinite(a) != np.isfinite(b)).any():
                worst[name] = float("inf")
            else:
                worst[name] = max(worst.get(name, 0.0), float(np.max(np.abs(a[both] - b[both]), initial=0.0)))
    gen_rate = traced / gen_s
    loop_rate = len(pick) / loop_s
    result = {
        "scene": cfg.name, "variant": variant, "cell_size_m": cfg.ckm.cell_size_m, "tiles": list(cfg.ckm.tiles), "grid_cells": int(np.prod(cfg.ckm.shape)) * len(cfg.ckm.heights),
        "cells_traced": traced, "base_stations": len(cfg.base_stations),
        "samples_per_src": cfg.ray_tracing.samples_per_src, "max_depth": cfg.ray_tracing.max_depth,
        "generator_s": round(gen_s, 3), "generator_cells_per_s": round(gen_rate, 2),
        "loop_cells": int(len(pick)), "loop_s": round(loop_s, 3), "loop_cells_per_s": round(loop_rate, 2),
        "speedup_vs_per_cell_loop": round(gen_rate / loop_rate, 2),
        "max_abs_difference_on_looped_cells": worst,
        **kernels,
        "solver_batching_speedup_bound": round(kernels["one_receiver_call_s"] / kernels["per_receiver_kernel_s"], 2),
        "note": "both sides: every layer (link layers included) through ckm.layers.tile_layers; generator: all "
                "traced cells of every tile; loop: a one-cell grid per call on a random subset",
    }
    print(json.dumps(result, indent=2))
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "results.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
