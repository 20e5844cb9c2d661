"""The targets table of `simart bench` (benchmarks.targets) and the actors benchmark's per-sensor
configurations. No benchmark is run and no wall time is asserted."""

from __future__ import annotations

from pathlib import Path

from benchmarks import actors, bench, targets
from simart_pipeline.config import load_scene_config

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "demo"


def _bench(mode: str, **by_name) -> dict:
    return {"mode": mode, "total_wall_s": 500.0,
            "benchmarks": [{"name": n, "status": "ok", "results": r, "reason": None} for n, r in by_name.items()]}


def _row(rows, issue, fragment):
    (row,) = [r for r in rows if r["issue"] == issue and fragment in r["target"]]
    return row


def test_targets_judge_each_bound_both_ways():
    t_le = targets.Target(1, "a <= 2", "x", lambda r: r["v"], "<=", 2.0)
    t_ge = targets.Target(1, "a >= 2", "x", lambda r: r["v"], ">=", 2.0)
    for v, le, ge in ((1.0, True, False), (2.0, True, True), (3.0, False, True), (float("inf"), False, True),
                      (float("nan"), False, False)):
        rows = targets.evaluate(_bench("full", x={"v": v}), [t_le, t_ge])
        assert [r["met"] for r in rows] == [le, ge], v


def test_targets_read_the_benchmarks_and_say_why_a_row_is_not_judged():
    res = _bench("full",
                 ckm_generator={"speedup_vs_per_cell_loop": 9.0},
                 osm_build={"helsinki.osm.pbf": {"total_s": 1.5}},
                 rerun={"steps": {"first run": {"wall_s": 100.0},
                                  "unchanged rerun": {"ratio_to_first_wall": 0.05, "ratio_to_first_in_process": 0.03}}})
    res["benchmarks"].append({"name": "sensing", "status": "skipped", "results": None, "reason": "no OSM extract"})
    rows = targets.evaluate(res)
    assert _row(rows, 7, "CKM generator")["met"] is False and _row(rows, 7, "CKM generator")["figure"] == 9.0
    assert _row(rows, 3, "Helsinki")["met"] is True
    assert _row(rows, 15, "whole command")["met"] is True
    assert _row(rows, 15, "excluding start-up")["met"] is False
    assert _row(rows, 2, "demo")["met"] is True
    camera = _row(rows, 6, "camera")
    assert camera["met"] is None and "skipped" in camera["why"]
    # a benchmark that did not run, a mode the row is not judged in, a target nothing measures yet
    assert "not run" in _row(rows, 20, "`cirs` asset")["why"]
    assert _row(rows, 20, "--quick` fits")["met"] is None and _row(rows, 20, "(full) fits")["met"] is True
    unmeasured = _row(rows, 15, "sequential")
    assert unmeasured["met"] is False and unmeasured["why"].startswith("not measured")
    # measured where the rerun benchmark ran with --baseline
    res["benchmarks"][[b["name"] for b in res["benchmarks"]].index("rerun")]["results"]["baseline"] = {
        "first_run_speedup_vs_baseline": 1.31}
    measured = _row(targets.evaluate(res), 15, "sequential")
    assert measured["met"] is True and measured["figure"] == 1.31
    # every target appears, judged or not
    assert len(rows) == len(targets.TARGETS)


def test_quick_run_does_not_judge_targets_named_for_the_full_scene():
    res = _bench("quick", rerun={"steps": {"first run": {"wall_s": 30.0},
                                           "unchanged rerun": {"ratio_to_first_wall": 0.5,
                                                               "ratio_to_first_in_process": 0.5}}})
    row = _row(targets.evaluate(res), 15, "whole command")
    assert row["met"] is None and row["figure"] == 0.5 and "quick" in row["why"]


def _ckm_set(coverage=99.5, gain=(0.2, 2.0), top3=99.5, ratio=1.5, equal_error_ratio=0.9, first_order_ratio=1.2):
    """A ckm_solver mechanism set's results, only the figures the targets read."""
    e = {"path_gain_db": {"p50": gain[0], "p95": gain[1]}, "rms_delay_spread_ns": {"p50": 1.0},
         "best_beam_agreement_pct": 96.0, "best_beam_top3_agreement_pct": top3,
         **{k: {"p50": 1.0} for k in ("asa_deg", "asd_deg", "zsa_deg")}, "zsd_deg": {"p50": None}}
    like = {**e, "path_gain_db": {"p50": 0.1, "p95": 4.0}}  # in PathSolver's diffuse model
    return {"coverage": {"covered_of_reached_pct": coverage}, "errors_vs_cell_points": e,
            "errors_vs_cell_points_pathsolver_diffuse_model": like,
            "errors_vs_centre": {"toa_ns": {"p50": 0.1}}, "speedup_vs_per_cell_loop": 150.0,
            "radio_map_solver": {"one_pass_over_radio_map_time": ratio,
                                 "first_order_diffraction_one_pass": {"over_radio_map_time": first_order_ratio},
                                 "at_one_pass_rays": {
                "path_gain_agreement_with_one_pass": {"abs_diff_db": {"p50": 0.05, "p95": 0.5}}},
                "path_gain_agreement_like_for_like": {"abs_diff_db": {"p50": 0.05, "p95": 0.5}},
                "equal_error": {"one_pass_over_radio_map_time_at_equal_error": equal_error_ratio,
                                "like_for_like_at_reference_rays": {"abs_diff_db": {"p50": 0.08}}}}}


