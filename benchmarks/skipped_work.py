"""Skipped work, shown with the time it saves, measured in one run.

    python -m benchmarks.skipped_work [--quick] --out DIR

(a) A weather whose radio materials equal another's reuses its radio work: on a fresh data root,
``simart run``'s own function (``cli.materialize_scene``) materialises the scene in ``sunny``, then
in ``night`` (the same weather group); night's run must not recompute the radio partitions (``cirs``
and ``radar_frames`` of group ``sunny``), seen in its progress lines and in the Dagster instance's
materialisation records. The time saved is a forced recompute of those radio partitions, measured
after. (b) A scene with no camera renders no camera frames: the ``sensor_frames`` stage of the
scene against copies with its cameras removed, and with cameras and LiDARs removed (nothing left to
ray cast). (c) A CKM tile entirely inside buildings traces nothing: ``ckm_layers`` of a tile whose
cells all lie inside one building against a tile of the same size in the street, both forced.

``--quick`` uses ``tests/scenes/tiny`` (one CKM tile), the full run ``scenes/demo``. (b) and (c) are
repeated, the variants alternating in order; best and median reported. Writes ``DIR/results.json``
and ``DIR/report.md``.
"""

from __future__ import annotations

import re
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DEMO
from benchmarks.harness import (TINY, Pipeline, alternating, cli_main, machine, quiet_dagster, ratio, scene_copy, summary,
                                write_outputs)

RADIO_ASSETS = ("cirs", "radar_frames")
_LINE = re.compile(r"^\[\s*\d+/\d+\] (\S+) \(([^)]*)\): (computing.*|up to date)$")
_DONE = re.compile(r"^\s+done in ([0-9.]+) s$")


def parse_progress(lines: list[str]) -> list[dict]:
    """``simart run``'s progress lines as its steps: ``[{"assets": {name: status}, "label",
    "seconds"}]`` (``seconds`` None where nothing was computed)."""
    steps: list[dict] = []
    for line in lines:
        m = _LINE.match(line)
        if m:
            name, label, status = m.groups()
            if not steps or steps[-1]["label"] != label or steps[-1]["seconds"] is not None:
                steps.append({"label": label, "assets": {}, "seconds": None})
            steps[-1]["assets"][name] = "computed" if status.startswith("computing") else "up to date"
            continue
        m = _DONE.match(line)
        if m and steps:
            steps[-1]["seconds"] = float(m.group(1))
    return steps


def statuses(steps: list[dict], asset: str) -> dict[str, str]:
    """``{partition label: "computed" | "up to date"}`` of one asset in parsed progress steps."""
    return {s["label"]: s["assets"][asset] for s in steps if asset in s["assets"]}


def materialisation_count(instance, asset: str, partition: str) -> int:
    """How many times the instance recorded ``asset`` materialised at ``partition``."""
    import dagster as dg

    recs = instance.fetch_materializations(dg.AssetKey(asset), limit=1000).records
    return sum(1 for r in recs if str(r.event_log_entry.dagster_event.partition) == str(partition))


def weather_reuse(src: Path, tmp: Path, tile: str | None) -> dict:
    """(a): sunny then night on a fresh data root, then a forced recompute of the radio partitions."""
    from simart_pipeline.cli import materialize_scene
    from simart_pipeline.radio.materials import WEATHER_GROUP

    scene = scene_copy(src, tmp / "reuse" / src.name)
    pipe = Pipeline(scene, tmp / "reuse" / "data")
    group = WEATHER_GROUP["night"]
    assert group == WEATHER_GROUP["sunny"], "sunny and night no longer share radio materials"
    runs = {}
    for weather in ("sunny", "night"):
        lines: list[str] = []
        t0 = time.perf_counter()
        materialize_scene(scene, pipe.data_root, weathers=[weather], tiles=[tile] if tile else None,
                          instance=pipe.instance, progress=lines.append)
        steps = parse_progress(lines)
        radio_steps = [s for s in steps if set(RADIO_ASSETS) & set(s["assets"])]
        runs[weather] = {"wall_s": round(time.perf_counter() - t0, 4), "steps": steps,
                         "radio": {a: statuses(steps, a) for a in RADIO_ASSETS},
                         "radio_step_s": sum(s["seconds"] or 0.0 for s in radio_steps)}
    key = pipe.key(weather_group=group)
    counts = {a: materialisation_count(pipe.instance, a, key) for a in RADIO_ASSETS}
    from simart_pipeline import resources

    resources._LOADED.clear()  # a recompute loads its radio scene, as night's own trace would have
    forced = pipe.materialize(list(RADIO_ASSETS), key, force=True)
    pipe.close()
    night_radio = runs["night"]["radio"]
    return {"weather_group": group, "runs": runs,
            "radio_materialisations_after_both_runs": counts,
            "night_recomputed_radio": any(v == "computed" for st in night_radio.values() for v in st.values()),
            "night_radio_partitions_up_to_date": sorted(f"{a} ({lbl})" for a, st in night_radio.items()
                                                        for lbl, v in st.items() if v == "up to date"),
            "forced_radio_recompute_s": round(forced["wall_s"], 4),
            "time_saved_s": round(forced["wall_s"], 4),
            "night_over_sunny_wall": ratio(runs["night"]["wall_s"], runs["sunny"]["wall_s"])}


