"""Declarative automation: what keeps a scene's datasets fresh without a command.

Every asset carries :data:`KEEP_FRESH`: Dagster's ``eager()`` (materialise a partition that becomes
missing, or whose upstream updated, once no upstream is missing or running) restricted by
:class:`InSceneConfig` to the partitions a scene's config uses (its weathers, their weather groups,
its CKM tiles), for the partition itself and for the upstream partitions it waits for: the
partition space holds every weather and a fixed 8 x 8 tiling, and a scene that lists two weathers
and four tiles must neither compute the others nor wait for them. :data:`AUTOMATION_SENSOR` evaluates
the conditions; :func:`new_scenes` notices new or changed scene folders. Both on by default for a
local instance (``SIMART_AUTOMATION=off`` declares them stopped).
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from functools import lru_cache
from pathlib import Path

import dagster as dg

from simart_pipeline import registry, versions
from simart_pipeline.ckm.grid import scene_tiles
from simart_pipeline.config import ConfigError, SceneConfig, load_scene_config
from simart_pipeline.radio.materials import WEATHER_GROUP


@lru_cache(maxsize=64)
def _config(path: str, mtime_ns: int) -> SceneConfig | None:
    try:
        return load_scene_config(path)
    except (ConfigError, OSError):
        return None


def scene_config(scene: str) -> SceneConfig | None:
    """The config of a registered scene as it is on disk now (None: unknown or invalid)."""
    try:
        d = registry.scene_dir(scene, registry.default_data_root(), registry.default_scenes_root())
        return _config(str(d), (Path(d) / "scene.yaml").stat().st_mtime_ns)
    except (FileNotFoundError, OSError):
        return None


def partition_in_use(partition_key: str, dimension: str | None, asset: str | None = None) -> bool:
    """True for a scene partition (``dimension`` None) or a (scene, ``dimension``) partition that
    the scene's config uses: a weather it lists, the group of one, one of its tiles. Multi-partition
    keys are ``scene|sub`` (dimension names in order). The dimension matters: ``sunny`` names both a
    weather and the dry weather group, which a scene listing only ``night`` uses."""
    scene, _, sub = str(partition_key).partition("|")
    cfg = scene_config(scene)
    if cfg is None or (asset == "beam_prediction" and cfg.beam_study is None):  # only scenes with a study
        return False
    used = {None: {""}, "weather": set(cfg.weathers), "weather_group": {WEATHER_GROUP[w] for w in cfg.weathers},
            "tile": set(scene_tiles(cfg.ckm))}[dimension]
    return sub in used


class InSceneConfig(dg.AutomationCondition):
    """True for the partitions the scene's config uses (:func:`partition_in_use`)."""

    @property
    def name(self) -> str:
        return "in_scene_config"

    def evaluate(self, context: dg.AutomationContext) -> dg.AutomationResult:
        pd = context.partitions_def
        dimension = next((d.name for d in pd.partitions_defs if d.name != "scene"), None) \
            if isinstance(pd, dg.MultiPartitionsDefinition) else None
        keys = context.candidate_subset.expensively_compute_partition_keys()
        used = {k for k in keys if partition_in_use(k, dimension, context.key.to_user_string())}
        return dg.AutomationResult(context, context.candidate_subset.compute_intersection_with_partition_keys(used))


# Dagster's eager(), with its "no upstream missing" made to look only at upstream partitions the
# scene uses: ckm_map reads the scene's tiles, not the 64 of the static tiling.
_AC = dg.AutomationCondition
KEEP_FRESH = (
    InSceneConfig()
    & (_AC.newly_missing() | _AC.any_deps_updated()).since_last_handled()
    & ~_AC.any_deps_match(_AC.missing() & InSceneConfig()).with_label("any used deps missing")
    & ~_AC.any_deps_in_progress()
    & ~_AC.in_progress()
).with_label("eager, within the scene's config")

_ON = dg.DefaultSensorStatus.RUNNING if os.environ.get("SIMART_AUTOMATION", "on") != "off" \
    else dg.DefaultSensorStatus.STOPPED

with warnings.catch_warnings():
    warnings.simplefilter("ignore", dg.BetaWarning)  # use_user_code_server: InSceneConfig is Python
    AUTOMATION_SENSOR = dg.AutomationConditionSensorDefinition(
        "keep_scenes_fresh", target=dg.AssetSelection.all(), use_user_code_server=True, default_status=_ON,
        description="Declarative automation of every asset (eager, restricted to the partitions each "
                    "scene's config uses). On by default for a local instance; SIMART_AUTOMATION=off "
                    "declares it stopped.")


def scan_scenes(instance, cursor: str | None) -> tuple[list[str], list[str], str]:
    """``(new scene names, problem lines, new cursor)`` of the folders under the scenes root whose
    scene.yaml is new or changed since ``cursor``: a valid one is registered and its config versions
    reported (so Dagster sees what an edit makes stale); an invalid one gives its ``file: key.path:
    message`` lines, and the scan goes on."""
    from simart_pipeline.assets.config_sources import report_config_versions
    from simart_pipeline.partitions import scene_partitions

    data_root = registry.default_data_root()
    seen = json.loads(cursor) if cursor else {}
    now, added, problems = {}, [], []
    for yaml_file in sorted(registry.default_scenes_root().glob("*/scene.yaml")):
        digest = hashlib.sha256(yaml_file.read_bytes()).hexdigest()
        now[str(yaml_file)] = digest
        if seen.get(str(yaml_file)) == digest:
            continue
        try:
            cfg = registry.register(yaml_file.parent, data_root)
        except ConfigError as exc:
            problems += exc.problems
            continue
        except Exception as exc:  # noqa: BLE001 - one bad folder never stops the scan
            problems.append(f"{yaml_file}: (top level): {' '.join(str(exc).split())}")
            continue
        report_config_versions(instance, versions.VersionPlan(cfg, yaml_file.parent))
        if not instance.has_dynamic_partition(scene_partitions.name, cfg.name):
            added.append(cfg.name)
    return added, problems, json.dumps(now, sort_keys=True)


@dg.sensor(name="new_scenes", minimum_interval_seconds=30, default_status=_ON)
def new_scenes(context: dg.SensorEvaluationContext):
    """New or changed scene folders (:func:`scan_scenes`): a new valid scene's partition is added,
    and the automation requests what is missing; problems go to the tick's log (and its skip
    reason when nothing is added)."""
    from simart_pipeline.partitions import scene_partitions

    added, problems, cursor = scan_scenes(context.instance, context.cursor)
    for line in problems:
        context.log.error(line)
    context.update_cursor(cursor)
    if added:
        return dg.SensorResult(dynamic_partitions_requests=[scene_partitions.build_add_request(added)])
    return dg.SkipReason("; ".join(problems) if problems else "no new or changed scene")
