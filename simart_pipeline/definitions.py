"""The one Definitions object: ``dagster dev`` and ``dagster definitions validate`` load it."""

import dagster as dg

from simart_pipeline.assets import ALL_ASSETS, ALL_CHECKS
from simart_pipeline.assets.config_sources import observation_jobs
from simart_pipeline.resources import ProjectResource, RayTracerResource, ZarrStoreIOManager


def build_definitions(data_root: str | None = None, scenes_root: str | None = None) -> dg.Definitions:
    project = ProjectResource(**{k: v for k, v in (("data_root", data_root), ("scenes_root", scenes_root)) if v})
    return dg.Definitions(
        assets=ALL_ASSETS,
        jobs=observation_jobs(),
        asset_checks=ALL_CHECKS,
        resources={
            "project": project,
            "ray_tracer": RayTracerResource(),
            "io_manager": ZarrStoreIOManager(data_root=project.data_root),
        },
    )


defs = build_definitions()
