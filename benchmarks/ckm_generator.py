"""The CKM generator (reference mode) against a SimART-style loop of one PathSolver call per cell.

    python -m benchmarks.ckm_generator [SCENE_DIR] [--loop-cells 60] [--cell-size M] [--samples N] [--out DIR]

On the same scene, grid and solver settings, in one run:

- the generator: every cell of the scene's grid through ``ckm.layers.tile_layers`` (cells batched
  per tile into as few PathSolver calls as memory allows, every layer vectorised), tile by tile;
- the loop: a random subset of the same traced cells, one ``PathSolver`` call per cell (one
  receiver each, as SimART does), reduced to layers by the same code.

It prints (and writes to ``DIR/results.json``) cells per second of both, the speed-up, and the
largest difference between the two on the looped cells for every layer (they must agree: the
solver is deterministic and per-receiver results do not depend on the batch).
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
from simart_pipeline.ckm import moments as mom
from simart_pipeline.ckm.grid import scene_tiles
from simart_pipeline.ckm.layers import codebook_weights, reference_moments, tile_grid, tile_layers
from simart_pipeline.config import load_scene_config
from simart_pipeline.radio.tracer import RadioScene

COMPARED = ("path_gain_db", "toa_s", "mean_delay_s", "rms_delay_spread_s", "asa_deg", "asd_deg",
            "zsa_deg", "zsd_deg", "los_power_fraction", "best_beam_gain_db")


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
        radio = RadioScene(scene_xml, cfg)
        weights = codebook_weights(cfg, radio.array_positions_m("tx"))
        tiles = scene_tiles(cfg.ckm)
        tile_layers(radio, cfg, geom, tiles[0])  # warm-up: kernel compilation, for both sides
        t0 = time.perf_counter()
        maps = {t: tile_layers(radio, cfg, geom, t) for t in tiles}
        gen_s = time.perf_counter() - t0
        traced = sum(int(ds.attrs["cells_traced"]) for ds in maps.values())

        # The loop: one PathSolver call per cell, on a random subset of the traced cells.
        rng = np.random.default_rng(0)
        cells = []
        for t, ds in maps.items():
            g = tile_grid(cfg, geom, t)
            for h, i, j in zip(*np.nonzero(g.traced)):
                cells.append((t, h, i, j, np.array([g.x[j], g.y[i], g.heights[h]])))
        pick = rng.choice(len(cells), size=min(args.loop_cells, len(cells)), replace=False)
        reference_moments(radio, cfg, cells[pick[0]][4][None], weights)  # warm-up of the 1-receiver shape
        t0 = time.perf_counter()
        looped = [reference_moments(radio, cfg, cells[k][4][None], weights) for k in pick]
        loop_s = time.perf_counter() - t0
    worst = {}
    for (mts, _), k in zip(looped, pick):
        t, h, i, j, pt = cells[k]
        tx = np.array([b.position_m for b in cfg.base_stations])
        mts.tau0_s = np.linalg.norm(pt[None] - tx, axis=-1)[:, None] / 299792458.0
        one = mom.layers_from_moments(mts)
        for name in COMPARED:
            a = np.asarray(one[name])[:, 0].astype(np.float64)
            b = maps[t][name].values[:, h, i, j].astype(np.float64)
            both = np.isfinite(a) & np.isfinite(b)
            if (np.isfinite(a) != np.isfinite(b)).any():
                worst[name] = float("inf")
            elif both.any():
                worst[name] = max(worst.get(name, 0.0), float(np.max(np.abs(a[both] - b[both]))))
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
        "note": "generator: all traced cells of every tile, every layer (link layers included); loop: "
                "one PathSolver call per cell on a random subset, propagation layers only",
    }
    print(json.dumps(result, indent=2))
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "results.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
