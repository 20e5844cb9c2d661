"""``simart``: run a scene end to end, validate it, list scenes, open the Dagster UI."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from simart_pipeline import registry

DAGSTER_HOME = registry.REPO_ROOT / ".dagster_home"


def _prepare_dagster_home() -> Path:
    """A project-local DAGSTER_HOME holding a copy of the repository's dagster.yaml."""
    home = Path(os.environ.get("DAGSTER_HOME") or DAGSTER_HOME)
    home.mkdir(parents=True, exist_ok=True)
    src = registry.REPO_ROOT / "dagster.yaml"
    dst = home / "dagster.yaml"
    if src.exists() and (not dst.exists() or dst.read_bytes() != src.read_bytes()):
        shutil.copyfile(src, dst)
    os.environ["DAGSTER_HOME"] = str(home)
    return home


def _print_problems(problems: list[str]) -> None:
    for p in problems:
        print(f"  - {p}", file=sys.stderr)


def cmd_validate(args) -> int:
    from simart_pipeline.validation import scene_problems

    cfg, problems = scene_problems(args.scene_dir)
    if problems:
        print(f"{args.scene_dir}: {len(problems)} problem(s):", file=sys.stderr)
        _print_problems(problems)
        return 1
    print(f"{args.scene_dir}: scene {cfg.name!r} is valid "
          f"({len(cfg.base_stations)} base stations, {len(cfg.platforms)} platforms, "
          f"weathers {', '.join(cfg.weathers)})")
    return 0


def cmd_scenes(args) -> int:
    from simart_pipeline.config import ConfigError, load_scene_config

    root = Path(args.scenes_root or registry.default_scenes_root())
    dirs = registry.list_scenes(root)
    if not dirs:
        print(f"no scenes under {root}")
        return 0
    for d in dirs:
        try:
            cfg = load_scene_config(d)
            print(f"{cfg.name:20s} {d}  [{cfg.source.kind}] {cfg.description}")
        except ConfigError as exc:
            print(f"{d.name:20s} {d}  INVALID: {len(exc.problems)} problem(s), see `simart validate {d}`")
    return 0


def _plan(cfg, weathers, tiles):
    from simart_pipeline.ckm.grid import scene_tiles

    ws = list(weathers or cfg.weathers)
    unknown = [w for w in ws if w not in cfg.weathers]
    if unknown:
        raise SystemExit(f"--weather {' '.join(unknown)}: not among the scene's weathers {list(cfg.weathers)}")
    ts = list(tiles or scene_tiles(cfg.ckm))
    unknown = [t for t in ts if t not in scene_tiles(cfg.ckm)]
    if unknown:
        raise SystemExit(f"--tile {' '.join(unknown)}: not among the scene's tiles {scene_tiles(cfg.ckm)}")
    return ws, ts


def materialize_scene(scene_dir: Path, data_root: Path, weathers=None, tiles=None, verbose=False,
                      instance=None, progress=print) -> dict[str, list[Path]]:
    """Register the scene and materialise every asset partition of it; returns the store paths."""
    import dagster as dg

    from simart_pipeline.assets import ALL_ASSETS
    from simart_pipeline.definitions import build_definitions
    from simart_pipeline.partitions import scene_partitions

    cfg = registry.register(scene_dir, data_root)
    weathers, tiles = _plan(cfg, weathers, tiles)
    if instance is None:
        _prepare_dagster_home()
        instance = dg.DagsterInstance.get()
    instance.add_dynamic_partitions(scene_partitions.name, [cfg.name])
    defs = build_definitions(data_root=str(data_root))
    resources = defs.resources
    run_config = None if verbose else {"loggers": {"console": {"config": {"log_level": "WARNING"}}}}
    steps = [(["osm_extract", "paired_meshes", "trajectory"], cfg.name)]
    steps += [(["sensor_frames", "cirs", "kpis", "session"], dg.MultiPartitionKey({"scene": cfg.name, "weather": w}))
              for w in weathers]
    steps += [(["ckm_layers"], dg.MultiPartitionKey({"scene": cfg.name, "tile": t})) for t in tiles]
    total = sum(len(s[0]) for s in steps)
    done = 0
    t_start = time.perf_counter()
    for names, key in steps:
        label = key if isinstance(key, str) else "|".join(f"{k}={v}" for k, v in key.keys_by_dimension.items())
        t0 = time.perf_counter()
        progress(f"[{done + 1:>2}-{done + len(names):>2}/{total}] {', '.join(names)} ({label}) ...")
        result = dg.materialize(ALL_ASSETS, selection=names, partition_key=key, instance=instance,
                                resources=resources, run_config=run_config, raise_on_error=False)
        if not result.success:
            failures = [e for e in result.all_events if e.is_step_failure]
            msg = failures[0].step_failure_data.error.message.strip() if failures else "run failed"
            raise RuntimeError(f"{', '.join(names)} ({label}) failed: {msg}")
        done += len(names)
        progress(f"        done in {time.perf_counter() - t0:.1f} s")
    progress(f"all {total} asset partitions of scene {cfg.name!r} materialised in "
             f"{time.perf_counter() - t_start:.1f} s")
    out: dict[str, list[Path]] = {}
    for names, key in steps:
        for name in names:
            out.setdefault(name, []).append(store_of(name, key, data_root))
    return out


