"""Every measurable target the project's issues name, read off one ``simart bench`` run.

Each :class:`Target` names its issue, the target in the issue's words, the benchmark whose results
hold the figure, how to read the figure, and the bound. :func:`evaluate` gives one row per target
(per scene where a benchmark measures several): the figure, and ``met`` True / False, or None with
the reason where this run did not measure it (benchmark skipped or failed, quick mode measuring a
smaller scene than the target names, or a measurement that does not exist yet). The report's table
(:func:`table_md`) is what ``docs/benchmarks.md`` shows; a target is never dropped because it is
missed or unmeasured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from benchmarks import ckm_solver as cs
from benchmarks import overhead, rerun

Figure = Callable[[dict], "float | None"]


@dataclass(frozen=True)
class Target:
    """``figure(results)`` reads the number from the benchmark's results (None: not in them);
    ``op`` is ``"<="`` or ``">="`` against ``bound``. ``full_only``: quick mode measures a stand-in
    (the tiny scene, fewer cells), so the row says so instead of judging. ``bench`` ``"bench"`` reads
    the whole command's results (its mode and total wall time)."""

    issue: int
    text: str
    bench: str
    figure: Figure
    op: str
    bound: float
    unit: str = ""
    full_only: bool = False
    mode: str | None = None          # judged only in this mode ("quick" or "full")
    unmeasured_why: str = ""         # a target no benchmark measures yet: why
    absent_why: str = ""             # why a run's results may lack the figure (an optional measurement);
    #                                  judged as unmeasured_met when they do
    unmeasured_met: bool | None = False  # its verdict: missed, or None where nothing of ours is lacking


def lookup(d, *keys, default=None):
    """``d[k1][k2]...``, or ``default`` where a key or a level is missing (results of any layout)."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


def _num(v) -> float | None:
    if v is None:
        return None
    try:
        return float(v)   # "inf" strings from JSON become inf, an unbounded error
    except (TypeError, ValueError):
        return None


def _ckm_solver(scene: str, mechanisms: str, *keys) -> Figure:
    return lambda r: _num(lookup(r, "scenes", scene, "sets", mechanisms, *keys))


# RadioMapSolver at the one-pass's ray count against the one-pass map, |dB| over cells both cover
_RMS_AGREEMENT = ("radio_map_solver", "at_one_pass_rays", "path_gain_agreement_with_one_pass", "abs_diff_db")
# ... and like for like: with diffraction the one-pass restricted to RadioMapSolver's first-order model
_RMS_LIKE_FOR_LIKE = ("radio_map_solver", "path_gain_agreement_like_for_like", "abs_diff_db")
_EQUAL_ERROR = ("radio_map_solver", "equal_error")


def _equal_error_ratio(scene: str, mechanisms: str) -> Figure:
    """The one-pass's time over RadioMapSolver's at equal Monte-Carlo error; infinite where it was
    measured and no ray count of the one-pass reached RadioMapSolver's error (not met, not n/a)."""
    def figure(r):
        e = lookup(r, "scenes", scene, "sets", mechanisms, *_EQUAL_ERROR)
        if not isinstance(e, dict):
            return None
        ratio = e.get("one_pass_over_radio_map_time_at_equal_error")
        return math.inf if ratio is None else _num(ratio)
    return figure


def _largest_spread(scene: str, mechanisms: str) -> Figure:
    """The largest p50 error of the four angular spreads against the cell's points."""
    def figure(r):
        e = lookup(r, "scenes", scene, "sets", mechanisms, "errors_vs_cell_points")
        return None if e is None else _num(cs.largest_spread_p50(e))
    return figure


