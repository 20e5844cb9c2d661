"""The one-pass run again, with other settings, against the converged PathSolver reference that a
:mod:`benchmarks.ckm_solver` run saved, and timed side by side with RadioMapSolver.

A converged reference of several seeded PathSolver runs takes about an hour on Munich's 20 cells
(``ckm_solver --converged-seeds 4``); a change to the one-pass need not trace it again. The run's
``results.json`` keeps every compared cell's values (``per_cell``: the one-pass, the reference at
the cell centres, and its two halves or its settle trace). Per variant (``--variant NAME=JSON``:
keyword arguments of :func:`simart_pipeline.ckm.one_pass.one_pass_moments` over the benchmark's,
which follow the config's) this reads the one-pass again at those centres and judges it:

- on the cells where the saved reference has settled in gain and best beam (its halves, or its
  trace with fewer samples, agree: both reach the cell, the gain within
  :data:`simart_pipeline.radio.convergence.GAIN_TOLERANCE_DB`, the same best beam; the rule of
  :func:`benchmarks.ckm_solver.settled_by_layer` for those layers): path gain error p50 / p95 /
  largest (dB) and best-beam agreement;
- over every saved cell: cells with a value, gain p95 and best beam.

Times: each variant and RadioMapSolver (``|E|^2``, the set's mechanisms, the variant's ray count)
warm, in turn for ``--rounds`` rounds, the fastest of each; the one-pass like for like (``|E|^2``,
every layer, 64 beams), as :func:`benchmarks.ckm_solver._against_radio_map` times it. Two runs
on 2 cores differ by about 0.1 in the ratio (docs/ckm-one-pass.md "Session 43").

    python -m benchmarks.saved_reference --results RUN/results.json --out DIR [--scene munich] [--set all]
        [--variant uniform='{"gather_pilot_directions": 0}'] [--variant default='{}'] [--rays 1e7] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import ckm_solver as cs

DEFAULT_VARIANTS = {"uniform gather": {"gather_pilot_directions": 0}, "default": {}}


def _column(values: dict, key: str) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values[key]], float)


def _layers(values: dict) -> dict:
    """Saved per-cell values (:func:`benchmarks.ckm_solver.per_cell_values`) as the layers
    :func:`benchmarks.ckm_solver.settled_cells` reads."""
    gain = _column(values, "path_gain_db")
    return {"has_path": np.isfinite(gain), "path_gain_db": gain, "best_beam": np.array(values["best_beam"]),
            "rms_delay_spread_s": 1e-9 * _column(values, "rms_delay_spread_ns")}


def settled_gain_and_beam(per_cell: dict) -> np.ndarray:
    """The saved cells whose reference has settled in path gain and best beam
    (:func:`benchmarks.ckm_solver.settled_cells` without the delay-spread rule): its two halves
    (``first_half_centre``, ``last_half_centre``) or, without them, its settle trace
    (``settle_trace_centre``) against itself agree; False everywhere where neither was saved."""
    if "first_half_centre" in per_cell:
        a, b = per_cell["first_half_centre"], per_cell["last_half_centre"]
    elif "settle_trace_centre" in per_cell:
        a, b = per_cell["settle_trace_centre"], per_cell["reference_centre"]
    else:
        return np.zeros(len(per_cell["reference_centre"]["best_beam"]), bool)
    return cs.settled_cells(_layers(a), _layers(b), delay_spread=False)


def judge(per_cell: dict, gain_db: np.ndarray, best_beam: np.ndarray) -> dict:
    """A one-pass's path gain (dB, NaN: no value) and best beam at the saved cells against the
    saved reference at their centres: on the cells settled in gain and best beam
    (:func:`settled_gain_and_beam`) and over every cell the reference reaches."""
    ref_db = _column(per_cell["reference_centre"], "path_gain_db")
    ref_beam = np.array(per_cell["reference_centre"]["best_beam"])
    settled = settled_gain_and_beam(per_cell)
    reached = np.isfinite(ref_db)
    both = reached & np.isfinite(gain_db)
    err = np.abs(np.asarray(gain_db, float) - ref_db)

    def stats(sel):
        e = err[sel & both]
        return {"cells": int(sel.sum()), "cells_with_a_value": int((sel & both).sum()),
                "gain_db_p50": round(float(np.percentile(e, 50)), 3) if e.size else None,
                "gain_db_p95": round(float(np.percentile(e, 95)), 3) if e.size else None,
                "gain_db_max": round(float(e.max()), 3) if e.size else None,
                "best_beam_pct": round(100 * float((np.asarray(best_beam)[sel & both] == ref_beam[sel & both]).mean()), 2)
                if (sel & both).any() else None}

    return {"settled_in_gain_and_beam": stats(settled & reached), "every_cell": stats(reached),
            "signed_error_db": [None if not np.isfinite(v) else round(float(v), 3)
                                for v in np.asarray(gain_db, float) - ref_db]}


def _cells_of(spec: dict, centres_m: np.ndarray) -> np.ndarray:
    """Flat grid indices of the saved cell centres (the benchmark's grid of ``spec``)."""
    x, y = cs.grid_axes(spec)
    ix = np.abs(x[None] - centres_m[:, :1]).argmin(1)
    iy = np.abs(y[None] - centres_m[:, 1:2]).argmin(1)
    if not (np.allclose(x[ix], centres_m[:, 0], atol=1e-6) and np.allclose(y[iy], centres_m[:, 1], atol=1e-6)):
        raise ValueError("the saved cell centres are not on this scene's benchmark grid")
    return iy * len(x) + ix


def run(results_path: Path, scene: str, mechanisms: str, variants: dict, num_rays: int, rounds: int, log=print) -> dict:
    from simart_pipeline.ckm import one_pass as op
    from simart_pipeline.ckm.outdoor import outdoor_fraction, radio_solids
    from simart_pipeline.ckm.radiomap import radio_map_path_gain_db
    from simart_pipeline.link.beams import dft_codebook

    saved = json.loads(Path(results_path).read_text())
    try:
        per_cell = saved["scenes"][scene]["sets"][mechanisms]["against_converged_reference"]["per_cell"]
    except KeyError:
        raise SystemExit(f"{results_path}: no saved per_cell values of {scene}, {mechanisms} (a ckm_solver run "
                         "with a converged reference, session 42 on, saves them)") from None
    spec = cs.SCENES[scene]
    cells = _cells_of(spec, np.asarray(per_cell["centre_m"], float))
    x, y = cs.grid_axes(spec)
    cfg = cs._config(spec, mechanisms)
    radio = cs._radio_scene(cs._radio_xml(spec, Path(tempfile.mkdtemp(prefix="saved-ref-"))), cfg, mechanisms)
    tx = np.array(spec["tx"], float)
    ori = np.radians([spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0])
    codebook = dft_codebook(radio.array_positions_m("tx"), radio.wavelength_m, 8, 8).weights
    solids = radio_solids(radio)
    frac = outdoor_fraction(radio, x, y, [cs.HEIGHT_M], solids=solids)
    base = {k: bool(getattr(cfg.ray_tracing, k)) for k in cs.SWITCHES}
    base.update(diffraction_resample_factor=cfg.ckm.diffraction_resample_factor, diffuse_gather=cfg.ckm.diffuse_gather)

    def one_pass(kw, rx_polarization):
        return op.one_pass_moments(radio, tx, ori, x, y, [cs.HEIGHT_M], int(num_rays), cs.MAX_DEPTH, codebook=codebook,
                                   rx_polarization=rx_polarization, solids=solids, cell_outdoor_fraction=frac,
                                   **{**base, **kw})

    out = {"results": str(results_path), "scene": scene, "set": mechanisms, "rays": int(num_rays), "variants": {}}
    for name, kw in variants.items():
        at = cs._layers_at(one_pass(kw, "V"), cells)
        out["variants"][name] = {"kwargs": kw, **judge(per_cell, np.where(at["has_path"], at["path_gain_db"], np.nan),
                                                       at["best_beam"])}
        log(f"{name}: {out['variants'][name]['settled_in_gain_and_beam']}")
    timed = {name: (lambda kw=kw: one_pass(kw, None)) for name, kw in variants.items()}
    timed["RadioMapSolver"] = lambda: radio_map_path_gain_db(radio, cfg, cs.HEIGHT_M, int(num_rays))
    timed["RadioMapSolver"]()  # compiled (the variants were, above)
    times = {k: [] for k in timed}
    for _ in range(int(rounds)):
        for name, call in timed.items():
            t = time.perf_counter()
            call()
            times[name].append(round(time.perf_counter() - t, 3))
    rms = min(times["RadioMapSolver"])
    out["warm_s"] = times
    for name in variants:
        out["variants"][name]["warm_s"] = min(times[name])
        out["variants"][name]["over_radio_map_time"] = round(min(times[name]) / rms, 3)
    return out


def report(out: dict) -> str:
    lines = [f"# The one-pass against a saved converged reference: {out['scene']}, {out['set']}, {out['rays']:.0e} rays",
             "", f"Reference: `{out['results']}` (its `per_cell` values at the cell centres).", "",
             "| variant | settled in gain and beam: cells | gain dB p50 / p95 / max | best beam % | every cell: "
             "with a value / reached | gain dB p95 | best beam % | warm s | / RadioMapSolver |",
             "|---" * 9 + "|"]
    for name, v in out["variants"].items():
        s, e = v["settled_in_gain_and_beam"], v["every_cell"]
        lines.append(f"| {name} | {s['cells']} | {s['gain_db_p50']} / {s['gain_db_p95']} / {s['gain_db_max']} | "
                     f"{s['best_beam_pct']} | {e['cells_with_a_value']} / {e['cells']} | {e['gain_db_p95']} | "
                     f"{e['best_beam_pct']} | {v['warm_s']} | {v['over_radio_map_time']} |")
    lines += ["", f"RadioMapSolver warm: {min(out['warm_s']['RadioMapSolver'])} s (fastest of "
              f"{len(out['warm_s']['RadioMapSolver'])}, in turn with the variants)."]
    return "\n".join(lines) + "\n"


def parse_variants(items: list[str]) -> dict:
    """``NAME=JSON`` items as {name: keyword arguments}; none: :data:`DEFAULT_VARIANTS`."""
    if not items:
        return dict(DEFAULT_VARIANTS)
    out = {}
    for item in items:
        name, sep, raw = item.partition("=")
        try:
            kw = json.loads(raw) if sep else None
        except json.JSONDecodeError as e:
            raise SystemExit(f"--variant {item}: {e}") from None
        if not name or not isinstance(kw, dict):
            raise SystemExit(f"--variant {item}: expected NAME=JSON with a JSON object of one_pass_moments arguments")
        out[name] = kw
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", required=True, type=Path, help="a ckm_solver results.json with per_cell values")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--scene", default="munich", choices=list(cs.SCENES))
    p.add_argument("--set", default="all", choices=list(cs.MECHANISM_SETS))
    p.add_argument("--variant", action="append", default=[], metavar="NAME=JSON")
    p.add_argument("--rays", type=float, default=1e7)
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args(argv)
    out = run(a.results, a.scene, a.set, parse_variants(a.variant), int(a.rays), a.rounds)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "results.json").write_text(json.dumps(out, indent=1))
    md = report(out)
    (a.out / "report.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
