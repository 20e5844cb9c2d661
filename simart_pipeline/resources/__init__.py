"""Dagster resources: where things are, how stores are read and written, and the ray tracer."""

from __future__ import annotations

from pathlib import Path

import dagster as dg
import xarray as xr

from simart_pipeline import registry, stores, versions
from simart_pipeline.config import SceneConfig, load_scene_config
from simart_pipeline.partitions import split_key
from simart_pipeline.scene import meshes as scene_meshes

# Assets whose partitions are a tree of groups, or a directory of standard files.
TREE_ASSETS = {"sensor_frames", "session", "radar_frames"}
DIRECTORY_ASSETS = {"paired_meshes", "session_bag", "beam_prediction"}


class ProjectResource(dg.ConfigurableResource):
    """The data root and the scenes root; resolves a scene partition key to its directory and config."""

    data_root: str = str(registry.default_data_root())
    scenes_root: str = str(registry.default_scenes_root())

    def scene_dir(self, scene: str) -> Path:
        return registry.scene_dir(scene, Path(self.data_root), Path(self.scenes_root))

    def config(self, scene: str) -> SceneConfig:
        return load_scene_config(self.scene_dir(scene))

    def version_plan(self, scene: str) -> versions.VersionPlan:
        """The data versions of the scene's asset partitions, from its config and files as they are now
        (file digests are cached by modification time, code versions per process)."""
        d = self.scene_dir(scene)
        return versions.VersionPlan(load_scene_config(d), d)


_LOADED: dict[tuple, object] = {}  # radio scenes loaded in this process (one per scene file, config, weather)


class RayTracerResource(dg.ConfigurableResource):
    """Sionna RT: picks the cuda variant when a GPU is present, LLVM otherwise (engine.init).

    A radio scene is loaded once per process for each (radio mesh file and its modification time,
    scene config, weather): the CKM tiles of one scene share one load."""

    def load(self, paired_meshes: scene_meshes.SceneMeshes | Path, cfg: SceneConfig, weather: str,
             actors_from: Path | None = None):
        """The radio scene of ``cfg`` in ``weather`` (``paired_meshes``: the asset's value, or the
        folder it was written to); with ``actors_from`` (the scene folder) it also holds the
        scene's actors (``scene.actors``): the CIRs see them, the CKM does not."""
        from simart_pipeline.radio.tracer import RadioScene
        from simart_pipeline.scene.actors import scene_actors

        root = paired_meshes if isinstance(paired_meshes, Path) else paired_meshes.root
        xml = scene_meshes.radio_scene_file(root)
        bodies = () if actors_from is None else tuple(
            versions.file_digest(Path(actors_from) / a.body.mesh)
            for a in (*cfg.platforms, *cfg.static_actors) if a.body.is_file)
        key = (str(xml.resolve()), xml.stat().st_mtime_ns, cfg.digest(), weather, actors_from is not None, bodies)
        if key not in _LOADED:
            if len(_LOADED) >= 4:
                _LOADED.pop(next(iter(_LOADED)))
            radio = RadioScene.from_config(xml, cfg, weather)
            if actors_from is not None:
                radio.add_actors(scene_actors(cfg, actors_from))
            _LOADED[key] = radio
        return _LOADED[key]

    def variant(self) -> str:
        from simart_pipeline import engine

        return engine.init()


class ZarrStoreIOManager(dg.ConfigurableIOManager):
    """One store per asset partition under ``data_root`` (see stores.store_path), written atomically."""

    data_root: str = str(registry.default_data_root())

    def _path(self, context) -> Path:
        asset = context.asset_key.path[-1]
        scene, sub = split_key(context.asset_partition_key)
        suffix = "" if asset in DIRECTORY_ASSETS else ".zarr"
        return stores.store_path(self.data_root, asset, scene, sub, suffix=suffix)

    def handle_output(self, context: dg.OutputContext, obj) -> None:
        path = self._path(context)
        if isinstance(obj, (xr.Dataset, xr.DataTree)):
            stores.write_store(obj, path)
        elif isinstance(obj, scene_meshes.PairedMeshesOutput):
            stores.write_directory(path, obj.save)
        else:
            raise TypeError(f"{context.asset_key.to_user_string()}: cannot store {type(obj).__name__}")
        context.add_output_metadata({"path": dg.MetadataValue.path(str(path))})

    def load_input(self, context: dg.InputContext):
        path = self._path(context)
        asset = context.asset_key.path[-1]
        if asset in DIRECTORY_ASSETS:
            if not path.is_dir():
                raise FileNotFoundError(f"no {asset} at {path}: materialise it first")
            return scene_meshes.load(path)
        return stores.open_store(path, tree=asset in TREE_ASSETS)