def test_ckm_solver_targets_read_each_scene_and_mechanism_set():
    from benchmarks import ckm_solver as cs

    sets = {"los_specular": _ckm_set(ratio=3.0), **{m: _ckm_set() for m in cs.TARGET_SETS}}
    sets[cs.TARGET_SETS[0]] = _ckm_set(coverage=80.0, top3=99.0, ratio=3.0, first_order_ratio=1.9)
    res = _bench("full", ckm_solver={"scenes": {"street_canyon": {"sets": sets}, "urban": {"sets": {
        cs.TARGET_SETS[0]: _ckm_set(equal_error_ratio=None)}}, "munich": {"sets": {}}}})
    rows = targets.evaluate(res)
    ms = cs.TARGET_SETS[0]
    cov = _row(rows, 17, f"street_canyon, mechanisms `{ms}`, against PathSolver with the same: a value in")
    assert cov["met"] is False and cov["figure"] == 80.0
    assert _row(rows, 17, f"street_canyon, mechanisms `{ms}`, against PathSolver with the same: PathSolver's best beam")["met"]
    assert _row(rows, 17, "street_canyon, mechanisms `all`, against PathSolver with the same: angular")["figure"] == 1.0
    assert _row(rows, 17, "street_canyon, LoS + specular: time within 2x")["met"] is False
    pre = f"street_canyon, mechanisms `{ms}`, against PathSolver with the same:"
    like95 = _row(rows, 17, f"{pre} in PathSolver's diffuse model, path gain p95")
    assert like95["met"] is False and like95["figure"] == 4.0
    assert _row(rows, 17, f"{pre} path gain p95")["met"] is True
    assert _row(rows, 8, "street_canyon: path gain p50")["met"] is True
    # a scene without the set: not judged, with why
    assert "not in this run" in _row(rows, 17, f"munich, mechanisms `{ms}`, against PathSolver with the same: a value in")["why"]
    # every chain against RadioMapSolver's fewer (3.0x) and like for like (1.9x): two rows
    assert _row(rows, 17, f"{pre} time within 2x of RadioMapSolver's (same")["met"] is False
    lfl = _row(rows, 17, f"{pre} time within 2x of RadioMapSolver's like for like")
    assert lfl["met"] is True and lfl["figure"] == 1.9
    equal = f"mechanisms `{ms}`, against PathSolver with the same: time within 2x of RadioMapSolver's at equal"
    assert _row(rows, 17, f"street_canyon, {equal}")["met"] is True
    # measured, and no one-pass ray count reached RadioMapSolver's error: not met, not "n/a"
    assert _row(rows, 17, f"urban, {equal}")["met"] is False
    assert _row(rows, 17, f"street_canyon, mechanisms `{ms}`, against PathSolver with the same: path gain against "
                "RadioMapSolver (its diffraction model), both")["figure"] == 0.08
    assert not [r for r in rows if r["issue"] == 17 and r["why"].startswith("not measured")]
    quick = targets.evaluate(_bench("quick", ckm_solver={"scenes": {"street_canyon": {"sets": sets}}}))
    row = _row(quick, 17, f"street_canyon, mechanisms `{ms}`, against PathSolver with the same: a value in")
    assert row["met"] is None and row["figure"] == 80.0 and "quick" in row["why"]


def test_report_carries_the_targets_table():
    res = _bench("full", ckm_generator={"speedup_vs_per_cell_loop": 12.0})
    res.update(command="simart bench --out X", started_utc="2026-11-25T00:00:00+00:00",
               machine={"cpu": "cpu", "cores": 2, "memory_gib": 24, "os": "linux", "python": "3.11", "packages": {},
                        "git_commit": "abc", "git_dirty": False})
    for r in res["benchmarks"]:
        r.update(title=r["name"], wall_s=1.0, command="c", report=None, plots=[], prepare_s=None)
    res["targets"] = targets.evaluate(res)
    md = bench.report_md(res)
    assert "## Targets of every issue" in md
    assert "| 7 | CKM generator >= 10x a loop of one PathSolver call per cell | 12 | >= 10 x | met |" in md


def test_only_sensor_keeps_exactly_one_rendered_sensor():
    cfg = load_scene_config(DEMO)
    rendered = [(d.name, s.name) for d in (*cfg.platforms, *cfg.base_stations) for s in d.sensors
                if s.kind in ("camera", "lidar")]
    others = sum(1 for d in (*cfg.platforms, *cfg.base_stations) for s in d.sensors if s.kind not in ("camera", "lidar"))
    assert len(rendered) >= 2
    for device, sensor in rendered:
        one = actors._only_sensor(cfg, device, sensor)
        kept = [(d.name, s.name) for d in (*one.platforms, *one.base_stations) for s in d.sensors
                if s.kind in ("camera", "lidar")]
        assert kept == [(device, sensor)]
        assert sum(1 for d in (*one.platforms, *one.base_stations) for s in d.sensors
                   if s.kind not in ("camera", "lidar")) == others


def test_rerun_report_names_what_was_computed_and_says_all_only_when_it_was():
    from benchmarks.rerun import _computed_summary

    first = [f"{a} (demo|{w})" for a in ("sensor_frames", "session", "session_bag", "cirs") for w in ("sunny", "rainy", "night")]
    nine = first[:9]
    assert _computed_summary(nine, len(first)) == "9: sensor_frames x3, session x3, session_bag x3"
    assert _computed_summary(first, len(first)).startswith("12 (all): ")
    assert _computed_summary(first[:2], len(first)) == "sensor_frames (demo|sunny), sensor_frames (demo|rainy)"
