"""The one-pass CKM and Sionna's RadioMapSolver on the Mitsuba variant this machine gets
(:func:`simart_pipeline.engine.init`: ``cuda`` where a GPU is present, LLVM otherwise).

Per scene (every mechanism, the ``all`` set of :mod:`benchmarks.ckm_solver`, its grid, station
and seed): warm times of the one-pass (V receiver, every layer) and of RadioMapSolver at each ray
count, the one-pass at several ray batch sizes, the one-pass like for like with RadioMapSolver
(``|E|^2``), the per-cell PathSolver loop, and the maps themselves (``maps_<scene>.npz``).
Beside them (``sums``) the one-pass with its per-cell sums where the variant does not put them
(``one_pass_moments(accumulate_on_device=...)``: on the device on a GPU, on the host on a CPU):
both times side by side and how far the two maps differ.

``--compare A B``: two finished runs (say a GPU's and a CPU's, same seed and main ray count),
map by map and cell by cell, with both machines' times side by side. The one-pass traces the same
Fibonacci lattice with the same random keys on either variant, so its maps agree to float32
rounding wherever the two ray casters (Embree on the CPU, OptiX on the GPU) agree on a hit.
RadioMapSolver's maps (Sionna 2.2) differ between two processes even on one machine (Munich,
every mechanism: max 42 dB, docs/ckm-one-pass.md "Session 22"), so theirs are a looser check.

    python -m benchmarks.ckm_variants --out DIR [--scenes ...] [--ray-counts 1e7 1e8] [--repeats 3]
    python -m benchmarks.ckm_variants --compare A B --out DIR
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import ckm_solver as cs
from benchmarks.bench import machine
from simart_pipeline import engine
from simart_pipeline.ckm import one_pass as op
from simart_pipeline.link.beams import dft_codebook

MECHANISMS = "all"
BATCH_RAYS = (op.DEFAULT_BATCH_RAYS, 4 * op.DEFAULT_BATCH_RAYS, 8 * op.DEFAULT_BATCH_RAYS)
LOOP_CELLS, LOOP_BUDGET_S = 8, 8.0
REPEATS = 1  # timed warm calls per timing at the main ray count (the fastest counts; --repeats)
SAVED_LAYERS = ("path_gain_db", "toa_s", "rms_delay_spread_s", "best_beam")


class SceneRuns:
    """The one-pass and RadioMapSolver calls of one scene, as :func:`benchmarks.ckm_solver.run_set`
    makes them for the ``all`` set."""

    def __init__(self, name: str, folder: Path):
        from simart_pipeline.ckm.outdoor import outdoor_fraction, radio_solids

        self.spec = spec = cs.SCENES[name]
        self.cfg = cfg = cs._config(spec, MECHANISMS)
        t0 = time.perf_counter()
        self.radio = cs._radio_scene(cs._radio_xml(spec, folder), cfg, MECHANISMS)
        self.build_s = time.perf_counter() - t0
        self.tx = np.array(spec["tx"])
        self.ori = np.radians([spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0])
        self.x, self.y = cs.grid_axes(spec)
        self.codebook = dft_codebook(self.radio.array_positions_m("tx"), self.radio.wavelength_m, 8, 8).weights
        self.switches = {k: bool(getattr(cfg.ray_tracing, k)) for k in cs.SWITCHES}
        self.solids = radio_solids(self.radio)
        # the cells' outdoor share depends on the scene and the grid alone (one per tile, as in
        # ckm/layers.py), so it is not part of a station's timed call
        self.outdoor = outdoor_fraction(self.radio, self.x, self.y, [cs.HEIGHT_M], solids=self.solids)

    def one_pass(self, n: int, rx_polarization="V", **kw):
        """The one-pass call at ``n`` rays; ``kw``: more of ``one_pass_moments``' arguments."""
        return lambda: op.one_pass_moments(
            self.radio, self.tx, self.ori, self.x, self.y, [cs.HEIGHT_M], n, cs.MAX_DEPTH, codebook=self.codebook,
            rx_polarization=rx_polarization, solids=self.solids, cell_outdoor_fraction=self.outdoor,
            diffraction_resample_factor=self.cfg.ckm.diffraction_resample_factor, **self.switches, **kw)

    def radio_map(self, n: int):
        from simart_pipeline.ckm.radiomap import radio_map_path_gain_db

        return lambda: radio_map_path_gain_db(self.radio, self.cfg, cs.HEIGHT_M, n)[0]


def _layers(m: op.OnePassMoments) -> dict[str, np.ndarray]:
    layers = m.layers()
    return {k: np.asarray(layers[k][0]) for k in SAVED_LAYERS if k in layers}