def _ckm_solver_targets() -> list[Target]:
    rows = []  # judged in the full run: --quick runs the street canyon alone, on a few cells
    for scene in ("street_canyon", "munich"):  # issue 8's, LoS + specular
        ls = "los_specular"
        rows += [
            Target(8, f"one-pass CKM {scene}: speed-up over one PathSolver call per cell >= 100x", "ckm_solver",
                   _ckm_solver(scene, ls, "speedup_vs_per_cell_loop"), ">=", cs.TARGET_SPEEDUP_VS_LOOP, "x",
                   full_only=True),
            Target(8, f"one-pass CKM {scene}: path gain p50 against the cell's points' mean <= 0.5 dB", "ckm_solver",
                   _ckm_solver(scene, ls, "errors_vs_cell_points", "path_gain_db", "p50"), "<=", cs.TARGET_GAIN_P50_DB,
                   "dB", full_only=True),
            Target(8, f"one-pass CKM {scene}: ToA p50 <= 1 ns", "ckm_solver",
                   _ckm_solver(scene, ls, "errors_vs_centre", "toa_ns", "p50"), "<=", cs.TARGET_TOA_P50_NS, "ns",
                   full_only=True),
            Target(8, f"one-pass CKM {scene}: best beam = PathSolver's (the cell's points pooled) in >= 95 % of cells",
                   "ckm_solver", _ckm_solver(scene, ls, "errors_vs_cell_points", "best_beam_agreement_pct"),
                   ">=", cs.TARGET_BEST_BEAM_PCT, "%", full_only=True),
            Target(8, f"one-pass CKM {scene}: path gain against RadioMapSolver, p95 <= 0.1 dB where both have rays",
                   "ckm_solver", _ckm_solver(scene, ls, *_RMS_AGREEMENT, "p95"),
                   "<=", 0.1, "dB", full_only=True),
            Target(17, f"one-pass CKM {scene}, LoS + specular: path gain against RadioMapSolver, p50 <= 0.1 dB",
                   "ckm_solver", _ckm_solver(scene, ls, *_RMS_AGREEMENT, "p50"), "<=", cs.TARGET_RADIO_MAP_GAIN_P50_DB,
                   "dB", full_only=True),
            Target(17, f"one-pass CKM {scene}, LoS + specular: time within 2x of RadioMapSolver's on the same grid",
                   "ckm_solver", _ckm_solver(scene, ls, "radio_map_solver", "one_pass_over_radio_map_time"), "<=",
                   cs.TARGET_RADIO_MAP_TIME_RATIO, "x", full_only=True),
        ]
    for scene in ("street_canyon", "munich", "urban"):  # issue 17's, with the mechanisms on
        for ms in cs.TARGET_SETS:
            pre = f"one-pass CKM {scene}, mechanisms `{ms}`, against PathSolver with the same:"

            def t(text, figure, op, bound, unit):
                return Target(17, f"{pre} {text}", "ckm_solver", figure, op, bound, unit, full_only=True)

            e3 = ("errors_vs_cell_points",)
            rows += [
                t("a value in >= 99 % of the sampled outdoor cells PathSolver reaches",
                  _ckm_solver(scene, ms, "coverage", "covered_of_reached_pct"), ">=", cs.TARGET_COVERAGE_PCT, "%"),
                t("path gain p50 against the cell's points' mean <= 0.5 dB",
                  _ckm_solver(scene, ms, *e3, "path_gain_db", "p50"), "<=", cs.TARGET_GAIN_P50_DB, "dB"),
                t("path gain p95 against the cell's points' mean <= 3 dB",
                  _ckm_solver(scene, ms, *e3, "path_gain_db", "p95"), "<=", cs.TARGET_GAIN_P95_DB, "dB"),
                t("ToA p50 <= 1 ns", _ckm_solver(scene, ms, "errors_vs_centre", "toa_ns", "p50"), "<=",
                  cs.TARGET_TOA_P50_NS, "ns"),
                t("RMS delay spread p50 <= 5 ns (cell points)", _ckm_solver(scene, ms, *e3, "rms_delay_spread_ns", "p50"),
                  "<=", cs.TARGET_DELAY_SPREAD_P50_NS, "ns"),
                t("angular spreads p50 <= 5 deg (the largest of ASA, ASD, ZSA, ZSD; cell points)",
                  _largest_spread(scene, ms), "<=", cs.TARGET_SPREAD_P50_DEG, "deg"),
                t("best beam = PathSolver's (the cell's points pooled) in >= 95 % of cells",
                  _ckm_solver(scene, ms, *e3, "best_beam_agreement_pct"), ">=", cs.TARGET_BEST_BEAM_PCT, "%"),
                t("PathSolver's best beam among the one-pass's 3 best in >= 99 % of cells",
                  _ckm_solver(scene, ms, *e3, "best_beam_top3_agreement_pct"), ">=", cs.TARGET_TOP3_PCT, "%"),
                t("speed-up over one PathSolver call per cell >= 100x",
                  _ckm_solver(scene, ms, "speedup_vs_per_cell_loop"), ">=", cs.TARGET_SPEEDUP_VS_LOOP, "x"),
                t("time within 2x of RadioMapSolver's (same grid and mechanisms)",
                  _ckm_solver(scene, ms, "radio_map_solver", "one_pass_over_radio_map_time"), "<=",
                  cs.TARGET_RADIO_MAP_TIME_RATIO, "x"),
                # the same paths: the one-pass restricted to RadioMapSolver's diffraction model (no
                # reflection before or after the wedge), as the path gain comparison below is
                t("time within 2x of RadioMapSolver's like for like (the one-pass in its diffraction model, "
                  "every layer; same grid, rays and mechanisms)",
                  _ckm_solver(scene, ms, "radio_map_solver", "first_order_diffraction_one_pass", "over_radio_map_time"),
                  "<=", cs.TARGET_RADIO_MAP_TIME_RATIO, "x"),
                t("path gain against RadioMapSolver (same mechanisms, its diffraction model), p50 <= 0.1 dB",
                  _ckm_solver(scene, ms, *_RMS_LIKE_FOR_LIKE, "p50"), "<=", cs.TARGET_RADIO_MAP_GAIN_P50_DB, "dB"),
                # the same two at equal Monte-Carlo error (ckm_solver.equal_error_front): each solver
                # against its own map at the reference's rays
                t("time within 2x of RadioMapSolver's at equal Monte-Carlo error (path gain p50, p95 and "
                  "coverage against each solver's own map at 1e8 rays)", _equal_error_ratio(scene, ms), "<=",
                  cs.TARGET_RADIO_MAP_TIME_RATIO, "x"),
                t("path gain against RadioMapSolver (its diffraction model), both at the reference's 1e8 rays, "
                  "p50 <= 0.1 dB", _ckm_solver(scene, ms, *_EQUAL_ERROR, "like_for_like_at_reference_rays",
                                               "abs_diff_db", "p50"), "<=", cs.TARGET_RADIO_MAP_GAIN_P50_DB, "dB"),
            ]
            # the same accuracy in PathSolver's own diffuse model (ckm_solver.run_set: it keeps one path
            # per primitive sequence after a diffuse reflection), which tells the solver's error apart
            like = ("errors_vs_cell_points_pathsolver_diffuse_model",)
            ps = "in PathSolver's diffuse model,"
            rows += [
                t(f"{ps} path gain {q} against the cell's points' mean <= {b:g} dB",
                  _ckm_solver(scene, ms, *like, "path_gain_db", q), "<=", b, "dB")
                for q, b in (("p50", cs.TARGET_GAIN_P50_DB), ("p95", cs.TARGET_GAIN_P95_DB))] + [
                t(f"{ps} RMS delay spread p50 <= 5 ns (cell points)",
                  _ckm_solver(scene, ms, *like, "rms_delay_spread_ns", "p50"), "<=", cs.TARGET_DELAY_SPREAD_P50_NS, "ns"),
                t(f"{ps} best beam = PathSolver's in >= 95 % of cells",
                  _ckm_solver(scene, ms, *like, "best_beam_agreement_pct"), ">=", cs.TARGET_BEST_BEAM_PCT, "%"),
                t(f"{ps} top-3: PathSolver's best beam among the one-pass's 3 best in >= 99 % of cells",
                  _ckm_solver(scene, ms, *like, "best_beam_top3_agreement_pct"), ">=", cs.TARGET_TOP3_PCT, "%"),
            ]
    return rows


