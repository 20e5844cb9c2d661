"""``simart``: run a scene end to end, validate it, list scenes, build a scene, open the Dagster UI.

Every failure of a command ends with one line on stderr, ``error: <file>: <key path or topic>: <what
is wrong>`` (the project's own message, or the innermost exception's with its class), and a non-zero
exit status; the stack trace is printed only with ``--verbose`` (:func:`main`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import shutil
import socket
import subprocess
import sys
import time
import traceback
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


class CliError(Exception):
    """A command's failure whose message is already the one line to print (file: topic: problem)."""


def _print_problems(problems: list[str]) -> None:
    for p in problems:
        print(f"  - {' '.join(p.split())}", file=sys.stderr)  # one line each (YAML errors span several)


def _os_problem(exc: OSError) -> str:
    """``file: what is wrong`` of an OSError (its own text repeats the errno and quotes the file)."""
    files = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    what = exc.strerror or str(exc)
    return f"{files}: {what}" if files else what


def _check_parent(out: Path, what: str) -> None:
    """Refuse ``out`` under a file (mkdir would only say "File exists", naming the file)."""
    for anc in Path(out).absolute().parents:
        if anc.exists():
            if not anc.is_dir():
                raise CliError(f"{out}: {what}: {anc} is a file, not a directory")
            return


def cmd_validate(args) -> int:
    from simart_pipeline.validation import scene_problems

    if not Path(args.scene_dir).is_dir():
        raise CliError(f"{args.scene_dir}: no such directory (give the directory that holds scene.yaml)")
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
        raise CliError(f"--weather {' '.join(unknown)}: not among the weathers of scene {cfg.name!r}: "
                       f"{list(cfg.weathers)}")
    ts = list(tiles or scene_tiles(cfg.ckm))
    unknown = [t for t in ts if t not in scene_tiles(cfg.ckm)]
    if unknown:
        raise CliError(f"--tile {' '.join(unknown)}: not among the tiles of scene {cfg.name!r}: {scene_tiles(cfg.ckm)}")
    return ws, ts


def _label(key) -> str:
    return key if isinstance(key, str) else "|".join(f"{k}={v}" for k, v in key.keys_by_dimension.items())


class StepFailed(RuntimeError):
    """A step of ``simart run`` failed: ``str()`` is the one line that names the partition and the
    project's own message (file, key path or topic, what is wrong); ``detail`` the full trace."""

    def __init__(self, line: str, detail: str = ""):
        super().__init__(line)
        self.detail = detail


def _root_cause(error) -> tuple[str, str]:
    """(``ExcClass: message`` of the innermost cause, every stack) of a Dagster step error: the
    project's own exception sits under Dagster's "Error occurred while executing op" wrapper."""
    stacks, err = [], error
    while err is not None:
        stacks.append("".join(err.stack) + f"{err.cls_name}: {err.message.strip()}")
        if err.cause is None:
            break
        err = err.cause
    msg = err.message.strip().splitlines()[0] if err.message.strip() else ""
    # SerializableErrorInfo's message starts with the (qualified) class name: keep it at the end
    head, sep, rest = msg.partition(": ")
    if sep and head.split(".")[-1] == err.cls_name:
        msg = rest
    return f"{msg} ({err.cls_name})" if msg else err.cls_name, "\n\nThe above caused:\n\n".join(reversed(stacks))


def _failure(result, label: str) -> StepFailed:
    """The first failed step of a run (or its failed blocking checks), as one line."""
    failures = [e for e in result.all_events if e.is_step_failure]
    if failures:
        step = failures[0].step_key or "step"
        line, detail = _root_cause(failures[0].step_failure_data.error)
        return StepFailed(f"{step} ({label}): {line}", detail)
    failed = [e for e in result.get_asset_check_evaluations() if not e.passed]
    if failed:
        c = failed[0]
        return StepFailed(f"{c.asset_key.to_user_string()} ({label}): asset check {c.check_name} failed: "
                          f"{c.description or ''}".rstrip(": "))
    return StepFailed(f"({label}): the run failed")


def _scene_on_instance(scene_dir, data_root, weathers, tiles, instance):
    """Register the scene under ``data_root`` and its partition on ``instance`` (default: the
    project-local one): (config, weathers, tiles, instance), weathers and tiles checked."""
    import dagster as dg

    from simart_pipeline.partitions import scene_partitions

    cfg = registry.register(scene_dir, data_root)
    weathers, tiles = _plan(cfg, weathers, tiles)
    if instance is None:
        _prepare_dagster_home()
        instance = dg.DagsterInstance.get()
    instance.add_dynamic_partitions(scene_partitions.name, [cfg.name])
    return cfg, weathers, tiles, instance


