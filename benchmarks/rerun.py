"""Reruns of the demo, measured side by side on a fresh data root: the first run, an unchanged
rerun, a rerun after one sensor's rate changes and one after the rain materials change.

    python -m benchmarks.rerun --out DIR [--scene scenes/demo] [--baseline REV [--repeats N]]

Each step is the whole ``simart run`` command in a new process, as a user types it (wall time,
interpreter and library start-up included), on a copy of the scene with its own data root and
Dagster instance. ``in_process_s`` is the time ``simart run`` itself reports for its partitions
(start-up excluded). Writes ``DIR/results.json`` and ``DIR/report.md``.

``--baseline REV`` also times, in the same run, the first run of the same scene by the code of git
revision ``REV`` (extracted with ``git archive``, run by this interpreter and its libraries, on its own
fresh data root and instance), before and after this commit's first run: issue 15's "figures of the
commit before, measured in the same run". ``first_run_speedup_vs_baseline`` is the baseline's mean
wall time over this commit's, from ``--repeats`` first runs of each (default 2), alternated.

Like for like: where a default of the :data:`PINNED_SECTIONS` sections differs between the two
codes (the ray-tracing mechanisms turned on since a baseline, say) and the scene does not set it,
both codes' first runs read a copy of the scene with the baseline's value written in
(``baseline.pinned``), so the ratio is of the same work. Keys the baseline does not know keep this
commit's default (``baseline.new_keys``). This commit's first run with its own defaults stays the
``first run`` step.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import mean

import yaml

from benchmarks.common import DEMO

SIMART = [sys.executable, "-m", "simart_pipeline.cli"]
TARGET_UNCHANGED_WALL = 0.10   # issue 15: the whole command, start-up included
TARGET_UNCHANGED_IN_PROCESS = 0.02
TARGET_FIRST_RUN_SPEEDUP = 1.3  # issue 15: against the baseline's first run (--baseline)
# Config sections whose defaults a baseline comparison pins to the baseline's (see the module doc)
PINNED_SECTIONS = ("ray_tracing", "ckm")
_DEFAULTS_SCRIPT = (
    "import json, sys\n"
    "from simart_pipeline.config import SceneConfig\n"
    "print(json.dumps({s: SceneConfig.model_fields[s].default.model_dump(mode='json') for s in sys.argv[1:]\n"
    "                  if s in SceneConfig.model_fields}))\n")


def _edit(scene: Path, edit) -> None:
    path = scene / "scene.yaml"
    raw = yaml.safe_load(path.read_text())
    edit(raw)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


def _first_sensor(raw: dict) -> dict:
    for dev in (*raw["platforms"], *raw["base_stations"]):
        if dev.get("sensors"):
            return dev["sensors"][0]
    raise SystemExit("the scene has no sensor to edit")


def _run(scene: Path, data: Path, env: dict, cwd: Path | None = None) -> dict:
    t0 = time.perf_counter()
    res = subprocess.run([*SIMART, "run", str(scene), "--data", str(data)], capture_output=True, text=True,
                         env=env, cwd=cwd)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"simart run failed:\n{res.stdout}\n{res.stderr}")
    computed = sorted(re.findall(r"\] (\S+ \([^)]*\)): computing", res.stdout))
    m = re.search(r"asset partitions computed, \d+ up to date, in ([0-9.]+) s", res.stdout)
    return {"wall_s": round(wall, 2), "in_process_s": float(m.group(1)) if m else None, "computed": computed}


def _computed_summary(computed: list[str], every: int) -> str:
    """Up to 8 partitions by name; more as a count per asset, and 'all' only when it is all of them."""
    if len(computed) <= 8:
        return ", ".join(computed)
    per_asset: dict[str, int] = {}
    for c in computed:
        per_asset[c.split(" (")[0]] = per_asset.get(c.split(" (")[0], 0) + 1
    counts = ", ".join(f"{a} x{n}" for a, n in per_asset.items())
    return f"{len(computed)}{' (all)' if len(computed) == every else ''}: {counts}"


def _extract(rev: str, into: Path) -> Path:
    """The tree of git revision ``rev`` of this repository, extracted under ``into``."""
    repo = Path(__file__).resolve().parents[1]
    into.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(repo), "archive", rev], capture_output=True, check=False)
    if archive.returncode != 0:
        raise SystemExit(f"--baseline {rev}: git archive failed: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into


def _first_run_of(code: Path | None, scene: Path, tmp: Path, tag: str, base_env: dict) -> dict:
    """A first run of ``scene`` on a fresh data root and instance, by the code at ``code`` (None:
    this checkout)."""
    data, home = tmp / f"data_{tag}", tmp / f"home_{tag}"
    home.mkdir()
    env = {**base_env, "DAGSTER_HOME": str(home)}
    if code is not None:  # ahead of this checkout's editable install
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(code), base_env.get("PYTHONPATH")]))
    try:
        return _run(scene, data, env, cwd=code)
    finally:
        shutil.rmtree(data, ignore_errors=True)
        shutil.rmtree(home, ignore_errors=True)


def config_defaults(code: Path | None, env: dict, sections=PINNED_SECTIONS) -> dict:
    """{section: {key: default}} of the scene config's ``sections`` in the code at ``code`` (None:
    this checkout), read by this interpreter in a new process (a baseline's modules must not meet
    this checkout's)."""
    run_env = dict(env)
    if code is not None:
        run_env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(code), env.get("PYTHONPATH")]))
    res = subprocess.run([sys.executable, "-c", _DEFAULTS_SCRIPT, *sections], capture_output=True, text=True,
                         env=run_env, cwd=code)
    if res.returncode != 0:
        raise SystemExit(f"reading the config defaults of {code or 'this checkout'} failed:\n{res.stderr}")
    return json.loads(res.stdout)


