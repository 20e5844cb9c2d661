"""The one Definitions object: ``dagster dev`` and ``dagster definitions validate`` load it."""

import dagster as dg

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


def build_definitions(data_root: str | None = None, scenes_root: str | None = None) -> dg.Definitions:
    project = ProjectResource(**{k: v for k, v in (("data_root", data_root), ("scenes_root", scenes_root)) if v})
    return dg.Definitions(
        assets=AUTOMATED_ASSETS,
        sensors=[AUTOMATION_SENSOR, new_scenes, NIGHTLY_SENSOR],
        jobs=observation_jobs(),
        asset_checks=ALL_CHECKS,
        resources={
            "project": project,
            "ray_tracer": RayTracerResource(),
            "io_manager": ZarrStoreIOManager(data_root=project.data_root),
        },
    )


defs = build_definitions()
