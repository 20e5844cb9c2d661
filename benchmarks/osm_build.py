"""Scene construction cost on the shared OSM extracts: read, mesh and write, per extract.

    python -m benchmarks.osm_build [--repeat 3] [--json out.json]

For each extract in ../shared/data/osm: the best of ``--repeat`` wall-clock times of reading
(pyosmium pass, one vectorised ENU projection, repairs, parts), meshing (solids, roofs, window
frames, ground surfaces) and writing (PLY, XML, labels, scene.json), with the counts, and the
visual / radio triangle ratio.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

from simart_pipeline import stores
from simart_pipeline.scene import meshes
from simart_pipeline.scene.osm import read_extract

OSM = Path(__file__).resolve().parents[2] / "shared" / "data" / "osm"
EXTRACTS = ["small_block.osm", "neukolln.osm", "taipei.osm", "helsinki.osm.pbf"]


def measure(path: Path, repeat: int) -> dict:
    best = {"read_s": float("inf"), "mesh_s": float("inf"), "write_s": float("inf")}
    for _ in range(repeat):
        t0 = time.perf_counter()
        geom = read_extract(path)
        t1 = time.perf_counter()
        m = meshes.build_meshes(geom)
        t2 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            stores.write_directory(Path(tmp) / "out", lambda d: meshes.save(m, d, {}, 0.2, 3.5e9))
        t3 = time.perf_counter()
        for k, v in zip(best, (t1 - t0, t2 - t1, t3 - t2)):
            best[k] = min(best[k], v)
    c = m.counts()
    return {**{k: round(v, 3) for k, v in best.items()}, "total_s": round(sum(best.values()), 3),
            "buildings": len(geom.of_class("building")), "building_parts": len(geom.of_class("building_part")),
            "visual_triangles": c["visual_triangles"], "radio_triangles": c["radio_triangles"],
            "visual_per_radio_triangle": round(c["visual_triangles"] / c["radio_triangles"], 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)  # the extracts' dropped buildings are expected here
    results = {}
    for name in EXTRACTS:
        results[name] = r = measure(OSM / name, args.repeat)
        print(f"{name:18s} read {r['read_s']:6.2f} s  mesh {r['mesh_s']:6.2f} s  write {r['write_s']:6.2f} s  "
              f"total {r['total_s']:6.2f} s  {r['buildings']} buildings + {r['building_parts']} parts  "
              f"visual {r['visual_triangles']} / radio {r['radio_triangles']} triangles "
              f"({r['visual_per_radio_triangle']}x)")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
