"""What the benchmarks share: a scene's source geometry and paired meshes, built as the assets do."""

from __future__ import annotations

from pathlib import Path

from simart_pipeline import stores
from simart_pipeline.scene import meshes, source
from simart_pipeline.scene.build import paired_meshes_for_scene

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "demo"


def build_scene(cfg, scene_dir: Path, out: Path):
    """Source geometry and the radio scene XML of ``cfg`` (paired meshes written under ``out``)."""
    geom = source.build_source_geometry(cfg, scene_dir)
    stores.write_directory(out, paired_meshes_for_scene(cfg, scene_dir, geom).save)
    return geom, meshes.radio_scene_file(out)