def run_scene(name: str, ray_counts, batch_rays, out: Path, log=print, other_sums: bool = True,
              repeats: int = REPEATS) -> dict:
    with tempfile.TemporaryDirectory(prefix="ckm-variants-") as tmp:
        s = SceneRuns(name, Path(tmp))
        main = ray_counts[0]
        res = {"scene_build_s": round(s.build_s, 3), "grid_cells": int(s.x.size * s.y.size),
               "seed": int(s.cfg.ray_tracing.seed), "one_pass": {}, "radio_map_solver": {}, "batch_rays": {}}
        maps: dict[str, np.ndarray] = {}
        for n in ray_counts:
            m, first, warm = cs._warm(s.one_pass(n), repeats if n == main else 0)
            res["one_pass"][str(n)] = {"first_call_s": cs._r3(first), "warm_s": round(warm, 3),
                                       "ray_hits": int(m.count.sum())}
            if n == main:
                n_outdoor = int((m.outdoor_fraction[0] > 0).sum())
                maps.update({f"one_pass_v_{k}": v for k, v in _layers(m).items()})
            log(f"{name} one-pass {n:.0e}: {res['one_pass'][str(n)]}", flush=True)
        for b in batch_rays:
            if b == op.default_batch_rays(engine.init()):
                continue
            _, first, warm = cs._warm(s.one_pass(main, batch_rays=b), repeats)
            res["batch_rays"][str(b)] = {"first_call_s": cs._r3(first), "warm_s": round(warm, 3)}
            log(f"{name} one-pass {main:.0e} batch {b}: {res['batch_rays'][str(b)]}", flush=True)
        if other_sums:  # the accumulation the variant does not choose, side by side (one_pass_moments)
            res["sums"] = _other_sums(s, main, res["one_pass"][str(main)]["warm_s"], maps, repeats)
            log(f"{name} one-pass {main:.0e} sums: {res['sums']}", flush=True)
        m, first, warm = cs._warm(s.one_pass(main, None), repeats)
        maps["one_pass_unpolarised_whole_cell_db"] = cs.whole_cell_db(m)
        res["one_pass_unpolarised"] = {"rays": main, "first_call_s": cs._r3(first), "warm_s": round(warm, 3)}
        for n in ray_counts:
            g, first, warm = cs._warm(s.radio_map(n), repeats if n == main else 0)
            res["radio_map_solver"][str(n)] = {"first_call_s": cs._r3(first), "warm_s": round(warm, 3),
                                               "cells_covered": int(np.isfinite(g).sum())}
            if n == main:
                maps["radio_map_path_gain_db"] = g
            log(f"{name} RadioMapSolver {n:.0e}: {res['radio_map_solver'][str(n)]}", flush=True)
        # |E|^2 over the whole cell, as RadioMapSolver; with diffraction the one-pass's model is wider
        res["path_gain_agreement_with_radio_map_solver"] = cs.map_agreement(maps["one_pass_unpolarised_whole_cell_db"],
                                                          maps["radio_map_path_gain_db"])
        X, Y = np.meshgrid(s.x, s.y)
        outdoor = np.flatnonzero((m.outdoor_fraction[0] == 1.0).ravel())
        cells = np.stack([X.ravel(), Y.ravel(), np.full(X.size, cs.HEIGHT_M)], -1)
        cells = cells[np.random.default_rng(0).permutation(outdoor)[:LOOP_CELLS]]
        per_call_s, calls = cs._per_cell_loop_s(s.radio, s.tx, s.ori, cells, LOOP_BUDGET_S)
        op_s = res["one_pass"][str(main)]["warm_s"]
        res["pathsolver_per_cell"] = {"samples_per_src": cs.reference_samples(s.spec, MECHANISMS),
                                      "per_call_s": round(per_call_s, 4), "calls": calls,
                                      "speedup_of_one_pass": round(per_call_s * n_outdoor / op_s, 1)}
        res["one_pass_over_radio_map_time"] = round(
            res["one_pass_unpolarised"]["warm_s"] / res["radio_map_solver"][str(main)]["warm_s"], 3)
        np.savez_compressed(out / f"maps_{name}.npz", **maps)
    return res


def _other_sums(s: SceneRuns, n: int, default_warm_s: float, maps: dict, repeats: int) -> dict:
    """The one-pass at ``n`` rays with the per-cell sums where the variant does not put them by
    default (on the device for LLVM, on the host for CUDA): both warm times and how far the two
    maps differ (float64 summation order and the beam factors' float32 rounding only)."""
    default_on_device = engine.init().startswith("cuda")
    m, first, warm = cs._warm(s.one_pass(n, accumulate_on_device=not default_on_device), repeats)
    other = _layers(m)
    a, b = maps["one_pass_v_path_gain_db"], other["path_gain_db"]
    both = np.isfinite(a) & np.isfinite(b)
    device_s, host_s = (default_warm_s, round(warm, 3)) if default_on_device else (round(warm, 3), default_warm_s)
    return {"host_warm_s": host_s, "device_warm_s": device_s, "other_first_call_s": cs._r3(first),
            "host_over_device_time": round(host_s / device_s, 3),
            "same_cells_with_a_value": bool(np.array_equal(np.isfinite(a), np.isfinite(b))),
            "path_gain_max_abs_diff_db": float(np.max(np.abs(a[both] - b[both]), initial=0.0)),
            "best_beam_same_pct": round(100 * float(np.mean(
                maps["one_pass_v_best_beam"][both] == other["best_beam"][both])), 3)}


