"""The nightly regeneration: once a night, one backfill of exactly the asset partitions that are
stale or missing (:func:`simart_pipeline.assets.staleness.stale_partitions`), every scene.

It is a sensor gated on a cron tick, not a schedule: a schedule targets one job, a job holds assets
of one partition definition only (here: scene, scene x weather, scene x weather group, scene x
tile), and in Dagster 1.13 only a sensor may answer with a backfill
(``RunRequest.for_asset_graph_subset``), which the backfill daemon then runs across partition
definitions in dependency order, through the instance's run queue and pools.

When: ``SIMART_NIGHTLY_CRON`` (default ``0 2 * * *``, 02:00) in ``SIMART_NIGHTLY_TZ`` (default the
machine's local zone), read where the code location loads. The sensor looks every minute; the
first cron tick after the one it last handled (its cursor) is due, once: a daemon that was down at
02:00 regenerates when it comes back, and a new sensor starts by remembering the last tick instead
of regenerating at once. Partitions that an unfinished backfill or a queued or running run already
covers are left out, so nothing is requested twice.
"""

from __future__ import annotations

import json
import os

import dagster as dg
from dagster._core.execution.backfill import BulkActionsFilter, BulkActionStatus
from dagster._core.storage.dagster_run import IN_PROGRESS_RUN_STATUSES
from dagster._time import get_current_datetime
from dagster._utils.schedules import get_latest_completed_cron_tick, get_next_cron_tick, is_valid_cron_string

from simart_pipeline.assets.staleness import BACKFILL_TAG, backfill_request, stale_partitions
from simart_pipeline.partitions import scene_partitions
from simart_pipeline.resources import ProjectResource

UNFINISHED_BACKFILL = [BulkActionStatus.REQUESTED, BulkActionStatus.CANCELING, BulkActionStatus.FAILING]


def local_timezone() -> str:
    """The machine's IANA time zone: ``$TZ``, else the target of /etc/localtime, else UTC."""
    if os.environ.get("TZ", "").strip(":"):
        return os.environ["TZ"].strip(":")
    target = os.path.realpath("/etc/localtime")
    return target.split("zoneinfo/", 1)[1] if "zoneinfo/" in target else "UTC"


NIGHTLY_CRON = os.environ.get("SIMART_NIGHTLY_CRON", "0 2 * * *")
NIGHTLY_TZ = os.environ.get("SIMART_NIGHTLY_TZ") or local_timezone()


def in_flight(instance) -> set[tuple[str, str]]:
    """``{(asset, partition key)}`` that an unfinished backfill targets or a queued or running run
    materialises."""
    out = set()
    for backfill in instance.get_backfills(filters=BulkActionsFilter(statuses=UNFINISHED_BACKFILL)):
        if backfill.asset_backfill_data is not None:
            out |= {(ak.asset_key.to_user_string(), str(ak.partition_key))
                    for ak in backfill.asset_backfill_data.target_subset.iterate_asset_partitions()}
    for run in instance.get_runs(filters=dg.RunsFilter(statuses=list(IN_PROGRESS_RUN_STATUSES))):
        part = run.tags.get("dagster/partition")
        out |= {(k.to_user_string(), part) for k in (run.asset_selection or ()) if part}
    return out


def regeneration_plan(instance, project: ProjectResource, log=None) -> dict[tuple[str, object], str]:
    """``{(asset, partition key): why}`` of every registered scene's stale or missing partitions
    (those its config uses) that nothing in flight covers yet; a scene whose config cannot be read
    is left out (and logged)."""
    busy = in_flight(instance)
    out = {}
    for scene in sorted(instance.get_dynamic_partitions(scene_partitions.name)):
        try:
            stale = stale_partitions(instance, project, scene)
        except Exception as exc:  # noqa: BLE001 - an invalid or vanished scene never stops the others
            if log is not None:
                log.warning(f"{scene}: not regenerated: {' '.join(str(exc).split())}")
            continue
        out.update({(a, k): why for (a, k), why in stale.items() if (a, str(k)) not in busy})
    return out


def nightly_regeneration_sensor(cron: str = NIGHTLY_CRON, timezone: str = NIGHTLY_TZ,
                                default_status: dg.DefaultSensorStatus = dg.DefaultSensorStatus.RUNNING
                                ) -> dg.SensorDefinition:
    """The sensor ``nightly_regeneration``: at the first evaluation after each tick of ``cron`` (in
    ``timezone``), one backfill of :func:`regeneration_plan`'s partitions."""
    if not is_valid_cron_string(cron):
        raise ValueError(f"SIMART_NIGHTLY_CRON: {cron!r} is not a cron string (e.g. '0 2 * * *')")

    @dg.sensor(name="nightly_regeneration", minimum_interval_seconds=60, default_status=default_status,
               description=f"At '{cron}' ({timezone}; SIMART_NIGHTLY_CRON, SIMART_NIGHTLY_TZ): one backfill of "
                           "every stale or missing asset partition of every scene, nothing else.")
    def nightly_regeneration(context: dg.SensorEvaluationContext, project: ProjectResource):
        now = get_current_datetime()
        tick = get_latest_completed_cron_tick(cron, now, timezone)
        upcoming = get_next_cron_tick(cron, now, timezone).isoformat()
        handled = json.loads(context.cursor)["tick"] if context.cursor else None
        cursor = json.dumps({"tick": tick.timestamp()})
        if handled is None:  # a new sensor remembers the last tick instead of regenerating at once
            return dg.SensorResult(skip_reason=f"started; the first regeneration is at {upcoming}", cursor=cursor)
        if tick.timestamp() <= handled:
            return dg.SensorResult(skip_reason=f"the next regeneration is at {upcoming}", cursor=context.cursor)
        plan = regeneration_plan(context.instance, project, context.log)
        if not plan:
            return dg.SensorResult(skip_reason=f"{tick.isoformat()}: nothing is stale or missing", cursor=cursor)
        for (asset, key), why in plan.items():
            context.log.info(f"{asset} ({key}): {why}")
        graph = context.repository_def.asset_graph
        request = backfill_request(graph, plan, {BACKFILL_TAG: "nightly", "simart/nightly_tick": tick.isoformat()})
        return dg.SensorResult(run_requests=[request], cursor=cursor)

    return nightly_regeneration


_ON = dg.DefaultSensorStatus.RUNNING if os.environ.get("SIMART_AUTOMATION", "on") != "off" \
    else dg.DefaultSensorStatus.STOPPED
NIGHTLY_SENSOR = nightly_regeneration_sensor(default_status=_ON)
