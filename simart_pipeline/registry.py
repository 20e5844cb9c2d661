"""Where scenes live: ``scenes/<name>/`` in the repository, or a directory registered by ``simart run``."""

from __future__ import annotations

import json
import os
from pathlib import Path

from simart_pipeline.config import SceneConfig, load_scene_config

REPO_ROOT = Path(__file__).resolve().parent.parent


def default_data_root() -> Path:
    return Path(os.environ.get("SIMART_DATA", REPO_ROOT / "data")).resolve()


def default_scenes_root() -> Path:
    return Path(os.environ.get("SIMART_SCENES", REPO_ROOT / "scenes")).resolve()


def _registry_file(data_root: Path) -> Path:
    return Path(data_root) / "scene_registry.json"


def register(scene_dir: Path, data_root: Path) -> SceneConfig:
    """Validate ``scene_dir`` and remember where scene ``<name>`` lives for this data root."""
    scene_dir = Path(scene_dir).resolve()
    cfg = load_scene_config(scene_dir)
    path = _registry_file(data_root)
    path.parent.mkdir(parents=True, exist_ok=True)
    reg = json.loads(path.read_text()) if path.exists() else {}
    reg[cfg.name] = str(scene_dir)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(reg, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)
    return cfg


def scene_dir(name: str, data_root: Path, scenes_root: Path) -> Path:
    path = _registry_file(data_root)
    if path.exists():
        reg = json.loads(path.read_text())
        if name in reg:
            return Path(reg[name])
    candidate = Path(scenes_root) / name
    if (candidate / "scene.yaml").is_file():
        return candidate
    raise FileNotFoundError(f"scene {name!r}: not registered in {path} and no {candidate}/scene.yaml")


def list_scenes(scenes_root: Path) -> list[Path]:
    return sorted(p.parent for p in Path(scenes_root).glob("*/scene.yaml"))
