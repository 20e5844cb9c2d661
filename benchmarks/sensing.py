"""Sensor rendering speed on a real city, and one frame in every weather.

    python -m benchmarks.sensing [--extract helsinki.osm.pbf] [--frames 20] [--sweeps 10] [--out DIR]

On an OSM extract from ../shared/data/osm built into the visual mesh as the ``paired_meshes``
stage builds it, a camera 2 m above the middle of the road with the most buildings around
looks along it:

- camera: 640 x 480, 90 deg, RGB + z-depth + semantic class + instance id per frame, through
  ``sensing.camera.render_camera`` (ray casting, sun shadow rays, shading, tone mapping, rain
  streaks, noise, and the numpy work of the stream), frames 1 m apart along the road, per weather;
- LiDAR: 64 channels x 2048 azimuths, -25..+15 deg, 120 m, through ``sensing.lidar.render_lidar``.

Timings are warm (the first frame compiles the kernels and is not counted). It prints frames per
second per weather and LiDAR sweeps per second, and measurable differences between the weathers
(mean luma, contrast of the far half of the depth range, share of LiDAR returns, range noise);
with ``--out`` it writes ``results.json`` and one PNG per weather of the same frame, plus the three
side by side (``weathers.png``).
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from simart_pipeline import engine, frames
from simart_pipeline.config import Camera, Lidar
from simart_pipeline.scene import meshes
from simart_pipeline.scene.osm import read_extract
from simart_pipeline.sensing import camera, lidar, raycast
from simart_pipeline.sensing.streams import stream_rng
from simart_pipeline.sensing.weather import WEATHER_MODELS

OSM = Path(__file__).resolve().parents[2] / "shared" / "data" / "osm"


def street_view(geom) -> tuple[np.ndarray, float]:
    """A point 2 m above the middle of the road with the most buildings within 40 m (a street
    canyon, not a field), and the road's heading (rad from +x)."""
    from shapely import STRtree

    roads = [f.geometry for f in geom.of_class("road")
             if f.geometry.geom_type == "LineString" and f.geometry.length > 30.0]
    if not roads:
        raise ValueError("the extract has no road to stand on")
    tree = STRtree([f.geometry for f in geom.volumes()])
    mids = [r.interpolate(0.5, normalized=True) for r in roads]
    crowd = [len(tree.query(m.buffer(40.0), predicate="intersects")) for m in mids]
    k = int(np.argmax(crowd))
    line, mid = roads[k], mids[k]
    ahead = line.interpolate(0.5 * line.length + 1.0)
    return np.array([mid.x, mid.y, 2.0]), float(np.arctan2(ahead.y - mid.y, ahead.x - mid.x))


def luma(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., :3].astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--extract", default="helsinki.osm.pbf")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--sweeps", type=int, default=10)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)  # dropped buildings of real extracts are expected here
    variant = engine.init()
    geom = read_extract(OSM / args.extract)
    scene_meshes = meshes.build_meshes(geom)
    caster = raycast.RayCaster(scene_meshes)
    start, yaw = street_view(geom)
    n = args.frames + 1
    along = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    pos = start[None] + np.arange(n)[:, None] * along[None]
    body = Rotation.from_euler("z", np.full((n, 1), yaw))
    times_ns = np.arange(n, dtype=np.int64) * 100_000_000
    cam = Camera(kind="camera", name="cam", width_px=640, height_px=480, horizontal_fov_deg=90.0)
    result = {"extract": args.extract, "visual_triangles": int(len(scene_meshes.visual.faces)),
              "variant": variant, "machine": f"{platform.machine()}, {__import__('os').cpu_count()} CPU cores",
              "camera": {"width_px": 640, "height_px": 480, "frames_timed": args.frames}, "weathers": {}}
    pictures = {}
    for name, wx in WEATHER_MODELS.items():
        rng = stream_rng(0, "bench", "cam", name)
        camera.render_camera(caster, cam, times_ns[:1], pos[:1], body[:1] * frames.OPTICAL_TO_BODY, wx, rng)
        t0 = time.perf_counter()
        ds = camera.render_camera(caster, cam, times_ns[1:], pos[1:], body[1:] * frames.OPTICAL_TO_BODY, wx, rng)
        dt = time.perf_counter() - t0
        rgb = ds["rgb"].values
        depth = ds["depth_m"].values[0]
        far = np.isfinite(depth) & (depth > np.nanpercentile(depth, 50))
        y0 = luma(rgb[0])
        pictures[name] = rgb[0]
        result["weathers"][name] = {
            "frames_per_s": round(args.frames / dt, 2), "ms_per_frame": round(1e3 * dt / args.frames, 1),
            "mean_luma_dn": round(float(y0.mean()), 2),
            "far_half_luma_std_dn": round(float(y0[far].std()), 2) if far.any() else None,
            "pixels_with_surface_pct": round(100 * float(np.isfinite(depth).mean()), 2)}
    lid = Lidar(kind="lidar", name="lidar", channels=64, horizontal_samples=2048, vertical_fov_deg=(-25.0, 15.0),
                max_range_m=120.0, range_noise_std_m=0.02)
    m = args.sweeps + 1
    lpos = start[None] + np.arange(m)[:, None] * along[None]
    lrot = Rotation.from_euler("z", np.full((m, 1), yaw))
    lt = np.arange(m, dtype=np.int64) * 100_000_000
    result["lidar"] = {"channels": 64, "horizontal_samples": 2048, "sweeps_timed": args.sweeps, "weathers": {}}
    ideal = None
    for name, wx in WEATHER_MODELS.items():
        rng = stream_rng(0, "bench", "lidar", name)
        lidar.render_lidar(caster, lid, lt[:1], lpos[:1], lrot[:1], wx, rng)
        t0 = time.perf_counter()
        ds = lidar.render_lidar(caster, lid, lt[1:], lpos[1:], lrot[1:], wx, rng)
        dt = time.perf_counter() - t0
        r = ds["range_m"].values
        if ideal is None:  # the exact ranges, to measure each weather's noise against
            ideal = raycast.RayBundle(caster, lidar.beam_directions(lid).reshape(-1, 3))
        exact = np.stack([ideal.cast(lpos[1 + i], lrot[1 + i].as_matrix())[0].reshape(r.shape[1:])
                          for i in range(args.sweeps)])
        both = np.isfinite(r) & np.isfinite(exact) & (exact <= lid.max_range_m)
        result["lidar"]["weathers"][name] = {
            "sweeps_per_s": round(args.sweeps / dt, 2), "ms_per_sweep": round(1e3 * dt / args.sweeps, 1),
            "returns_pct": round(100 * float(np.isfinite(r).mean()), 2),
            "range_error_std_m": round(float((r - exact)[both].std()), 4)}
    print(json.dumps(result, indent=1))
    if args.out:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps(result, indent=2) + "\n")
        for name, img in pictures.items():
            plt.imsave(args.out / f"weather_{name}.png", img)
        fig, axes = plt.subplots(1, len(pictures), figsize=(6.4 * len(pictures), 5.2), dpi=80)
        for ax, (name, img) in zip(np.atleast_1d(axes), pictures.items()):
            ax.imshow(img)
            ax.set_title(f"{name}: {result['weathers'][name]['ms_per_frame']} ms/frame")
            ax.axis("off")
        fig.suptitle(f"{args.extract}: the same 640 x 480 frame in every weather")
        fig.tight_layout()
        fig.savefig(args.out / "weathers.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
