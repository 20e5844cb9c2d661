from simart_pipeline.assets.checks import ALL_CHECKS
from simart_pipeline.assets.ckm import ckm_layers, ckm_map
from simart_pipeline.assets.config_sources import CONFIG_SOURCES
from simart_pipeline.assets.link import kpis
from simart_pipeline.assets.radio import cirs, radar_frames
from simart_pipeline.assets.scene import osm_extract, paired_meshes, trajectory
from simart_pipeline.assets.sensing import sensor_frames
from simart_pipeline.assets.session import session, session_bag
from simart_pipeline.assets.study import beam_prediction

ALL_ASSETS = [osm_extract, paired_meshes, trajectory, sensor_frames, cirs, radar_frames, kpis, ckm_layers, ckm_map,
              session, session_bag, beam_prediction, *CONFIG_SOURCES]

__all__ = ["ALL_ASSETS", "ALL_CHECKS", "CONFIG_SOURCES"]
