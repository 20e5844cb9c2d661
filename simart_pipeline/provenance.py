"""Provenance attrs stamped on every store: config hash, code and package versions, seeds.

No wall-clock time: the same config and code give bitwise-equal stores (Dagster records when
each materialisation ran).
"""

from __future__ import annotations

import json
import subprocess
from functools import lru_cache
from pathlib import Path

from simart_pipeline import __version__, engine
from simart_pipeline.config import SceneConfig

OSM_ATTRIBUTION = "Map data © OpenStreetMap contributors, ODbL 1.0 (https://www.openstreetmap.org/copyright)"


@lru_cache(maxsize=1)
def code_version() -> str:
    """Package version plus the git commit when run from a checkout (``+dirty`` if modified)."""
    root = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty"],
                             capture_output=True, text=True, timeout=5)
        if rev.returncode == 0 and rev.stdout.strip():
            return f"{__version__}+g{rev.stdout.strip()}"
    except (OSError, subprocess.SubprocessError):
        pass
    return __version__


def attrs(cfg: SceneConfig, asset: str, **extra) -> dict:
    out = {
        "scene": cfg.name,
        "created_by": f"simart-pipeline asset {asset}",
        "config_sha256": cfg.digest(),
        "code_version": code_version(),
        "package_versions": json.dumps(engine.versions(), sort_keys=True),
        "seed": cfg.seed,
        "ray_tracing_seed": cfg.ray_tracing.seed,
        "world_origin_lat_lon_alt": [cfg.origin.latitude_deg, cfg.origin.longitude_deg, cfg.origin.altitude_m],
        "frame_convention": "ENU world frame around the origin; REP 105/103 frame names",
        "time_convention": "int64 ns of simulated time since session start",
    }
    if cfg.source.kind == "osm":
        out["attribution"] = OSM_ATTRIBUTION
    out.update(extra)
    return out
