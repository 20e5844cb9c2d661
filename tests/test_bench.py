"""`simart bench`: the Pareto front, the report of failed and skipped benchmarks, the command line.

The benchmarks themselves are not run here (minutes to an hour); no test asserts a wall time.
"""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench
from benchmarks.raytracing_front import dominance, pareto_front, same_result_times, sweep_settings
from simart_pipeline import cli
from simart_pipeline.config import RayTracing


def test_pareto_front_of_known_points():
    # (time, error): A, B, C trade off; D is dominated by B (slower and worse); E equals C
    # (kept: neither dominates the other); F has no error value (never on the front).
    t = [1.0, 2.0, 4.0, 3.0, 4.0, 0.5]
    e = [3.0, 1.0, 0.0, 2.0, 0.0, np.nan]
    assert pareto_front(t, e) == [0, 1, 2, 4]


def test_settings_with_the_same_result_are_one_point_on_the_front():
    # B computes A's paths (a mechanism that changes nothing here) and was timed faster by noise:
    # with its own time it would push A off the front; as one point both stay on it, and C, as
    # accurate but slower than both, does not
    t, res = [1.00, 0.94, 1.20, 0.50], ["a", "a", "c", "d"]
    e = [2.0, 2.0, 2.0, 5.0]
    assert 0 not in pareto_front(t, e)
    merged = same_result_times(t, res)
    assert merged == [0.94, 0.94, 1.20, 0.50]
    assert pareto_front(merged, e) == [3, 0, 1]
    assert dominance(merged, e, 0)["on_front"] is True


def test_pareto_front_staircase_analytic():
    # points on y = 1/x are all non-dominated; points strictly above it are all dominated
    x = np.linspace(1, 10, 10)
    t = np.concatenate([x, x + 0.5])
    e = np.concatenate([1 / x, 1 / x + 0.1])
    assert pareto_front(t, e) == list(range(10))


def test_dominance_says_by_how_much():
    t = [1.0, 2.0, 4.0, 3.0]
    e = [3.0, 1.0, 0.0, 2.0]
    assert dominance(t, e, 1) == {"on_front": True, "time_ratio": 1.0, "error_gap": 0.0}
    d = dominance(t, e, 3)  # (3 s, 2 dB): B does better in 2 s; at <= 3 s the front reaches 1 dB
    assert d["on_front"] is False
    assert d["time_ratio"] == pytest.approx(2.0 / 3.0)
    assert d["error_gap"] == pytest.approx(1.0)


def test_sweep_flips_each_mechanism_and_references_the_most_expensive():
    default = RayTracing()
    settings, ref = sweep_settings(default, quick=True)
    assert settings[0]["group"] == "default" and settings[0]["samples_per_src"] == default.samples_per_src
    mech = {s["label"] for s in settings if s["group"] == "mechanism"}
    assert mech == {"specular reflection off", "diffuse reflection on", "refraction off", "diffraction off"}
    assert ref["samples_per_src"] == max(s["samples_per_src"] for s in settings)
    assert ref["max_depth"] == max(s["max_depth"] for s in settings)
    assert all(ref[m] for m in ("specular_reflection", "diffuse_reflection", "refraction", "diffraction"))
    full, ref_full = sweep_settings(default, quick=False)
    assert ref_full["samples_per_src"] == 10_000_000 and ref_full["max_depth"] == 5
    assert len(full) > len(settings)