def pin_baseline_defaults(raw: dict, baseline: dict, this: dict) -> tuple[dict, list[str]]:
    """The scene config ``raw`` with the baseline's default written in wherever a key of a section
    of ``baseline`` ({section: {key: default}}) has another default in ``this`` and ``raw`` does not
    set it: (what was pinned, {"section.key": value}; the keys only ``this`` knows, which keep its
    default). ``raw`` is changed in place."""
    pinned, new_keys = {}, []
    for section, base in baseline.items():
        ours = this.get(section, {})
        given = raw.get(section) or {}
        for key, value in ours.items():
            if key not in base:
                new_keys.append(f"{section}.{key}")
            elif key not in given and base[key] != value:
                raw.setdefault(section, {})[key] = base[key]
                pinned[f"{section}.{key}"] = base[key]
    return pinned, sorted(new_keys)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="directory for results.json and report.md")
    ap.add_argument("--scene", default=str(DEMO), help="scene directory (default: the demo)")
    ap.add_argument("--baseline", metavar="REV", help="also time the first run by git revision REV's code, "
                    "before and after this commit's (e.g. the commit before a change)")
    ap.add_argument("--repeats", type=int, default=2, help="first runs of each, alternated, with --baseline "
                    "(default 2)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    src = Path(args.scene).resolve()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = tmp / src.name
        shutil.copytree(src, scene)
        data, home = tmp / "data", tmp / "dagster_home"
        home.mkdir()
        env = {**os.environ, "DAGSTER_HOME": str(home), "PYTHONHASHSEED": "0"}
        steps, baseline = {}, None
        if args.baseline:
            code = _extract(args.baseline, tmp / "baseline_code")
            like = tmp / "like_for_like" / src.name  # the scene with the baseline's defaults written in
            shutil.copytree(src, like)
            pinned, new_keys = {}, []

            def pin(raw):
                p, n = pin_baseline_defaults(raw, config_defaults(code, env), config_defaults(None, env))
                pinned.update(p)
                new_keys.extend(n)
            _edit(like, pin)
            baseline = {"rev": args.baseline, "pinned": pinned, "new_keys": new_keys,
                        "runs": [_first_run_of(code, like, tmp, "b0", env)]}
        steps["first run"] = _run(scene, data, env)
        if baseline is not None:  # baseline, this commit, baseline, this commit ...: drift shows in both
            # this commit's own first run is the same work when nothing was pinned
            baseline["this_commit_runs"] = [steps["first run"] if not baseline["pinned"]
                                            else _first_run_of(None, like, tmp, "c0", env)]
            for k in range(1, args.repeats):
                baseline["runs"].append(_first_run_of(code, like, tmp, f"b{k}", env))
                baseline["this_commit_runs"].append(_first_run_of(None, like, tmp, f"c{k}", env))
        steps["unchanged rerun"] = _run(scene, data, env)
        sensor = {}

        def rate(raw):
            s = _first_sensor(raw)
            sensor.update(name=s["name"], old=s.get("rate_hz"))
            s["rate_hz"] = float(s.get("rate_hz") or 1.0) * 2
        _edit(scene, rate)
        steps[f"after {sensor['name']}'s rate changed"] = _run(scene, data, env)
        _edit(scene, lambda raw: raw.setdefault("materials", {}).update(
            rain={"concrete": "wet_brick", "medium_dry_ground": "wet_ground", "very_dry_ground": "wet_ground"}))
        steps["after the rain materials changed"] = _run(scene, data, env)
    first = steps["first run"]
    for s in steps.values():
        s["ratio_to_first_wall"] = round(s["wall_s"] / first["wall_s"], 4)
        if s["in_process_s"] is not None and first["in_process_s"]:
            s["ratio_to_first_in_process"] = round(s["in_process_s"] / first["in_process_s"], 4)
    unchanged = steps["unchanged rerun"]
    if baseline is not None:
        base_wall = mean(r["wall_s"] for r in baseline["runs"])
        this_wall = mean(r["wall_s"] for r in baseline["this_commit_runs"])
        baseline.update(mean_wall_s=round(base_wall, 2), this_commit_mean_wall_s=round(this_wall, 2),
                        first_run_speedup_vs_baseline=round(base_wall / this_wall, 3))
    results = {
        "scene": src.name, "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
        "python": platform.python_version(), "steps": steps, "baseline": baseline,
        "targets": {"unchanged_wall_ratio_max": TARGET_UNCHANGED_WALL,
                    "unchanged_in_process_ratio_max": TARGET_UNCHANGED_IN_PROCESS,
                    "unchanged_wall_met": unchanged["ratio_to_first_wall"] <= TARGET_UNCHANGED_WALL,
                    "unchanged_in_process_met": unchanged.get("ratio_to_first_in_process", 1) <= TARGET_UNCHANGED_IN_PROCESS},
    }
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    lines = [f"# Reruns of `{src.name}`", "", f"Machine: {results['machine']}; Python {results['python']}. "
             "Each step is a whole `simart run` in a new process on one fresh data root and Dagster instance.", "",
             "| step | wall (s) | / first | in process (s) | / first | computed partitions |",
             "|---|---|---|---|---|---|"]
    every = len(steps["first run"]["computed"])
    for name, s in steps.items():
        comp = _computed_summary(s["computed"], every)
        lines.append(f"| {name} | {s['wall_s']} | {s['ratio_to_first_wall']:.3f} | {s['in_process_s']} | "
                     f"{s.get('ratio_to_first_in_process', float('nan')):.4f} | {comp or 'none'} |")
    t = results["targets"]
    lines += ["", f"Unchanged rerun: {unchanged['ratio_to_first_wall']:.1%} of the first run's wall time "
              f"(target <= {TARGET_UNCHANGED_WALL:.0%}: {'met' if t['unchanged_wall_met'] else 'missed'}); "
              f"{unchanged.get('ratio_to_first_in_process', float('nan')):.2%} excluding start-up "
              f"(target <= {TARGET_UNCHANGED_IN_PROCESS:.0%}: {'met' if t['unchanged_in_process_met'] else 'missed'})."]
    if baseline is not None:
        same = (", both with the baseline's defaults of " + ", ".join(f"`{k}: {v}`" for k, v in baseline["pinned"].items())
                if baseline["pinned"] else "")
        lines += ["", f"First run against `{baseline['rev']}`'s code{same}, {len(baseline['runs'])} of each alternated "
                  f"(baseline first): {', '.join(str(r['wall_s']) for r in baseline['runs'])} s against "
                  f"{', '.join(str(r['wall_s']) for r in baseline['this_commit_runs'])} s; this commit "
                  f"{baseline['first_run_speedup_vs_baseline']:.3f}x faster (target >= "
                  f"{TARGET_FIRST_RUN_SPEEDUP}x: "
                  f"{'met' if baseline['first_run_speedup_vs_baseline'] >= TARGET_FIRST_RUN_SPEEDUP else 'missed'})."]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
