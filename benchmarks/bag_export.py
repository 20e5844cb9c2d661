"""Time and peak memory of writing a materialised session as a ROS bag.

    python -m benchmarks.bag_export DATA_ROOT SCENE_DIR OUT [--weather sunny] [--format mcap]

Opens the session, radar and CKM stores that ``simart run SCENE_DIR --data DATA_ROOT`` wrote, writes
the bag to OUT (which must not exist) and prints the messages, the bag's size, the seconds, and the
peak resident memory of this process before and after (``resource.getrusage``): what the export
adds is the difference. For a session 10x longer, copy the scene, multiply its ``clock.duration_s``
and ``simart run`` it (``--weather sunny --tile r0c0`` is enough) before measuring.
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

from simart_pipeline import stores
from simart_pipeline.ckm.maps import map_path
from simart_pipeline.config import load_scene_config
from simart_pipeline.export import bag
from simart_pipeline.radio.materials import WEATHER_GROUP
from simart_pipeline.scene.actors import scene_actors


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("scene_dir", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--weather", default="sunny")
    ap.add_argument("--format", default="mcap", choices=bag.FORMATS)
    args = ap.parse_args(argv)
    cfg = load_scene_config(args.scene_dir)
    group = WEATHER_GROUP[args.weather]
    session = stores.open_store(stores.store_path(args.data_root, "session", cfg.name, args.weather), tree=True)
    radar = stores.store_path(args.data_root, "radar_frames", cfg.name, group)
    ckm = map_path(args.data_root, cfg.name, group)
    before = _peak_mib()
    t0 = time.perf_counter()
    counts = bag.export_session(args.out, args.format, session, cfg, actors=scene_actors(cfg, args.scene_dir),
                                ckm=stores.open_store(ckm) if ckm.exists() else None, ckm_materials=group,
                                radar=stores.open_store(radar, tree=True) if radar.exists() else None)
    seconds = time.perf_counter() - t0
    files = [args.out] if args.out.is_file() else [f for f in args.out.rglob("*") if f.is_file()]
    print(f"{cfg.name}/{args.weather} ({args.format}, {cfg.clock.duration_s:g} s): {sum(counts.values())} messages, "
          f"{sum(f.stat().st_size for f in files) / 1e6:.1f} MB, {seconds:.1f} s, peak RSS {_peak_mib():.0f} MiB "
          f"({before:.0f} MiB before the export)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