@pytest.fixture
def fake_benchmarks(tmp_path, monkeypatch):
    """Three fake benchmark modules on PYTHONPATH: one that fails, one that writes its JSON, one
    that outlives its time limit; and one whose input is missing."""
    mods = tmp_path / "mods"
    mods.mkdir()
    (mods / "fake_fail.py").write_text("import sys\nprint('boom: the scene exploded', file=sys.stderr)\nsys.exit(3)\n")
    (mods / "fake_ok.py").write_text(textwrap.dedent("""
        import json, sys, time
        from pathlib import Path
        out = Path(sys.argv[sys.argv.index('--out') + 1])
        quick = '--quick' in sys.argv
        (out / 'results.json').write_text(json.dumps({'speedup_vs_loop': 7.5, 'quick': quick}))
        held = b'x' * 300_000_000  # written, so resident: the peak the report must show
        time.sleep(1.0)  # held past the bench's reading interval
        """))
    (mods / "fake_slow.py").write_text("import time\ntime.sleep(60)\n")
    monkeypatch.setenv("PYTHONPATH", f"{mods}:{bench.ROOT}")
    args = lambda q, o: ["--out", str(o)] + (["--quick"] if q else [])  # noqa: E731
    return [
        bench.Bench("fake_ok", "A benchmark that works", args),
        bench.Bench("fake_fail", "A benchmark that fails", args),
        bench.Bench("fake_slow", "A benchmark that hangs", args, timeout_s=(1, 1)),
        bench.Bench("fake_nodata", "A benchmark without its input", args, needs=(tmp_path / "no" / "osm",)),
        bench.Bench("fake_noextra", "A benchmark without its extra", args, needs_module="no_such_module_xyz"),
    ]


def test_failed_benchmark_is_reported_as_failed(tmp_path, fake_benchmarks):
    out = tmp_path / "bench"
    res = bench.run_all(out, quick=True, benchmarks=fake_benchmarks, log=lambda *_: None, module_prefix="")
    saved = json.loads((out / "results.json").read_text())
    status = {r["name"]: r["status"] for r in saved["benchmarks"]}
    assert status == {"fake_ok": "ok", "fake_fail": "failed", "fake_slow": "failed",
                      "fake_nodata": "skipped", "fake_noextra": "skipped"}
    recs = {r["name"]: r for r in saved["benchmarks"]}
    assert recs["fake_fail"]["returncode"] == 3
    assert "boom: the scene exploded" in recs["fake_fail"]["reason"]
    assert "limit of 1 s" in recs["fake_slow"]["reason"]
    assert recs["fake_ok"]["results"] == {"speedup_vs_loop": 7.5, "quick": True}
    assert str(tmp_path / "no" / "osm") in recs["fake_nodata"]["reason"]
    assert recs["fake_noextra"]["reason"].startswith("not installed")
    assert (out / "fake_fail" / "stderr.txt").read_text().strip() == "boom: the scene exploded"
    # each run's peak resident memory, from the kernel: the 300 MB the working one held
    assert 0.3 <= recs["fake_ok"]["peak_memory_gb"] < 0.6
    assert recs["fake_fail"]["peak_memory_gb"] < 0.1 and recs["fake_nodata"]["peak_memory_gb"] is None
    # the machine is named
    m = saved["machine"]
    assert m["cores"] >= 1 and m["python"] == ".".join(map(str, sys.version_info[:3]))
    assert set(bench.PACKAGES) <= set(m["packages"])
    assert res["benchmarks"] == saved["benchmarks"]
    # the report says it, in the summary table and in each section
    md = (out / "report.md").read_text()
    assert "1 ran, 2 failed, 2 skipped" in md
    assert "| fake_fail | **FAILED** |" in md
    assert f"| fake_ok | ok | {recs['fake_ok']['wall_s']} | {recs['fake_ok']['peak_memory_gb']} |" in md
    assert "> **FAILED: exit status 3: boom: the scene exploded**" in md
    assert "> **SKIPPED: input missing:" in md and "> **SKIPPED: not installed: no_such_module_xyz" in md
    assert "speedup_vs_loop: 7.5" in md
    for name in status:
        assert f"## {name}:" in md


def test_a_benchmarks_own_report_and_plots_are_linked_from_the_section(tmp_path):
    rec = {"name": "rt", "title": "Ray tracing", "status": "ok", "reason": None, "wall_s": 1.0, "returncode": 0,
           "command": "benchmarks.rt", "results": {"x": 1}, "report": "# Front\n\n![front](front.png)\n",
           "plots": ["rt/front.png"]}
    results = {"mode": "quick", "command": "simart bench --quick --out X", "started_utc": "now",
               "total_wall_s": 1.0, "machine": bench.machine(), "benchmarks": [rec]}
    md = bench.report_md(results, [])
    assert "### Front" in md and "![front](rt/front.png)" in md