# the process and machine of each run `simart run` starts, so that the next one can tell a run
# whose process was killed from one still going
RUN_PID_TAG, RUN_HOST_TAG = "simart/pid", "simart/host"


def release_dead_runs(instance) -> list[str]:
    """Runs that ``simart run`` started on this machine in a process that is gone (killed
    mid-run): their op concurrency slots (the ``raytracing`` and ``rendering`` pools of
    dagster.yaml, one op at a time) are freed and the runs marked failed. Dagster frees a slot when
    the op ends; a killed process never ends it, and the next run's op in that pool waited for it
    for ever. Runs launched from the UI (no such tags) and live processes are left alone. Returns
    the runs released."""
    import dagster as dg

    from simart_pipeline.stores import process_alive

    live = (dg.DagsterRunStatus.NOT_STARTED, dg.DagsterRunStatus.STARTING, dg.DagsterRunStatus.STARTED)
    runs = instance.get_runs(filters=dg.RunsFilter(statuses=list(live), tags={RUN_HOST_TAG: socket.gethostname()}))
    released = []
    for run in runs:
        pid = run.tags.get(RUN_PID_TAG)
        if pid is None or not pid.isdigit() or process_alive(int(pid)):
            continue
        if instance.event_log_storage.supports_global_concurrency_limits:
            instance.event_log_storage.free_concurrency_slots_for_run(run.run_id)
        instance.report_run_failed(run, message=f"simart run process {pid} ended before the run did (killed?); "
                                                 f"its concurrency slots were freed by the next simart run")
        released.append(run.run_id)
    return released


