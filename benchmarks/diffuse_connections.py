"""Run time against error of the diffuse hits' connections to cells (``ckm.diffuse_connections``).

The one-pass with every mechanism (the ``all`` set of :mod:`benchmarks.ckm_solver`) at ``--rays``
rays, once per number of connections per diffuse hit, timed warm and alternated (the fastest of
``--repeats``), against the same solver at ``--reference-rays`` with ``--reference-connections``:
both estimators are unbiased, so the reference's own noise is the floor and the figures are the
noise at the tested ray count. Over the cells the reference gives a value: how many of them each
run covers, path gain |dB| p50 / p95, best-beam agreement, RMS delay spread |ns| p50. The first
setting runs again at the rays each other setting's time buys it: at equal time, which error is
lower (``--no-equal-time`` skips it).

    python -m benchmarks.diffuse_connections --out DIR [--scenes street_canyon urban]
        [--rays 1e7] [--reference-rays 1e8] [--connections 0 0.5 1] [--repeats 2] [--no-equal-time]
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
from benchmarks.ckm_variants import SceneRuns
from simart_pipeline import engine
from simart_pipeline.ckm import one_pass as op
from simart_pipeline.ckm.moments import too_few_hits

SCENES = ("street_canyon", "urban")
CONNECTIONS = (0.0, 0.5, 1.0)
COMPILE_RAYS = 100_000  # a first call per setting compiles its kernels outside the timing


def _solve(s: SceneRuns, n: int, connections: float) -> op.OnePassMoments:
    return s.one_pass(n, diffuse_connections=connections)()


def _errors(layers: dict, ref: dict, cells: np.ndarray) -> dict:
    """A run's layers against the reference's over ``cells`` (the reference's cells with a value)."""
    g = layers["path_gain_db"][0][cells]
    has = np.isfinite(g)
    gain = np.abs(g[has] - ref["path_gain_db"][0][cells][has])
    ds, ds0 = layers["rms_delay_spread_s"][0][cells], ref["rms_delay_spread_s"][0][cells]
    both = np.isfinite(ds) & np.isfinite(ds0)
    return {"cells_covered_pct": round(100 * float(has.mean()), 2),
            "path_gain_abs_db": {"p50": round(float(np.median(gain)), 4), "p95": round(float(np.percentile(gain, 95)), 3)},
            "best_beam_agreement_pct": round(100 * float(np.mean(
                layers["best_beam"][0][cells] == ref["best_beam"][0][cells])), 2),
            "rms_delay_spread_abs_ns_p50": round(float(np.median(np.abs(ds[both] - ds0[both]))) * 1e9, 3)}


def _few_effective_hits(m: op.OnePassMoments) -> int:
    """Cells outside the mask with a ray hit but an effective count (Kish) below ``min_hits_for_power``."""
    few = too_few_hits(m, 1, float(m.min_count_for_power))  # the layers' Kish rule
    return int(np.sum((m.count >= 1) & ~m.masked & few))


def run_scene(name: str, rays: int, reference_rays: int, connections, reference_connections: float,
              repeats: int, equal_time: bool = True, log=print) -> dict:
    return sweep(name, rays, reference_rays, connections, reference_connections, _solve, "connections", repeats,
                 equal_time, log)


def sweep(name: str, rays: int, reference_rays: int, settings, reference_setting, solve, label: str,
          repeats: int, equal_time: bool = True, log=print) -> dict:
    """One setting of the one-pass (``solve(scene_runs, rays, setting)``) against another at
    ``reference_rays`` on scene ``name``: each of ``settings`` timed warm, alternated, the fastest
    of ``repeats``; errors over the reference's cells with a value; with ``equal_time`` the first
    setting again at the rays each other's time buys it. ``label`` names the setting in the log."""
    with tempfile.TemporaryDirectory(prefix="one-pass-sweep-") as tmp:
        s = SceneRuns(name, Path(tmp))
        for c in sorted(set(settings) | {reference_setting}):
            solve(s, COMPILE_RAYS, c)
        t = time.perf_counter()
        m = solve(s, reference_rays, reference_setting)
        res = {"reference": {"rays": reference_rays, label: reference_setting,
                             "s": round(time.perf_counter() - t, 2)}}
        ref = m.layers()
        cells = ref["enough_hits"][0] & ~m.masked[0]
        res["reference"]["cells_with_a_value"] = int(cells.sum())
        log(f"{name} reference: {res['reference']}", flush=True)
        times = {c: [] for c in settings}
        layers, hits, few, passes = {}, {}, {}, {}
        for _ in range(repeats):  # alternated: a drift of the machine's speed hits every setting alike
            for c in settings:
                t = time.perf_counter()
                m = solve(s, rays, c)
                times[c].append(time.perf_counter() - t)
                layers[c], hits[c], few[c] = m.layers(), int(m.count.sum()), _few_effective_hits(m)
                if m.lattice_second_pass:
                    passes[c] = m.lattice_second_pass
        runs = {}
        for c in settings:
            runs[str(c)] = {"warm_s": round(min(times[c]), 3), "times_s": [round(v, 3) for v in times[c]],
                            "ray_hits": hits[c], "cells_few_effective_hits": few[c], **_errors(layers[c], ref, cells)}
            if c in passes:
                runs[str(c)]["lattice_second_pass"] = passes[c]
            log(f"{name} {rays:.0e} rays, {label} {c}: {runs[str(c)]}", flush=True)
        base = runs[str(settings[0])]["warm_s"]
        for r in runs.values():
            r["time_over_first"] = round(r["warm_s"] / base, 3)
        if equal_time:  # the first setting again with the rays another one's time buys it
            for c in settings[1:]:
                n = int(round(rays * runs[str(c)]["time_over_first"]))
                t = time.perf_counter()
                m = solve(s, n, settings[0])
                runs[str(c)]["first_at_equal_time"] = {"rays": n, "s": round(time.perf_counter() - t, 3),
                                                       **_errors(m.layers(), ref, cells)}
                log(f"{name} {n:.2e} rays, {label} {settings[0]} (the time of {c}): "
                    f"{runs[str(c)]['first_at_equal_time']}", flush=True)
        res.update(rays=rays, runs=runs)
    return res


def _row(v: dict) -> str:
    g = v["path_gain_abs_db"]
    return (f"{v['cells_covered_pct']} | {g['p50']} / {g['p95']} | {v['best_beam_agreement_pct']} | "
            f"{v['rms_delay_spread_abs_ns_p50']} |")


def table(results: dict, label: str = "connections") -> list[str]:
    """The markdown rows of ``results`` (``main``'s), the setting's column named ``label``."""
    rows = [f"| scene | {label} | rays | warm s | x time | cells % | gain p50 / p95 dB | best beam % | DS p50 ns |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name, r in results["scenes"].items():
        first = next(iter(r["runs"]))
        for c, v in r["runs"].items():
            rows.append(f"| {name} | {c} | {r['rays']:.2e} | {v['warm_s']} | {v['time_over_first']} | " + _row(v))
            if "first_at_equal_time" in v:
                e = v["first_at_equal_time"]
                rows.append(f"| {name} | {first}, at {c}'s time | {e['rays']:.2e} | {e['s']} | | " + _row(e))
    return rows


def sweep_parser(doc: str, scenes) -> argparse.ArgumentParser:
    """The arguments every :func:`sweep` benchmark takes (a module adds its settings')."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenes", nargs="+", default=list(scenes), choices=sorted(cs.SCENES))
    ap.add_argument("--rays", type=float, default=1e7)
    ap.add_argument("--reference-rays", type=float, default=1e8)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-equal-time", action="store_true",
                    help="skip the first setting's runs at the rays the others' time buys it")
    return ap


def run_sweeps(a: argparse.Namespace, ap: argparse.ArgumentParser, run, label: str) -> int:
    """``run(scene name, args)`` per scene of ``a``, the results and their table written to
    ``a.out`` and the table printed."""
    if int(a.reference_rays) <= int(a.rays):
        ap.error("--reference-rays must exceed --rays (the reference's noise is the floor)")
    a.out.mkdir(parents=True, exist_ok=True)
    results = {"machine": machine(), "variant": engine.init(), "rays": int(a.rays), "scenes": {}}
    for name in a.scenes:
        results["scenes"][name] = run(name, a)
    (a.out / "results.json").write_text(json.dumps(results, indent=1))
    rows = table(results, label)
    (a.out / "results.md").write_text("\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


def main(argv=None) -> int:
    ap = sweep_parser(__doc__, SCENES)
    ap.add_argument("--connections", type=float, nargs="+", default=list(CONNECTIONS))
    ap.add_argument("--reference-connections", type=float, default=1.0)
    a = ap.parse_args(argv)
    return run_sweeps(a, ap, lambda name, a: run_scene(
        name, int(a.rays), int(a.reference_rays), a.connections, a.reference_connections, max(1, a.repeats),
        not a.no_equal_time), "connections")


if __name__ == "__main__":
    raise SystemExit(main())