def test_simart_bench_help(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["bench", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "--quick" in text and "--out DIR" in text and "report.md" in text


def test_simart_bench_refuses_an_unknown_benchmark(tmp_path, capsys):
    assert cli.main(["bench", "--out", str(tmp_path / "b"), "--only", "no_such_bench"]) == 1
    assert "unknown benchmark(s) no_such_bench" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_every_registered_benchmark_module_exists():
    for b in bench.BENCHMARKS:
        assert (bench.ROOT / "benchmarks" / f"{b.name}.py").is_file(), b.name
        argv = b.args(True, Path("/tmp/x"))
        assert all(isinstance(a, str) for a in argv)


def test_link_sys_measures_the_numpy_side_without_sionna_sys(tmp_path):
    """Without the optional extra the link benchmark still measures the numpy link abstraction and
    says that Sionna SYS is not installed (with it, the comparison runs: pytest -m sys_reference)."""
    import json

    from benchmarks import link_sys

    out = tmp_path / "link.json"
    assert link_sys.main(["--users", "50", "--subcarriers", "24", "--repeat", "1", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["numpy_phy_evaluations_per_s"] == pytest.approx(50 / r["numpy_phy_s"])
    assert r["numpy_mcs_selections_per_s"] == pytest.approx(50 / r["numpy_illa_s"])
    try:
        import sionna.sys  # noqa: F401
        has_sys = True
    except ImportError:
        has_sys = False
    assert ("sionna_sys" in r) != has_sys


def test_publish_writes_the_page_with_its_plots_beside_it(tmp_path, capsys):
    out = tmp_path / "run"
    (out / "rt").mkdir(parents=True)
    png = b"\x89PNG\r\n\x1a\nfake"
    (out / "rt" / "front.png").write_bytes(png)
    rec = {"name": "rt", "title": "Ray tracing", "status": "ok", "reason": None, "wall_s": 1.0, "returncode": 0,
           "command": "benchmarks.rt", "results": {"x": 1}, "report": "# Front\n\n![front](front.png)\n",
           "plots": ["rt/front.png"]}
    results = {"mode": "full", "command": "simart bench --out run", "started_utc": "now", "total_wall_s": 1.0,
               "machine": bench.machine(), "benchmarks": [rec]}
    bench.write(out, results, [])
    doc = tmp_path / "docs" / "benchmarks.md"
    doc.parent.mkdir()
    assert cli.main(["bench", "--publish", str(out), "--doc", str(doc)]) == 0
    md = doc.read_text()
    assert md.startswith("# Benchmarks: run time against error")
    assert "## Benchmarks (full)" in md and "#### Front" in md
    assert "![front](benchmarks/rt/front.png)" in md
    assert (tmp_path / "docs" / "benchmarks" / "rt" / "front.png").read_bytes() == png
    # a run that does not exist is refused with one line naming it, and nothing is written
    other = tmp_path / "other.md"
    assert cli.main(["bench", "--publish", str(tmp_path / "nope"), "--doc", str(other)]) == 1
    assert "nope" in capsys.readouterr().err and not other.exists()


def test_publish_keeps_what_a_person_wrote_above_the_marker(tmp_path):
    out = tmp_path / "run"
    results = {"mode": "full", "command": "simart bench --out run", "started_utc": "now", "total_wall_s": 2.0,
               "machine": bench.machine(), "benchmarks": []}
    bench.write(out, results, [])
    doc = tmp_path / "benchmarks.md"
    bench.publish(out, doc)
    first = doc.read_text()
    assert bench.REPORT_MARKER in first and "2.0 s in all" in first
    doc.write_text("# My findings\n\nThe default is off the front.\n\n" + bench.REPORT_MARKER + "\nold report\n")
    results["total_wall_s"] = 3.0
    bench.write(out, results, [])
    bench.publish(out, doc)
    md = doc.read_text()
    assert md.startswith("# My findings\n\nThe default is off the front.\n\n" + bench.REPORT_MARKER)
    assert "old report" not in md and "3.0 s in all" in md and md.count(bench.REPORT_MARKER) == 1
