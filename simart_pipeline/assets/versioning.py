"""Data versions on every materialisation: the asset's code version, and a data version computed
from its inputs (``simart_pipeline.versions``), recorded in Dagster and in the store's attrs."""

from __future__ import annotations

import warnings

import dagster as dg
import xarray as xr

from simart_pipeline import versions
from simart_pipeline.partitions import split_key


FORCE_TAG = "simart/force"  # run tag: recompute even what is up to date inside an asset (CKM map tiles)


def code_version(asset: str) -> str:
    return versions.code_version(asset)


def config_dep(asset: str) -> dg.AssetDep:
    """The stage's dependency on its part of the scene config (``assets.config_sources``)."""
    return dg.AssetDep(dg.AssetKey(["scene_config", asset]))


def partition_version(context: dg.AssetExecutionContext, project, asset: str) -> tuple[str, dict]:
    """(data version, the inputs it digests) of the partition being materialised."""
    scene, sub = split_key(context.partition_key)
    plan = project.version_plan(scene)
    return plan.data_version(asset, sub), plan.inputs(asset, sub)


def version_metadata(project, version: str, inputs: dict) -> dict:
    return {"data_version": version, "data_version_inputs": dg.MetadataValue.json(inputs),
            "data_root": project.data_root}


def versioned(context: dg.AssetExecutionContext, project, asset: str, value, metadata: dict) -> dg.Output:
    """``value`` as an Output carrying its data version (also stamped on a dataset's attrs)."""
    version, inputs = partition_version(context, project, asset)
    if isinstance(value, (xr.Dataset, xr.DataTree)):
        value.attrs["data_version"] = version
    elif hasattr(value, "scene_info"):  # paired meshes: a directory whose scene.json says it
        value.scene_info["data_version"] = version
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", dg.BetaWarning)  # Output(data_version=...): stable in use since 1.3
        return dg.Output(value, data_version=dg.DataVersion(version),
                         metadata={**metadata, **version_metadata(project, version, inputs)})


def versioned_result(context: dg.AssetExecutionContext, project, asset: str, metadata: dict) -> dg.MaterializeResult:
    version, inputs = partition_version(context, project, asset)
    return dg.MaterializeResult(data_version=dg.DataVersion(version),
                                metadata={**metadata, **version_metadata(project, version, inputs)})