@contextlib.contextmanager
def _collector_off_libraries():
    """The libraries' objects (Dagster, Sionna, Mitsuba: millions) live as long as the process: out
    of the collector's sight (``gc.freeze``), a full collection scans only what was made since
    (0.3 s a collection otherwise)."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def materialize_scene(scene_dir: Path, data_root: Path, weathers=None, tiles=None, verbose=False,
                      instance=None, progress=print, force: bool = False) -> dict[str, list[Path]]:
    """Register the scene and materialise every asset partition of it that is missing or stale
    (all of them with ``force``); returns the store paths. Each partition's line says whether it was
    computed, and why, or was already up to date."""
    import dagster as dg

    from simart_pipeline.assets import ALL_ASSETS, ALL_CHECKS
    from simart_pipeline.assets.config_sources import report_config_versions
    from simart_pipeline.assets.staleness import partition_status, scene_steps, stores_of
    from simart_pipeline.assets.versioning import FORCE_TAG
    from simart_pipeline.definitions import build_definitions

    cfg, weathers, tiles, instance = _scene_on_instance(scene_dir, data_root, weathers, tiles, instance)
    for run_id in release_dead_runs(instance):
        progress(f"run {run_id}: its process is gone (killed?); marked failed, its concurrency slots freed")
    defs = build_definitions(data_root=str(data_root))
    resources = defs.resources
    plan = resources["project"].version_plan(cfg.name)
    # Without --verbose Dagster's own log stays quiet (its step-failure traces too): a failure ends
    # in one line that names the partition and the project's message, the trace only with --verbose.
    run_config = None if verbose else {"loggers": {"console": {"config": {"log_level": "CRITICAL"}}}}
    t_start = time.perf_counter()
    # Dagster learns the scene's config versions first, so that its own staleness (the UI) agrees.
    report_config_versions(instance, plan)
    steps = scene_steps(cfg, weathers, tiles)
    total = sum(len(s[0]) for s in steps)
    with _collector_off_libraries():
        done = computed = 0
        for names, key in steps:
            label = _label(key)
            stale = {}
            for name in names:
                ok, why = (False, "--force") if force else partition_status(
                    instance, plan, name, key, data_root, stores_of(name, key, data_root, cfg))
                if not ok:
                    stale[name] = why
            for i, name in enumerate(names):
                status = f"computing ({stale[name]})" if name in stale else "up to date"
                progress(f"[{done + i + 1:>2}/{total}] {name} ({label}): {status}")
            if stale:
                t0 = time.perf_counter()
                tags = {RUN_PID_TAG: str(os.getpid()), RUN_HOST_TAG: socket.gethostname(),
                        **({FORCE_TAG: "true"} if force else {})}
                result = dg.materialize([*ALL_ASSETS, *ALL_CHECKS], selection=list(stale), partition_key=key,
                                        instance=instance, resources=resources, run_config=run_config,
                                        raise_on_error=False, tags=tags)
                if not result.success:
                    raise _failure(result, label)
                for ev in result.get_asset_check_evaluations():  # warnings: the run goes on, the user is told
                    if not ev.passed:
                        progress(f"        check {ev.check_name} ({ev.severity.value.lower()}): {ev.description}")
                # A run's outputs (a weather's rendered frames: gigabytes) hang in reference cycles of
                # the run's objects until a full collection, which a few large objects never trigger:
                # without this, each weather's step held the last one's frames too (2.4 GB peak on
                # tests/scenes/beam_tiny at 480 x 360 against 1.3 GB with it).
                del result
                gc.collect()
                computed += len(stale)
                progress(f"        done in {time.perf_counter() - t0:.1f} s")
            done += len(names)
    progress(f"scene {cfg.name!r}: {computed} of {total} asset partitions computed, {total - computed} up to date, "
             f"in {time.perf_counter() - t_start:.1f} s")
    out: dict[str, list[Path]] = {}
    for names, key in steps:
        for name in names:
            if name not in ("ckm_layers", "ckm_map"):  # the tiles write into the scene's mosaic maps
                out.setdefault(name, []).extend(stores_of(name, key, data_root, cfg))
    from simart_pipeline.ckm.maps import map_groups, map_path

    out["ckm"] = [map_path(data_root, cfg.name, name) for name in map_groups(cfg)]
    return out


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
    # a failed step raises StepFailed: main prints its one line (and its trace with --verbose)
    stores = materialize_scene(Path(args.scene_dir), data_root, args.weather, args.tile, args.verbose,
                               force=args.force)
    print("outputs:")
    for asset, paths in stores.items():
        for p in paths:
            print(f"  {asset:14s} {p}")
    return 0


BACKFILL_DEFAULT_ASSETS = ("ckm_layers",)


def scene_backfill(scene: str, assets=None, weathers=None, tiles=None, force: bool = False, instance=None,
                   progress=print) -> str | None:
    """Submit one Dagster backfill of a scene's asset partitions (``assets``, default every CKM
    tile, narrowed by ``weathers`` and ``tiles``) that are missing or stale (all of them with
    ``force``) to the instance, whose daemon runs it; returns its id (None: nothing to do).

    The scene (a name or a directory holding scene.yaml) is registered under the data root the code
    location uses ($SIMART_DATA or ./data), as ``simart run`` does."""
    from simart_pipeline import versions
    from simart_pipeline.assets.config_sources import report_config_versions
    from simart_pipeline.assets.staleness import BACKFILL_TAG, stale_partitions, scene_partitions_of, submit_backfill
    from simart_pipeline.assets.versioning import FORCE_TAG
    from simart_pipeline.definitions import build_definitions
    from simart_pipeline.partitions import split_key

    assets = list(assets or BACKFILL_DEFAULT_ASSETS)
    unknown = [a for a in assets if a not in versions.STAGES]
    if unknown:
        raise CliError(f"--asset {' '.join(unknown)}: no such asset; assets: {', '.join(versions.STAGES)}")
    data_root, scenes_root = registry.default_data_root(), registry.default_scenes_root()
    scene_dir = Path(scene) if Path(scene, "scene.yaml").is_file() else registry.scene_dir(scene, data_root, scenes_root)
    if not Path(scene_dir, "scene.yaml").is_file():
        raise CliError(f"{scene}: not a registered scene nor a directory holding scene.yaml (scenes root {scenes_root})")
    cfg, weathers, tiles, instance = _scene_on_instance(scene_dir, data_root, weathers, tiles, instance)
    defs = build_definitions(data_root=str(data_root), scenes_root=str(scenes_root))
    project = defs.resources["project"]
    report_config_versions(instance, project.version_plan(cfg.name))
    wanted = scene_partitions_of(cfg, assets, weathers, tiles)
    every_stale = stale_partitions(instance, project, cfg.name)  # the scene's, every asset, upstream first
    chosen = {p: "--force" for p in wanted} if force else {p: every_stale[p] for p in wanted if p in every_stale}
    if not chosen:
        progress(f"scene {cfg.name!r}: nothing to backfill, all {len(wanted)} asset partitions of "
                 f"{', '.join(assets)} are up to date (--force recomputes them)")
        return None
    for (asset, key), why in chosen.items():
        progress(f"  {asset} ({_label(key)}): {why}")
    # upstream partitions that are neither up to date nor in this backfill: its runs would fail
    reads, todo = set(), [(a, split_key(k)[1]) for a, k in chosen]
    while todo:
        for up in versions.upstream(cfg, *todo.pop()):
            if up not in reads:
                reads.add(up)
                todo.append(up)
    behind = [(a, k) for a, k in every_stale if (a, split_key(k)[1]) in reads and (a, k) not in chosen]
    if behind:
        names = list(dict.fromkeys(a for a, _ in behind))
        progress(f"warning: {len(behind)} upstream partition(s) ({', '.join(f'{a} ({_label(k)})' for a, k in behind)}) "
                 f"are missing or stale and not in this backfill, whose runs need them: add --asset "
                 f"{' '.join(names)}, or run `simart run {scene_dir}` first")
    tags = {BACKFILL_TAG: "cli", **({FORCE_TAG: "true"} if force else {})}
    backfill_id = submit_backfill(instance, defs.resolve_asset_graph(), chosen, tags,
                                  title=f"simart backfill {cfg.name}",
                                  description=f"{len(chosen)} partition(s) of {', '.join(assets)}")
    progress(f"backfill {backfill_id}: {len(chosen)} of {len(wanted)} asset partitions of scene {cfg.name!r} "
             f"({len(wanted) - len(chosen)} up to date), submitted to the instance at {instance.root_directory}")
    progress("  the daemon of `simart dev` runs it, one run at a time in the pools of dagster.yaml;")
    progress(f"  watch it at http://127.0.0.1:3000/runs/b/{backfill_id}?tab=partitions (the UI's Backfills tab)")
    return backfill_id


def cmd_backfill(args) -> int:
    scene_backfill(args.scene, args.asset, args.weather, args.tile, force=args.force)
    return 0


DEV_STOP_GRACE_S = 8.0  # after SIGINT or SIGTERM, what `dagster dev` gets to stop before SIGKILL


def cmd_dev(args) -> int:
    """``dagster dev`` on the project-local instance, stopped cleanly by SIGINT or SIGTERM.

    ``dagster dev`` leaves a SIGTERM to its webserver and daemon children that do not all heed it
    (it took more than 20 s, then a kill): here either signal becomes one SIGINT to the whole
    process group (what a terminal's Ctrl-C does, which dagster dev handles), and what is still
    running after :data:`DEV_STOP_GRACE_S` is killed."""
    import signal

    home = _prepare_dagster_home()
    print(f"DAGSTER_HOME={home}", flush=True)
    extra = args.dagster_args[1:] if args.dagster_args[:1] == ["--"] else args.dagster_args
    cmd = [sys.executable, "-m", "dagster", "dev", "-m", "simart_pipeline.definitions", *extra]
    child = subprocess.Popen(cmd, cwd=registry.REPO_ROOT, start_new_session=True)
    stopping = []

    def stop(signum, _frame):
        stopping.append(signum)
        try:
            os.killpg(child.pid, signal.SIGINT)
        except ProcessLookupError:
            pass

    old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while child.poll() is None and not stopping:
            time.sleep(0.2)
        if stopping:
            try:
                child.wait(timeout=DEV_STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                pass
            try:
                os.killpg(child.pid, signal.SIGKILL)  # whatever of the group is left
            except ProcessLookupError:
                pass
            child.wait()
            return 128 + stopping[0]
        return child.returncode
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def cmd_preflight(args) -> int:
    from simart_pipeline import engine

    try:
        print(f"ok: {engine.preflight()}")
        return 0
    except engine.PreflightError as exc:
        print(f"preflight: {exc}", file=sys.stderr)
        return 3


def cmd_bench(args) -> int:
    root = registry.REPO_ROOT
    if not (root / "benchmarks" / "bench.py").is_file():
        raise CliError(f"{root / 'benchmarks'}: not found; `simart bench` runs from a source checkout of the project")
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from benchmarks import bench

    if args.publish is None and args.out is None:
        raise CliError("bench: give --out DIR (or --publish DIR --doc PATH)")
    if args.publish is not None and (args.doc is None or not (args.publish / "results.json").is_file()):
        raise CliError(f"{args.publish}: --publish needs --doc PATH and a finished run (its results.json)")
    unknown = sorted(set(args.only or ()) - {b.name for b in bench.BENCHMARKS})
    if unknown:
        raise CliError(f"--only: unknown benchmark(s) {', '.join(unknown)}; known: "
                       f"{', '.join(b.name for b in bench.BENCHMARKS)}")
    return bench.run_from_args(args)


def _floats(text: str, n: tuple[int, ...], what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if len(values) not in n:
        raise argparse.ArgumentTypeError(f"{what}: expected {' or '.join(map(str, n))} numbers, got {len(values)}")
    return values


def _origin(text: str) -> tuple[float, float, float]:
    v = _floats(text, (2, 3), "--origin LAT,LON[,ALT_M]")
    if not (-90 <= v[0] <= 90 and -180 <= v[1] <= 180):
        raise argparse.ArgumentTypeError(f"--origin: latitude {v[0]} or longitude {v[1]} out of range")
    return (v[0], v[1], v[2] if len(v) == 3 else 0.0)


def _bbox(text: str) -> tuple[float, float, float, float]:
    v = _floats(text, (4,), "--bbox MIN_LON,MIN_LAT,MAX_LON,MAX_LAT")
    if not (-180 <= v[0] < v[2] <= 180 and -90 <= v[1] < v[3] <= 90):
        raise argparse.ArgumentTypeError(f"--bbox {text}: expected MIN_LON < MAX_LON and MIN_LAT < MAX_LAT, in degrees")
    return v


def cmd_scene_build(args) -> int:
    from simart_pipeline.scene.build import build_scene

    t0 = time.perf_counter()
    _check_parent(Path(args.out), "--out")
    try:  # the builders' own errors (ValueError) name the file and the problem: main prints them
        info = build_scene(args.source, args.out, origin=args.origin, bbox_deg=args.bbox, force=args.force,
                           frequency_hz=args.carrier_frequency_hz, storey_height_m=args.storey_height_m,
                           facade_detail=not args.no_facade_detail)
    except OSError as exc:
        raise CliError(f"{args.out}: cannot build the scene there: {_os_problem(exc)}") from exc
    c = info["counts"]
    origin = info.get("origin")
    where = (f"origin {origin['latitude_deg']:.7f}, {origin['longitude_deg']:.7f}" if origin else "no geodetic origin")
    print(f"{args.out}: {c['buildings']} buildings, visual {c['visual_triangles']} triangles, radio "
          f"{c['radio_triangles']} triangles in {c['radio_meshes']} meshes ({', '.join(c['radio_materials'])}); "
          f"{where}; {len(info.get('warnings', []))} warning(s); {time.perf_counter() - t0:.2f} s")
    if info.get("attribution"):
        print(info["attribution"])
    return 0


def cmd_ckm(args) -> int:
    """Open a scene's channel knowledge map as an xarray dataset: print it, or export it."""
    from simart_pipeline import registry as reg
    from simart_pipeline.ckm.maps import map_groups, map_name_for_weather, map_path, open_scene_map
    from simart_pipeline.config import load_scene_config

    data_root = Path(args.data or reg.default_data_root()).resolve()
    out = Path(args.export) if args.export else None
    if out is not None and out.suffix != ".zarr":  # checked before anything is opened or computed
        raise CliError(f"{out}: --export: give a .zarr path (a standalone copy of the map)")
    scene_dir = Path(args.scene) if Path(args.scene, "scene.yaml").is_file() else \
        reg.scene_dir(args.scene, data_root, reg.default_scenes_root())
    cfg = load_scene_config(scene_dir)
    source = map_path(data_root, cfg.name, map_name_for_weather(cfg, args.weather) if args.weather
                      else next(iter(map_groups(cfg))))
    ds = open_scene_map(data_root, cfg, args.weather)
    if args.layer:
        missing = [v for v in args.layer if v not in ds.data_vars]
        if missing:
            raise CliError(f"{source}: --layer: no layer {', '.join(missing)}; layers: "
                           f"{', '.join(sorted(ds.data_vars))}")
        ds = ds[list(args.layer)]
    if out is not None:
        from simart_pipeline import stores as zarr_stores

        _check_parent(out, "--export")
        _check_export_path(out, source)
        try:
            zarr_stores.write_store(ds.load(), out)
        except OSError as exc:
            raise CliError(f"{out}: --export: cannot write there: {_os_problem(exc)}") from exc
        print(f"wrote {out}")
        return 0
    print(ds)
    return 0


def cmd_export(args) -> int:
    """Write a materialised (scene, weather) session as one ROS bag."""
    from simart_pipeline import registry as reg
    from simart_pipeline import stores as zarr_stores
    from simart_pipeline.ckm.maps import map_path
    from simart_pipeline.ckm.mosaic import open_map
    from simart_pipeline.config import load_scene_config
    from simart_pipeline.export import bag
    from simart_pipeline.radio.materials import WEATHER_GROUP
    from simart_pipeline.scene.actors import scene_actors

    data_root = Path(args.data or reg.default_data_root()).resolve()
    out = Path(args.out)
    if args.format == "rosbag1" and out.suffix != ".bag":
        raise CliError(f"{out}: --out: a ROS 1 bag is one file; give a .bag path")
    if args.format != "rosbag1" and out.suffix == ".bag":
        raise CliError(f"{out}: --out: a rosbag2 bag is a directory; give a path without .bag")
    ours = (out.is_dir() and (out / "metadata.yaml").is_file()) or (out.is_file() and out.suffix == ".bag")
    if out.exists() and not ours:
        raise CliError(f"{out}: --out: exists and is not a bag; refusing to replace it")
    _check_parent(out, "--out")
    scene_dir = Path(args.scene) if Path(args.scene, "scene.yaml").is_file() else \
        reg.scene_dir(args.scene, data_root, reg.default_scenes_root())
    cfg = load_scene_config(scene_dir)
    weather = args.weather or cfg.weathers[0]
    if weather not in cfg.weathers:
        raise CliError(f"{scene_dir / 'scene.yaml'}: --weather: {weather!r} is not one of the scene's weathers "
                       f"({', '.join(cfg.weathers)})")
    session_path = zarr_stores.store_path(data_root, "session", cfg.name, weather)
    if not session_path.exists():
        raise CliError(f"{session_path}: no session store: run `simart run {scene_dir}` first")
    group = WEATHER_GROUP[weather]
    radar_path = zarr_stores.store_path(data_root, "radar_frames", cfg.name, group)
    ckm_path = map_path(data_root, cfg.name, group)
    counts = bag.export_session(
        out, args.format, zarr_stores.open_store(session_path, tree=True), cfg,
        actors=scene_actors(cfg, scene_dir), ckm=open_map(ckm_path) if ckm_path.exists() else None,
        ckm_materials=group, radar=zarr_stores.open_store(radar_path, tree=True) if radar_path.exists() else None)
    print(f"wrote {out} ({args.format}): {sum(counts.values())} messages on {len(counts)} topics")
    return 0


def _check_export_path(out: Path, source: Path) -> None:
    """An export replaces ``out`` whole: refuse where that would destroy something else (a directory
    or file that is not a Zarr store, the map itself or a directory holding it)."""
    o, src = out.resolve(), source.resolve()
    if o == src or o in src.parents or src in o.parents:
        raise CliError(f"{out}: --export: is (or holds, or lies inside) the map {source} itself; "
                       "give a path outside the data root's ckm stores")
    if out.exists() and not (out.is_dir() and (out / "zarr.json").is_file()):
        raise CliError(f"{out}: --export: exists and is not a Zarr store; refusing to replace it")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="simart",
        description="simart-pipeline: turn a scene (OpenStreetMap extract, mesh, or procedural layout) into a "
                    "synchronized multimodal ISAC dataset: trajectories, camera/LiDAR/IMU/GPS streams, "
                    "Sionna RT channels, KPIs and channel knowledge maps, as Zarr stores.")
    p.add_argument("--verbose", action="store_true", help="print the stack trace of a failure")
    # the same flag after the command; SUPPRESS keeps a flag given before the command
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="print the stack trace of a failure")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="materialise every asset of a scene on the embedded Dagster instance",
                       description="Validate and register SCENE_DIR, then materialise those of its asset partitions "
                                   "(every weather and CKM tile unless narrowed) that are missing or stale (their "
                                   "code, the part of the config they read, a source file or an upstream data "
                                   "version changed), say why each ran, and print where the stores are.")
    r.add_argument("scene_dir", metavar="SCENE_DIR", help="directory holding scene.yaml (e.g. scenes/demo)")
    r.add_argument("--weather", nargs="+", metavar="W", help="only these weathers (sunny, rainy, night)")
    r.add_argument("--tile", nargs="+", metavar="T", help="only these CKM tiles (r<row>c<col>)")
    r.add_argument("--data", metavar="DIR", help="data root for the stores (default: ./data or $SIMART_DATA)")
    r.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                   help="show Dagster's own event log, and the stack trace of a failure")
    r.add_argument("--force", action="store_true",
                   help="recompute every partition, even those whose data version is up to date")
    r.set_defaults(func=cmd_run)
    bf = sub.add_parser("backfill", parents=[common], help="submit a Dagster backfill of a scene's stale partitions",
                        description="Submit one Dagster backfill of those partitions of SCENE's assets (default: every "
                                    "CKM tile, ckm_layers) that are missing or stale, to the project-local instance. "
                                    "The daemon of `simart dev` runs it (one run per partition, in dependency order, "
                                    "through the run queue and pools of dagster.yaml); an interrupted backfill is "
                                    "resumed by submitting it again: what finished is up to date and left out. Data "
                                    "root: $SIMART_DATA or ./data, the same as the code location's.")
    bf.add_argument("scene", metavar="SCENE", help="scene name (registered) or scene directory")
    bf.add_argument("--asset", nargs="+", metavar="A", help="these assets (default ckm_layers; e.g. ckm_layers ckm_map)")
    bf.add_argument("--tile", nargs="+", metavar="T", help="only these CKM tiles (r<row>c<col>)")
    bf.add_argument("--weather", nargs="+", metavar="W", help="only these weathers (sunny, rainy, night)")
    bf.add_argument("--force", action="store_true", help="every chosen partition, even those that are up to date")
    bf.set_defaults(func=cmd_backfill)
    v = sub.add_parser("validate", parents=[common], help="check a scene's config and inputs",
                       description="Check SCENE_DIR/scene.yaml against the schema and the scene's inputs; report "
                                   "every problem with its file and key path. Exit status 1 on any problem.")
    v.add_argument("scene_dir", metavar="SCENE_DIR")
    v.set_defaults(func=cmd_validate)
    s = sub.add_parser("scenes", parents=[common], help="list the scenes under scenes/",
                       description="List every directory under the scenes root that holds a scene.yaml.")
    s.add_argument("--scenes-root", metavar="DIR", help="default: the repository's scenes/ or $SIMART_SCENES")
    s.set_defaults(func=cmd_scenes)
    d = sub.add_parser("dev", help="open the Dagster UI on the project-local instance",
                       description="Run `dagster dev` with DAGSTER_HOME=.dagster_home; extra arguments go to dagster.")
    d.add_argument("dagster_args", nargs=argparse.REMAINDER)
    d.set_defaults(func=cmd_dev)
    sc = sub.add_parser("scene", help="build scenes from OpenStreetMap extracts or meshes",
                        description="Scene construction commands.")
    scs = sc.add_subparsers(dest="scene_command", required=True)
    b = scs.add_parser(
        "build", parents=[common], help="an OSM extract or a mesh to paired visual and radio meshes",
        description="Build DIR/radio/scene.xml (+ PLY meshes, loadable by sionna.rt.load_scene), the visual mesh "
                    "with per-face semantic class and instance id under DIR/visual/, and DIR/scene.json (origin, "
                    "counts, materials, attribution). SOURCE is an OSM extract (.osm, .osm.pbf) or a mesh "
                    "(.obj, .ply, .stl, .gltf, .glb). DIR is written aside and renamed into place.")
    b.add_argument("source", metavar="SOURCE")
    b.add_argument("--out", metavar="DIR", required=True, help="output directory (must be empty or absent)")
    b.add_argument("--origin", metavar="LAT,LON[,ALT_M]", type=_origin,
                   help="world origin (WGS84); default: the extract's centre at altitude 0")
    b.add_argument("--bbox", metavar="MIN_LON,MIN_LAT,MAX_LON,MAX_LAT", type=_bbox,
                   help="clip an OSM extract to this box (deg); default: the whole extract")
    b.add_argument("--force", action="store_true", help="replace a non-empty DIR")
    b.add_argument("--carrier-frequency-hz", type=float, default=3.5e9, metavar="HZ",
                   help="frequency at which non-ITU radio materials (water) are written (default 3.5e9)")
    b.add_argument("--storey-height-m", type=float, default=3.0, metavar="M",
                   help="storey height for building:levels and window rows (default 3)")
    b.add_argument("--no-facade-detail", action="store_true", help="no window frames on the visual mesh")
    b.set_defaults(func=cmd_scene_build)
    k = sub.add_parser("ckm", parents=[common], help="show a scene's channel knowledge map (xarray) or export a copy",
                       description="Open the mosaic CKM store of a materialised scene as an xarray dataset. "
                                   "In Python: simart_pipeline.ckm.maps.open_scene_map(data_root, cfg, weather).")
    k.add_argument("scene", help="scene name (registered by `simart run`) or scene directory")
    k.add_argument("--weather", help="whose radio materials (default: the first mapped weather)")
    k.add_argument("--layer", nargs="+", help="only these layers")
    k.add_argument("--export", metavar="OUT.zarr", help="write the map (or the chosen layers) to a standalone Zarr store")
    k.add_argument("--data", help="data root (default data/ or $SIMART_DATA)")
    k.set_defaults(func=cmd_ckm)
    e = sub.add_parser("export", parents=[common], help="write a materialised session as a ROS bag",
                       description="Write the (SCENE, WEATHER) session (sensors, poses and frames, CIRs, KPIs, beams, "
                                   "CKM layers, radar frames) as one bag: rosbag2 MCAP (a directory), rosbag2 "
                                   "SQLite 3 (a directory) or ROS 1 (a .bag file); written aside and renamed into "
                                   "place. Topics: docs/ros-export.md.")
    e.add_argument("scene", help="scene name (registered by `simart run`) or scene directory")
    e.add_argument("--weather", metavar="W", help="default: the scene's first weather")
    e.add_argument("--format", choices=["mcap", "rosbag2-sqlite3", "rosbag1"], default="mcap")
    e.add_argument("--out", metavar="PATH", required=True)
    e.add_argument("--data", help="data root (default data/ or $SIMART_DATA)")
    e.set_defaults(func=cmd_export)
    f = sub.add_parser("preflight", parents=[common], help="check that Sionna RT can run here (libLLVM >= 17 or CUDA)",
                       description="Report the ray-tracing backend, or what is missing and how to fix it.")
    f.set_defaults(func=cmd_preflight)
    bn = sub.add_parser(
        "bench", parents=[common], help="run every stage benchmark and write one report (run time against error)",
        description="Run the stage benchmarks of benchmarks/ one after the other, each in its own process, writing "
                    "its JSON into DIR/<name>/; then DIR/results.json (every benchmark's results, wall time and "
                    "exit status, the machine, package versions, git commit) and DIR/report.md (one section per "
                    "benchmark). A failed benchmark is reported as failed (exit status 1); one whose inputs are "
                    "missing is reported as skipped, with why. Same as `python -m benchmarks`. Needs a source "
                    "checkout. docs/benchmarks.md")
    bn.add_argument("--out", type=Path, metavar="DIR",
                    help="folder for report.md, results.json and one folder per benchmark")
    bn.add_argument("--doc", type=Path, metavar="PATH",
                    help="also write the report as this markdown page, its plots copied beside it into PATH "
                         "without its suffix (docs/benchmarks.md: docs/benchmarks/)")
    bn.add_argument("--publish", type=Path, metavar="DIR",
                    help="run nothing: write --doc from the finished run in DIR")
    bn.add_argument("--quick", action="store_true",
                    help="smaller settings: the whole command within about 10 minutes on 2 cores (full: an hour)")
    bn.add_argument("--only", nargs="+", metavar="NAME", help="only these benchmarks (default: all)")
    bn.set_defaults(func=cmd_bench)
    return p