def store_of(asset: str, key, data_root: Path) -> Path:
    from simart_pipeline import stores
    from simart_pipeline.partitions import split_key
    from simart_pipeline.resources import DIRECTORY_ASSETS

    scene, sub = split_key(key)
    return stores.store_path(data_root, asset, scene, sub, suffix="" if asset in DIRECTORY_ASSETS else ".zarr")


def cmd_run(args) -> int:
    from simart_pipeline import engine
    from simart_pipeline.validation import scene_problems

    try:
        backend = engine.preflight()
    except engine.PreflightError as exc:
        print(f"preflight: {exc}", file=sys.stderr)
        return 3
    cfg, problems = scene_problems(args.scene_dir)
    if problems:
        print(f"{args.scene_dir}: {len(problems)} problem(s); nothing was run:", file=sys.stderr)
        _print_problems(problems)
        return 1
    data_root = Path(args.data or registry.default_data_root()).resolve()
    print(f"scene {cfg.name!r} from {Path(args.scene_dir).resolve()}; backend {backend}; data root {data_root}")
    try:
        stores = materialize_scene(Path(args.scene_dir), data_root, args.weather, args.tile, args.verbose)
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print("outputs:")
    for asset, paths in stores.items():
        for p in paths:
            print(f"  {asset:14s} {p}")
    return 0


def cmd_dev(args) -> int:
    home = _prepare_dagster_home()
    print(f"DAGSTER_HOME={home}")
    extra = args.dagster_args[1:] if args.dagster_args[:1] == ["--"] else args.dagster_args
    cmd = [sys.executable, "-m", "dagster", "dev", "-m", "simart_pipeline.definitions", *extra]
    return subprocess.call(cmd, cwd=registry.REPO_ROOT)


def cmd_preflight(args) -> int:
    from simart_pipeline import engine

    try:
        print(f"ok: {engine.preflight()}")
        return 0
    except engine.PreflightError as exc:
        print(f"preflight: {exc}", file=sys.stderr)
        return 3


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="simart",
        description="simart-pipeline: turn a scene (OpenStreetMap extract, mesh, or procedural layout) into a "
                    "synchronized multimodal ISAC dataset: trajectories, camera/LiDAR/IMU/GPS streams, "
                    "Sionna RT channels, KPIs and channel knowledge maps, as Zarr stores.")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="materialise every asset of a scene on the embedded Dagster instance",
                       description="Validate and register SCENE_DIR, then materialise all of its asset partitions "
                                   "(every weather and CKM tile unless narrowed) and print where the stores are.")
    r.add_argument("scene_dir", metavar="SCENE_DIR", help="directory holding scene.yaml (e.g. scenes/demo)")
    r.add_argument("--weather", nargs="+", metavar="W", help="only these weathers (sunny, rainy, night)")
    r.add_argument("--tile", nargs="+", metavar="T", help="only these CKM tiles (r<row>c<col>)")
    r.add_argument("--data", metavar="DIR", help="data root for the stores (default: ./data or $SIMART_DATA)")
    r.add_argument("--verbose", action="store_true", help="show Dagster's own event log")
    r.set_defaults(func=cmd_run)
    v = sub.add_parser("validate", help="check a scene's config and inputs",
                       description="Check SCENE_DIR/scene.yaml against the schema and the scene's inputs; report "
                                   "every problem with its file and key path. Exit status 1 on any problem.")
    v.add_argument("scene_dir", metavar="SCENE_DIR")
    v.set_defaults(func=cmd_validate)
    s = sub.add_parser("scenes", help="list the scenes under scenes/",
                       description="List every directory under the scenes root that holds a scene.yaml.")
    s.add_argument("--scenes-root", metavar="DIR", help="default: the repository's scenes/ or $SIMART_SCENES")
    s.set_defaults(func=cmd_scenes)
    d = sub.add_parser("dev", help="open the Dagster UI on the project-local instance",
                       description="Run `dagster dev` with DAGSTER_HOME=.dagster_home; extra arguments go to dagster.")
    d.add_argument("dagster_args", nargs=argparse.REMAINDER)
    d.set_defaults(func=cmd_dev)
    f = sub.add_parser("preflight", help="check that Sionna RT can run here (libLLVM >= 17 or CUDA)",
                       description="Report the ray-tracing backend, or what is missing and how to fix it.")
    f.set_defaults(func=cmd_preflight)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