def _drop_sensors(kinds: set[str]):
    def edit(raw):
        for dev in (*raw.get("platforms", []), *raw.get("base_stations", [])):
            if dev.get("sensors"):
                dev["sensors"] = [s for s in dev["sensors"] if s.get("kind") not in kinds]
    return edit


def no_camera(src: Path, tmp: Path, repeats: int) -> dict:
    """(b): the sensor_frames stage of the scene, without its cameras, without cameras and LiDARs."""
    variants = {"as it is": None, "cameras removed": {"camera"}, "cameras and LiDARs removed": {"camera", "lidar"}}
    pipes = {}
    for i, (name, kinds) in enumerate(variants.items()):
        scene = scene_copy(src, tmp / f"sensors{i}" / src.name, _drop_sensors(kinds) if kinds else None)
        pipes[name] = Pipeline(scene, tmp / f"sensors{i}" / "data")
        pipes[name].upstream()
    last: dict = {}

    def stage(name):
        def go():
            r = pipes[name].materialize(["sensor_frames"], pipes[name].key(weather="sunny"))
            last[name] = r
            return r["wall_s"]
        return go

    for name in variants:  # warm-up, not counted
        stage(name)()
    times = alternating({name: stage(name) for name in variants}, repeats)
    for p in pipes.values():
        p.close()
    out = {"variants": {}}
    base = summary(times["as it is"])
    for name in variants:
        s = summary(times[name])
        meta = last[name]["metadata"].get("sensor_frames", {})
        out["variants"][name] = {**s, "streams": meta.get("streams"), "render_s_metadata": meta.get("render_s"),
                                 "time_saved_s": round(base["best_s"] - s["best_s"], 4),
                                 "ratio_to_scene_as_it_is": ratio(s["best_s"], base["best_s"])}
    return out


def inside_and_street_tiles(geom, cell_m: float, height_m: float, street_xy, n: int) -> dict:
    """Two CKM grids of ``n`` x ``n`` cells of ``cell_m``: one whose every cell centre lies inside a
    building (centred in the largest footprint where that holds), one in the open near
    ``street_xy``: ``{"inside": (cx, cy), "street": (cx, cy)}``, None where none is found."""
    from simart_pipeline.scene.geometry import building_footprints, inside_buildings

    def cells(cx, cy):
        off = (np.arange(n) - (n - 1) / 2) * cell_m
        xx, yy = np.meshgrid(cx + off, cy + off)
        return inside_buildings(geom, xx.ravel(), yy.ravel(), np.full(n * n, height_m))

    inside = None
    for poly in sorted(building_footprints(geom), key=lambda p: -p.area):
        for pt in (poly.centroid, poly.representative_point()):
            if cells(pt.x, pt.y).all():
                inside = (round(float(pt.x), 3), round(float(pt.y), 3))
                break
        if inside:
            break
    street = None
    for dx in np.arange(0.0, 20.0, 1.0):  # the first spot near the street point with all cells outdoors
        if not cells(street_xy[0] + dx, street_xy[1]).any():
            street = (round(float(street_xy[0] + dx), 3), round(float(street_xy[1]), 3))
            break
    return {"inside": inside, "street": street}