def _error_line(exc: BaseException) -> str:
    """The one line of a failure: the project's own errors (StepFailed, CliError, the ValueErrors of
    config, stores, scene building, replay) already name the file and the problem; an OSError is
    told as ``file: what``; anything else gets its class name appended."""
    from simart_pipeline.config import ConfigError

    if isinstance(exc, ConfigError) and len(exc.problems) > 1:
        _print_problems(exc.problems[:-1])
        return f"{len(exc.problems)} problems, the last: {' '.join(exc.problems[-1].split())}"
    if isinstance(exc, OSError):
        return f"{_os_problem(exc)} ({type(exc).__name__})"
    msg = " ".join(str(exc).split())
    own = isinstance(exc, (StepFailed, CliError)) or (
        isinstance(exc, ValueError) and type(exc).__module__.startswith("simart_pipeline."))
    return msg if own and msg else f"{msg} ({type(exc).__name__})" if msg else type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    """Run one command; any failure ends in one ``error:`` line and exit status 1, its trace only
    with ``--verbose``."""
    args = build_parser().parse_args(argv)
    args.verbose = getattr(args, "verbose", False)
    try:
        return args.func(args)
    except KeyboardInterrupt:  # stores are swapped in whole, so an interrupted run loses nothing
        print("error: interrupted; what was written completely is kept, rerun to finish", file=sys.stderr)
        return 130
    except Exception as exc:
        if args.verbose:
            detail = exc.detail if isinstance(exc, StepFailed) and exc.detail else None
            print(detail or "".join(traceback.format_exception(exc)).rstrip(), file=sys.stderr)
        hint = "" if args.verbose or isinstance(exc, CliError) else "  (--verbose shows the trace)"
        print(f"error: {_error_line(exc)}{hint}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
