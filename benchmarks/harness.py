"""What the integration benchmarks share: a scene on its own data root and ephemeral Dagster instance,
asset partitions materialised there as ``simart run`` does (``cli.materialize_scene``), one run per
call, with the run's wall time and each step's time from Dagster's own event log; a timer that
alternates the order of the things it compares; the machine named; ratios and report files.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import time
from pathlib import Path

import yaml

TINY = Path(__file__).resolve().parents[1] / "tests" / "scenes" / "tiny"
QUIET = {"loggers": {"console": {"config": {"log_level": "CRITICAL"}}}}


def machine() -> str:
    return (f"{platform.machine()}, {os.cpu_count()} CPU cores, {platform.platform()}; Python "
            f"{platform.python_version()}; shared machine (other jobs may run beside this one)")


def scene_copy(src: Path, dst: Path, edit=None, name: str | None = None) -> Path:
    """A copy of scene folder ``src`` at ``dst``, its ``scene.yaml`` changed by ``edit(raw)``
    (and renamed to ``name``) when given."""
    shutil.copytree(src, dst)
    if edit or name:
        path = dst / "scene.yaml"
        raw = yaml.safe_load(path.read_text())
        if edit:
            edit(raw)
        if name:
            raw["name"] = name
        path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return dst


class Pipeline:
    """One scene registered on its own data root with an ephemeral Dagster instance (as
    ``cli.materialize_scene`` sets it up), to materialise chosen asset partitions one run at a time."""

    def __init__(self, scene_dir: Path, data_root: Path, instance=None):
        import dagster as dg

        from simart_pipeline import registry
        from simart_pipeline.assets.config_sources import report_config_versions
        from simart_pipeline.definitions import build_definitions
        from simart_pipeline.partitions import scene_partitions

        self.scene_dir, self.data_root = Path(scene_dir), Path(data_root)
        self.cfg = registry.register(self.scene_dir, self.data_root)
        self.instance = instance or dg.DagsterInstance.ephemeral()
        self.instance.add_dynamic_partitions(scene_partitions.name, [self.cfg.name])
        self.resources = build_definitions(data_root=str(self.data_root)).resources
        report_config_versions(self.instance, self.resources["project"].version_plan(self.cfg.name))

    def close(self) -> None:
        """Dispose of the instance here, in this thread (left to the garbage collector, its
        in-memory SQLite connections complain from whichever thread collects them)."""
        self.instance.dispose()

    def key(self, **dims):
        """The partition key: ``key()`` the scene's, ``key(weather=...)``, ``key(weather_group=...)``
        or ``key(tile=...)`` a two-dimensional one."""
        import dagster as dg

        return self.cfg.name if not dims else dg.MultiPartitionKey({"scene": self.cfg.name, **dims})

    def upstream(self) -> None:
        """The scene's own partitions (source geometry, meshes, trajectory): what every stage reads."""
        self.materialize(["osm_extract", "paired_meshes", "trajectory"], self.key())

    def materialize(self, names: list[str], key, force: bool = False) -> dict:
        """One Dagster run of the asset partitions ``names`` at ``key`` (their checks included):
        ``{"wall_s", "steps": {step key: seconds}, "metadata": {asset: {key: value}}}``."""
        import dagster as dg

        from simart_pipeline.assets import ALL_ASSETS, ALL_CHECKS
        from simart_pipeline.assets.versioning import FORCE_TAG

        t0 = time.perf_counter()
        result = dg.materialize([*ALL_ASSETS, *ALL_CHECKS], selection=names, partition_key=key,
                                instance=self.instance, resources=self.resources, run_config=QUIET,
                                raise_on_error=True, tags={FORCE_TAG: "true"} if force else None)
        wall = time.perf_counter() - t0
        meta = {}
        for name in names:
            for m in result.asset_materializations_for_node(name):
                meta[name] = {k: getattr(v, "value", v) for k, v in m.metadata.items()}
        return {"wall_s": wall, "steps": step_seconds(self.instance, result.run_id), "metadata": meta}


def step_seconds(instance, run_id: str) -> dict[str, float]:
    """Each step's time in a run, from Dagster's event log (step start to step success)."""
    start, out = {}, {}
    for e in instance.all_logs(run_id):
        ev = e.dagster_event
        if ev is None or not e.step_key:
            continue
        if ev.event_type_value == "STEP_START":
            start[e.step_key] = e.timestamp
        elif ev.event_type_value in ("STEP_SUCCESS", "STEP_FAILURE") and e.step_key in start:
            out[e.step_key] = e.timestamp - start[e.step_key]
    return out


def alternating(fns: dict[str, callable], repeats: int) -> dict[str, list[float]]:
    """Each of ``fns`` (name -> callable returning seconds, or None to time the call) run
    ``repeats`` times, the order reversed every other round: ``{name: [seconds, ...]}``."""
    names = list(fns)
    times: dict[str, list[float]] = {n: [] for n in names}
    for r in range(repeats):
        for n in (names if r % 2 == 0 else names[::-1]):
            t0 = time.perf_counter()
            got = fns[n]()
            times[n].append(float(got) if isinstance(got, (int, float)) else time.perf_counter() - t0)
    return times


def summary(samples: list[float]) -> dict:
    """Best and median of repeated timings (seconds, 4 decimals)."""
    return {"best_s": round(min(samples), 4), "median_s": round(statistics.median(samples), 4),
            "samples_s": [round(s, 4) for s in samples]}


def ratio(a: float, b: float) -> float | None:
    """``a / b``, or None when ``b`` is not positive."""
    return round(a / b, 4) if b and b > 0 else None


def write_outputs(out: Path, results: dict, lines: list[str]) -> None:
    """``out/results.json`` and ``out/report.md``; the report is printed too."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def quiet_dagster() -> None:
    """Dagster's own log off: the benchmarks print their own lines."""
    import logging

    logging.getLogger("dagster").setLevel(logging.CRITICAL)


def cli_main(run, doc: str, argv=None) -> int:
    """``python -m benchmarks.NAME [--quick] --out DIR`` of a benchmark whose ``run(quick, out)``
    measures and writes ``DIR/results.json`` and ``DIR/report.md``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the tiny test scene instead of the demo")
    ap.add_argument("--out", required=True, type=Path, help="directory for results.json and report.md")
    args = ap.parse_args(argv)
    run(args.quick, args.out)
    return 0
