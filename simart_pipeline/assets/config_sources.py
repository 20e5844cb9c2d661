"""The scene config as source assets: one observable source asset per stage, ``scene_config/<stage>``,
partitioned like the stage, whose data version is the digest of the part of ``scene.yaml`` (and of
the files) that the stage reads (``versions.VersionPlan.config_version``).

Each stage depends on its own config source, so the Dagster UI marks exactly the partitions an edit
concerns as stale, with the cause ("has a new dependency data version: scene_config/sensor_frames"):
a sensor's rate stales ``sensor_frames`` and what reads it, the rain materials the rainy radio work,
the CKM grid the CKM. ``simart run`` observes them before it decides what to run; in the UI,
"Observe sources" (or the asset's observe button) reads the edited file."""

from __future__ import annotations

import warnings

import dagster as dg

from simart_pipeline import versions
from simart_pipeline.partitions import scene_partitions, scene_tile, scene_weather, scene_weather_group
from simart_pipeline.radio.materials import WEATHER_GROUPS
from simart_pipeline.vocabulary import WEATHERS

CONFIG_PREFIX = "scene_config"
DATA_VERSION_TAG = "dagster/data_version"  # the tag Dagster reads an observation's data version from
PARTITIONS = {"scene": scene_partitions, "weather": scene_weather, "weather_group": scene_weather_group,
              "tile": scene_tile}


def config_key(asset: str) -> dg.AssetKey:
    return dg.AssetKey([CONFIG_PREFIX, asset])


def _sub_keys(cfg, partitioned_by: str) -> list[str | None]:
    from simart_pipeline.ckm.grid import scene_tiles

    return {"scene": [None], "weather": list(WEATHERS), "weather_group": list(WEATHER_GROUPS),
            "tile": scene_tiles(cfg.ckm)}[partitioned_by]


def config_versions(plan: versions.VersionPlan, asset: str) -> dict:
    """``{partition key: config version}`` of one stage's config source for the plan's scene."""
    kind = versions.STAGES[asset].partitioned_by
    return {plan.cfg.name if sub is None else dg.MultiPartitionKey({"scene": plan.cfg.name, kind: sub}):
            plan.config_version(asset, sub) for sub in _sub_keys(plan.cfg, kind)}


def report_config_versions(instance: dg.DagsterInstance, plan: versions.VersionPlan) -> int:
    """Record every config source's version of the plan's scene as an observation (what the
    observation jobs do, without a run per partitioning: ``simart run`` calls it before it plans)."""
    n = 0
    for asset in versions.STAGES:
        for key, version in config_versions(plan, asset).items():
            instance.report_runless_asset_event(dg.AssetObservation(
                config_key(asset), partition=str(key), tags={DATA_VERSION_TAG: version}))
            n += 1
    return n


def _config_source(asset: str, stage: versions.Stage):
    partitions_def = PARTITIONS[stage.partitioned_by]

    @dg.observable_source_asset(key=config_key(asset), partitions_def=partitions_def, group_name="config",
                                required_resource_keys={"project"},
                                description=f"The part of each scene's scene.yaml (and the files it names) "
                                            f"that `{asset}` reads.")
    def observe_config(context) -> dg.DataVersionsByPartition:
        project = context.resources.project
        out = {}
        for scene in sorted(context.instance.get_dynamic_partitions(scene_partitions.name)):
            try:
                plan = project.version_plan(scene)
            except Exception as exc:  # an invalid or vanished scene has no version to observe
                context.log.warning(f"{scene}: config not observed: {exc}")
                continue
            out.update({k: dg.DataVersion(v) for k, v in config_versions(plan, asset).items()})
        return dg.DataVersionsByPartition(out)

    return observe_config


with warnings.catch_warnings():
    warnings.simplefilter("ignore", dg.BetaWarning)  # observable_source_asset: in use since Dagster 1.1
    CONFIG_SOURCES = [_config_source(asset, stage) for asset, stage in versions.STAGES.items()]


def observation_jobs() -> list[dg.UnresolvedAssetJobDefinition]:
    """One job per partitioning that observes the config sources (a job holds one partitioning)."""
    jobs = []
    for kind in PARTITIONS:
        keys = [config_key(a) for a, st in versions.STAGES.items() if st.partitioned_by == kind]
        if keys:
            jobs.append(dg.define_asset_job(f"observe_scene_config_{kind}", selection=dg.AssetSelection.assets(*keys),
                                            description="Read every scene's scene.yaml and files: the config "
                                                        "sources' data versions (what is stale, and why)."))
    return jobs