def _front_gap(r: dict) -> float | None:
    """0 when the ray-tracing default is on the front, else 1 (judged as <= 0)."""
    on = lookup(r, "default_on_front", "on_front")
    return None if on is None else (0.0 if on else 1.0)


TARGETS: list[Target] = [
    Target(2, "`simart run` of the demo finishes in a few minutes on 2 cores (first run <= 300 s)", "rerun",
           lambda r: _num(lookup(r, "steps", "first run", "wall_s")), "<=", 300, "s", full_only=True),
    Target(3, "building Helsinki (446 buildings + parts) takes seconds, not minutes (<= 10 s)", "osm_build",
           lambda r: _num(lookup(r, "helsinki.osm.pbf", "total_s")), "<=", 10, "s"),
    Target(5, "numpy link abstraction against Sionna SYS (double): effective SINR within 0.01 dB", "link_sys",
           lambda r: _num(r.get("sionna_double_max_eff_diff_db")), "<=", 0.01, "dB"),
    Target(5, "numpy link abstraction against Sionna SYS (double): BLER within 1e-6", "link_sys",
           lambda r: _num(r.get("sionna_double_max_bler_diff")), "<=", 1e-6),
    Target(5, "numpy link adaptation against Sionna SYS (double): the same MCS for every user", "link_sys",
           lambda r: _num(r.get("sionna_double_mcs_mismatches")), "<=", 0, "users differing"),
    Target(6, "camera RGB+depth+semantic 640x480 on a real city about 73 ms a frame or less (sunny)", "sensing",
           lambda r: _num(lookup(r, "weathers", "sunny", "ms_per_frame")), "<=", 73, "ms"),
    Target(6, "LiDAR 64x2048 sweep about 30 ms or less (sunny)", "sensing",
           lambda r: _num(lookup(r, "lidar", "weathers", "sunny", "ms_per_sweep")), "<=", 30, "ms"),
    Target(7, "CKM generator >= 10x a loop of one PathSolver call per cell", "ckm_generator",
           lambda r: _num(r.get("speedup_vs_per_cell_loop")), ">=", 10, "x"),
    *_ckm_solver_targets(),
    Target(8, "`ckm_solver --quick` fits in five minutes on 2 cores", "ckm_solver",
           lambda r: _num(lookup(r, "settings", "total_s")), "<=", 300, "s", mode="quick"),
    Target(15, "unchanged rerun of the demo: whole command <= 10 % of the first run", "rerun",
           lambda r: _num(lookup(r, "steps", "unchanged rerun", "ratio_to_first_wall")), "<=", rerun.TARGET_UNCHANGED_WALL,
           "ratio",
           full_only=True),
    Target(15, "unchanged rerun of the demo: <= 2 % of the first run excluding start-up", "rerun",
           lambda r: _num(lookup(r, "steps", "unchanged rerun", "ratio_to_first_in_process")), "<=",
           rerun.TARGET_UNCHANGED_IN_PROCESS, "ratio",
           full_only=True),
    Target(15, "first run >= 1.3x faster than the sequential run before (the commit before, in the same run; "
               "like for like: defaults that changed since pinned to the baseline's)",
           "rerun", lambda r: _num(lookup(r, "baseline", "first_run_speedup_vs_baseline")), ">=",
           rerun.TARGET_FIRST_RUN_SPEEDUP, "x",
           absent_why="measured only by `python -m benchmarks.rerun --baseline REV` (the full bench passes "
                      "it where this clone has the baseline revision); `simart run` has no concurrent mode: "
                      "drjit already keeps both cores busy in tracing and rendering, and an ideal two-process "
                      "split of the demo's partitions measured 1.04x (issue 15's notes)"),
    Target(20, "`cirs` asset <= 1.10x the bare Sionna calls it makes", "overhead",
           lambda r: _num(lookup(r, "cirs", "ratio_median")), "<=", overhead.TARGET_CIRS_RATIO, "x", full_only=True),
    Target(20, "the paper's claim: a radio mesh 10x (one order of magnitude) or more lighter than the visual mesh "
               "keeps the strongest path of >= 95 % of the links", "mesh_simplification",
           lambda r: _num(lookup(r, "claim", "largest_reduction_x")), ">=", 10, "x fewer triangles"),
    Target(20, "the ray-tracing default lies on the run-time/error front", "raytracing_front", _front_gap,
           "<=", 0, "(0 on, 1 off)"),
    Target(20, "the same report on the CUDA variant, with the CPU/GPU ratio, where a GPU is lent", "bench",
           lambda r: None, ">=", 1, "GPU runs",
           unmeasured_why="the machine of this run has no GPU; the GPU runs of sessions 22, 24, 26 and 30 "
                          "(benchmarks.ckm_variants, an H100 and H200s) are in docs/ckm-one-pass.md",
           unmeasured_met=None),
    Target(20, "`simart bench --quick` fits in 10 minutes on 2 cores", "bench",
           lambda r: _num(r.get("total_wall_s")), "<=", 600, "s", mode="quick"),
    Target(20, "`simart bench` (full) fits in an hour on 2 cores", "bench",
           lambda r: _num(r.get("total_wall_s")), "<=", 3600, "s", mode="full"),
]