def _table(results: dict) -> list[str]:
    rows = ["| scene | rays | one-pass V s | one-pass |E|^2 s | RadioMapSolver s | ratio | per-cell loop s/call | speed-up |",
            "|---|---|---|---|---|---|---|---|"]
    for name, r in results["scenes"].items():
        main = str(results["ray_counts"][0])
        for n in results["ray_counts"]:
            k = str(n)
            unpol = r["one_pass_unpolarised"]["warm_s"] if k == main else None
            rm = r["radio_map_solver"].get(k, {}).get("warm_s")
            rows.append(f"| {name} | {n:.0e} | {r['one_pass'].get(k, {}).get('warm_s')} | {unpol} | {rm} | "
                        f"{r['one_pass_over_radio_map_time'] if k == main else ''} | "
                        f"{r['pathsolver_per_cell']['per_call_s'] if k == main else ''} | "
                        f"{r['pathsolver_per_cell']['speedup_of_one_pass'] if k == main else ''} |")
    return rows


def compare(a_dir: Path, b_dir: Path) -> dict:
    """Two runs of this benchmark (e.g. a GPU's and a CPU's, same seed and main ray count), map
    by map and cell by cell, with both machines' warm times side by side."""
    a, b = (json.loads((d / "results.json").read_text()) for d in (a_dir, b_dir))
    if a["ray_counts"][0] != b["ray_counts"][0]:
        raise ValueError(f"{a_dir} and {b_dir}: main ray counts differ ({a['ray_counts'][0]} and {b['ray_counts'][0]})")
    main = str(a["ray_counts"][0])
    out = {"a": {k: a[k] for k in ("variant", "machine")}, "b": {k: b[k] for k in ("variant", "machine")},
           "rays": int(main), "scenes": {}}
    gain = "one_pass_v_path_gain_db"
    for name in sorted(set(a["scenes"]) & set(b["scenes"])):
        ra, rb = a["scenes"][name], b["scenes"][name]
        if ra["seed"] != rb["seed"]:
            raise ValueError(f"{name}: seeds differ ({ra['seed']} and {rb['seed']})")
        ma, mb = np.load(a_dir / f"maps_{name}.npz"), np.load(b_dir / f"maps_{name}.npz")
        both = np.isfinite(ma[gain]) & np.isfinite(mb[gain])
        ds_ns = np.abs(ma["one_pass_v_rms_delay_spread_s"] - mb["one_pass_v_rms_delay_spread_s"]) * 1e9
        out["scenes"][name] = {
            "one_pass_path_gain": cs.map_agreement(ma[gain], mb[gain]),
            "one_pass_rms_delay_spread_abs_diff_ns": cs._percentiles(ds_ns),
            "one_pass_best_beam_same_pct": round(100 * float(np.mean(
                ma["one_pass_v_best_beam"][both] == mb["one_pass_v_best_beam"][both])), 2),
            "radio_map_solver_path_gain": cs.map_agreement(ma["radio_map_path_gain_db"], mb["radio_map_path_gain_db"]),
            "warm_s": {k: {"one_pass_v": r["one_pass"][main]["warm_s"],
                           "one_pass_unpolarised": r["one_pass_unpolarised"]["warm_s"],
                           "radio_map_solver": r["radio_map_solver"][main]["warm_s"]}
                       for k, r in (("a", ra), ("b", rb))}}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--scenes", nargs="+", default=list(cs.SCENES), choices=list(cs.SCENES))
    p.add_argument("--ray-counts", nargs="+", type=float, default=[1e7, 1e8],
                   help="the first is the main count (maps, batch sizes, like for like)")
    p.add_argument("--batch-rays", nargs="+", type=float, default=list(BATCH_RAYS))
    p.add_argument("--repeats", type=int, default=REPEATS,
                   help="timed warm calls per timing at the main ray count (the fastest is reported)")
    p.add_argument("--no-other-sums", action="store_true",
                   help="skip the one-pass with the per-cell sums where the variant does not put them")
    p.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"),
                   help="compare two finished runs (folders of results.json and maps); no tracing")
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    if a.compare:
        res = compare(*a.compare)
        (a.out / "compare.json").write_text(json.dumps(res, indent=1))
        print(json.dumps(res["scenes"], indent=1))
        return 0
    variant = engine.init()
    print(f"variant: {variant}", flush=True)
    counts = [int(n) for n in a.ray_counts]
    results = {"variant": variant, "machine": machine(), "ray_counts": counts, "repeats": int(a.repeats), "scenes": {}}
    for name in a.scenes:
        t0 = time.perf_counter()
        results["scenes"][name] = run_scene(name, counts, [int(b) for b in a.batch_rays], a.out,
                                            other_sums=not a.no_other_sums, repeats=max(1, a.repeats))
        results["scenes"][name]["wall_s"] = round(time.perf_counter() - t0, 1)
        (a.out / "results.json").write_text(json.dumps(results, indent=1))  # each scene as it lands
    print("\n".join(_table(results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
