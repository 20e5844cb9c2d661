"""The one Definitions object: ``dagster dev``, ``dagster definitions validate`` and the gRPC code
server of a Kubernetes deployment (``deploy/``, ``docs/cluster.md``) load it."""

import dagster as dg

from simart_pipeline import cluster
from simart_pipeline.assets import ALL_ASSETS, ALL_CHECKS, CONFIG_SOURCES
from simart_pipeline.assets.config_sources import observation_jobs
from simart_pipeline.assets.automation import AUTOMATION_SENSOR, KEEP_FRESH, new_scenes
from simart_pipeline.assets.nightly import NIGHTLY_SENSOR
from simart_pipeline.resources import ProjectResource, RayTracerResource, ZarrStoreIOManager

# Every materialisable asset keeps itself fresh (assets/automation.py); the config sources
# are observed, not materialised.
AUTOMATED_ASSETS = [*dg.map_asset_specs(lambda spec: spec.replace_attributes(automation_condition=KEEP_FRESH),
                                        [a for a in ALL_ASSETS if a not in CONFIG_SOURCES]),
                    *CONFIG_SOURCES]


# Jobs to launch from the command line (`dagster job backfill`, docs/cluster.md). A job holds assets
# of one partition definition, so a scene's CKM takes three: its scene assets (per scene), its tiles
# (per scene and tile, the ray tracing), its map (per scene).
CKM_JOBS = [
    dg.define_asset_job("scene_assets", selection=["osm_extract", "paired_meshes", "trajectory"],
                        description="A scene's source geometry, paired meshes and trajectories."),
    dg.define_asset_job("ckm_tiles", selection=["ckm_layers"],
                        description="CKM tiles: one partition per (scene, tile), each a ray-tracing step."),
    dg.define_asset_job("ckm_maps", selection=["ckm_map"], description="A scene's CKM maps and pictures."),
]


def build_definitions(data_root: str | None = None, scenes_root: str | None = None,
                      executor: str | None = None) -> dg.Definitions:
    """The project's Definitions. ``executor`` (default ``$SIMART_EXECUTOR``, else ``local``):
    ``local`` keeps Dagster's default executor; ``k8s`` runs each step in its own Kubernetes pod and
    puts the steps of the GPU pools on GPU nodes (``simart_pipeline.cluster``)."""
    project = ProjectResource(**{k: v for k, v in (("data_root", data_root), ("scenes_root", scenes_root)) if v})
    on_k8s = cluster.executor_mode(executor) == "k8s"
    return dg.Definitions(
        assets=cluster.gpu_tagged(AUTOMATED_ASSETS) if on_k8s else AUTOMATED_ASSETS,
        executor=cluster.k8s_executor() if on_k8s else None,
        sensors=[AUTOMATION_SENSOR, new_scenes, NIGHTLY_SENSOR],
        jobs=[*observation_jobs(), *CKM_JOBS],
        asset_checks=ALL_CHECKS,
        resources={
            "project": project,
            "ray_tracer": RayTracerResource(),
            "io_manager": ZarrStoreIOManager(data_root=project.data_root),
        },
    )


defs = build_definitions()