def tile_inside_buildings(src: Path, tmp: Path, repeats: int) -> dict:
    """(c): ckm_layers of a tile entirely inside a building against one of the same size in the street."""
    from simart_pipeline.ckm.grid import scene_tiles
    from simart_pipeline.ckm.layers import tile_grid
    from simart_pipeline.scene import geometry

    base = Pipeline(scene_copy(src, tmp / "ckm_base" / src.name), tmp / "ckm_base" / "data")
    base.materialize(["osm_extract"], base.key())
    from simart_pipeline import stores

    geom = geometry.from_dataset(stores.open_store(stores.store_path(base.data_root, "osm_extract", base.cfg.name)).load())
    ckm = base.cfg.ckm
    starts = [w[:2] for p in base.cfg.platforms for w in (getattr(p.trajectory, "waypoints_m", None) or ())]
    spots, n = {"inside": None, "street": None}, 0
    for n in (4, 3, 2):  # the largest square of cells that fits inside a building and in a street
        for start in starts:  # a street point: where a platform drives or flies
            spots = inside_and_street_tiles(geom, ckm.cell_size_m, ckm.heights[0], start, n)
            if None not in spots.values():
                break
        if None not in spots.values():
            break
    if spots["inside"] is None or spots["street"] is None:
        base.close()
        return {"skipped_by_project": None, "note": f"no place found for the two tiles: {spots}"}
    pipes, grids = {}, {}
    for i, (name, centre) in enumerate(spots.items()):
        def edit(raw, centre=centre):
            raw["ckm"] = {**raw["ckm"], "center_m": list(centre), "size_m": [n * ckm.cell_size_m] * 2,
                          "tiles": [1, 1]}
            raw["ckm"].pop("region_m", None)
        scene = scene_copy(src, tmp / f"ckm{i}" / src.name, edit)
        pipes[name] = Pipeline(scene, tmp / f"ckm{i}" / "data")
        pipes[name].materialize(["osm_extract", "paired_meshes"], pipes[name].key())
        tile = scene_tiles(pipes[name].cfg.ckm)[0]
        grids[name] = (tile, tile_grid(pipes[name].cfg, geom, tile))
    last: dict = {}

    def stage(name):
        def go():
            from simart_pipeline import resources

            resources._LOADED.clear()  # each tile loads its radio scene where it needs one, as a new process would
            p = pipes[name]
            r = p.materialize(["ckm_layers"], p.key(tile=grids[name][0]), force=True)
            last[name] = r
            return r["wall_s"]
        return go

    for name in pipes:  # warm-up, not counted
        stage(name)()
    times = alternating({name: stage(name) for name in pipes}, repeats)
    for p in (base, *pipes.values()):
        p.close()
    out = {"centres_m": spots, "cell_size_m": ckm.cell_size_m, "variants": {}}
    for name in pipes:
        meta = last[name]["metadata"].get("ckm_layers", {})
        out["variants"][name] = {**summary(times[name]), "cells": int(grids[name][1].traced.size),
                                 "cells_to_trace": int(grids[name][1].traced.sum()),
                                 "cells_traced_metadata": meta.get("cells_traced"),
                                 "ckm_layers_step_s": round(last[name]["steps"].get("ckm_layers", float("nan")), 4)}
    v = out["variants"]
    out["skipped_by_project"] = v["inside"]["cells_traced_metadata"] == 0 and v["inside"]["cells_to_trace"] == 0
    out["time_saved_s"] = round(v["street"]["best_s"] - v["inside"]["best_s"], 4)
    out["inside_over_street"] = ratio(v["inside"]["best_s"], v["street"]["best_s"])
    return out


def report_lines(r: dict) -> list[str]:
    a, b, c = r["weather_reuse"], r["no_camera"], r["tile_inside_buildings"]
    sunny, night = a["runs"]["sunny"], a["runs"]["night"]
    lines = [f"# Skipped work on `{r['scene']}`", "", f"Machine: {r['machine']}.", "",
             "| skipped work | seen | time saved (s) | measured how |", "|---|---|---|---|",
             f"| night reuses sunny's radio work (group `{a['weather_group']}`) | night's run: "
             f"{'radio RECOMPUTED' if a['night_recomputed_radio'] else 'radio up to date'}; materialised in both runs: "
             f"{', '.join(f'{k} {v}x' for k, v in a['radio_materialisations_after_both_runs'].items())} | "
             f"{a['time_saved_s']} | a forced recompute of {', '.join(RADIO_ASSETS)} after both runs |"]
    nb = b["variants"]
    for name in ("cameras removed", "cameras and LiDARs removed"):
        lines.append(f"| sensor_frames with {name} | streams: {nb[name]['streams']} | {nb[name]['time_saved_s']} | "
                     f"best of {r['repeats']}: {nb[name]['best_s']} s against {nb['as it is']['best_s']} s |")
    if c.get("variants"):
        vi, vs = c["variants"]["inside"], c["variants"]["street"]
        lines.append(f"| CKM tile inside a building ({vi['cells']} cells) | "
                     f"{'skipped: ' if c['skipped_by_project'] else 'NOT skipped: '}{vi['cells_traced_metadata']} "
                     f"cells traced (street tile: {vs['cells_traced_metadata']}) | {c['time_saved_s']} | "
                     f"best of {r['repeats']}: {vi['best_s']} s against {vs['best_s']} s for a street tile of the same size |")
    else:
        lines.append(f"| CKM tile inside a building | not measured: {c.get('note')} | | |")
    lines += ["", f"Weather reuse: sunny's run {sunny['wall_s']} s (its radio step {sunny['radio_step_s']:.2f} s), "
              f"night's {night['wall_s']} s ({a['night_over_sunny_wall']:.3f}x); night's radio partitions up to "
              f"date: {', '.join(a['night_radio_partitions_up_to_date']) or 'none'}."]
    return lines


def run(quick: bool, out: Path) -> dict:
    """Measure, write ``out/results.json`` and ``out/report.md``, return the results."""
    quiet_dagster()
    src = TINY if quick else DEMO
    repeats = 3
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        from simart_pipeline.ckm.grid import scene_tiles
        from simart_pipeline.config import load_scene_config

        first_tile = scene_tiles(load_scene_config(src).ckm)[0]
        results = {"benchmark": "skipped_work", "quick": quick, "scene": src.name, "machine": machine(),
                   "repeats": repeats,
                   "weather_reuse": weather_reuse(src, tmp, first_tile),
                   "no_camera": no_camera(src, tmp, repeats),
                   "tile_inside_buildings": tile_inside_buildings(src, tmp, repeats)}
    write_outputs(Path(out), results, report_lines(results))
    return results


def main(argv=None) -> int:
    return cli_main(run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
