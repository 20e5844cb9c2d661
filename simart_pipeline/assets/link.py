"""Link-level assets: beams, SINR with interference and the PHY abstraction, from the CIRs."""

import dagster as dg
import numpy as np
import xarray as xr

from simart_pipeline import provenance
from simart_pipeline.link.kpis import compute_kpis
from simart_pipeline.partitions import scene_weather, split_key
from simart_pipeline.resources import ProjectResource


@dg.asset(partitions_def=scene_weather, code_version="1", group_name="radio")
def kpis(context: dg.AssetExecutionContext, project: ProjectResource, cirs: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Beam gains over the DFT codebook, best beam, SINR with interference, Shannon rate."""
    scene, _ = split_key(context.partition_key)
    cfg = project.config(scene)
    ds = compute_kpis(cirs.load(), cfg)
    ds.attrs.update(provenance.attrs(cfg, "kpis"))
    meta = {"time_steps": ds.sizes["time"]}
    if "sinr_db" in ds:
        sinr = ds["sinr_db"].values
        if np.isfinite(sinr).any():
            meta.update(sinr_db_median=float(np.nanmedian(sinr)), sinr_db_min=float(np.nanmin(sinr)),
                        sinr_db_max=float(np.nanmax(sinr)))
    return dg.Output(ds, metadata=meta)