def _met(value: float, op: str, bound: float) -> bool:
    if math.isnan(value):
        return False
    return value <= bound if op == "<=" else value >= bound


def evaluate(bench_results: dict, targets: list[Target] | None = None) -> list[dict]:
    """One row per target: ``issue``, ``target``, ``benchmark``, ``figure``, ``bound``, ``met`` and
    ``why`` (for a row not judged)."""
    by_name = {r["name"]: r for r in bench_results.get("benchmarks", [])}
    mode = bench_results.get("mode")
    rows = []
    for t in TARGETS if targets is None else targets:
        row = {"issue": t.issue, "target": t.text, "benchmark": t.bench, "bound": f"{t.op} {t.bound:g} {t.unit}".strip(),
               "figure": None, "met": None, "why": ""}
        rec = bench_results if t.bench == "bench" else by_name.get(t.bench)
        if t.unmeasured_why:
            row["met"], row["why"] = t.unmeasured_met, f"not measured: {t.unmeasured_why}"
        elif rec is None:
            row["why"] = f"{t.bench} was not run"
        elif t.bench != "bench" and rec.get("status") != "ok":
            row["why"] = f"{t.bench} {rec.get('status')}: {(rec.get('reason') or '').splitlines()[0] if rec.get('reason') else ''}"
        elif t.mode is not None and mode != t.mode:
            row["why"] = f"judged in a {t.mode} run"
        else:
            value = t.figure(rec if t.bench == "bench" else (rec.get("results") or {}))
            if value is None:
                if t.absent_why:
                    row["met"], row["why"] = t.unmeasured_met, f"not measured: {t.absent_why}"
                else:
                    row["why"] = "not measured in a quick run" if mode == "quick" else "not in this run's results"
            else:
                row["figure"] = value
                if t.full_only and mode == "quick":
                    row["why"] = "quick run: measured on a smaller stand-in, judged in the full run"
                else:
                    row["met"] = _met(value, t.op, t.bound)
        rows.append(row)
    return sorted(rows, key=lambda r: r["issue"])


def _fmt(v: float | None) -> str:
    if v is None:
        return "–"
    if math.isinf(v):
        return "unbounded"
    return f"{v:.4g}"


def table_md(rows: list[dict]) -> str:
    verdict = {True: "met", False: "**NOT met**", None: "not judged"}
    count = {k: sum(r["met"] is k for r in rows) for k in (True, False, None)}
    lines = [f"{count[True]} met, {count[False]} not met, {count[None]} not judged in this run.", "",
             "| issue | target | figure | bound | verdict | benchmark | note |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['issue']} | {r['target']} | {_fmt(r['figure'])} | {r['bound']} | {verdict[r['met']]} | "
                     f"{r['benchmark']} | {r['why']} |")
    return "\n".join(lines) + "\n"
