"""Link-level assets: beams, SINR with interference and the PHY abstraction, from the CIRs."""

import dagster as dg
import numpy as np
import xarray as xr

from simart_pipeline import provenance, stores
from simart_pipeline.link.beams import scene_codebook_weights
from simart_pipeline.link.kpis import compute_kpis
from simart_pipeline.assets.versioning import code_version, config_dep, versioned
from simart_pipeline.partitions import from_weather_group, scene_weather, split_key
from simart_pipeline.radio.materials import WEATHER_GROUP
from simart_pipeline.resources import ProjectResource


@dg.asset(partitions_def=scene_weather, code_version=code_version("kpis"),
          deps=[config_dep("kpis")], group_name="radio",
          ins={"cirs": dg.AssetIn(partition_mapping=from_weather_group)})
def kpis(context: dg.AssetExecutionContext, project: ProjectResource,
         cirs: xr.Dataset) -> dg.Output[xr.Dataset]:
    """Beam gains, best beam, serving cell, SINR with interference, EESM, BLER, MCS, TBS, rates."""
    scene, weather = split_key(context.partition_key)
    cfg = project.config(scene)
    weights = None
    if cfg.codebook.path is not None:
        weights = scene_codebook_weights(cfg, cirs["tx_ant_position_m"].values,
                                         project.scene_dir(scene))
    source = str(stores.store_path(project.data_root, "cirs", scene, WEATHER_GROUP[weather]))
    ds = compute_kpis(cirs.load(), cfg, codebook_weights=weights, source=source)
    ds.attrs.update(provenance.attrs(cfg, "kpis"))
    meta = {"time_steps": ds.sizes["time"], "served_fraction": float(ds["rx_served"].mean())}
    for name in ("sinr_db", "effective_sinr_db"):
        v = ds[name].values
        if np.isfinite(v).any():
            meta[f"{name}_median"] = float(np.nanmedian(v))
    if ds["rx_served"].any():
        meta["mcs_rate_mbps_mean"] = float(ds["mcs_rate_bps"].where(ds["rx_served"]).mean()) / 1e6
    return versioned(context, project, "kpis", ds, meta)
