"""Partitions: a dynamic ``scene`` dimension, crossed with the static weathers and CKM tiles."""

import warnings

import dagster as dg

from simart_pipeline.config import MAX_TILES_PER_AXIS
from simart_pipeline.vocabulary import WEATHERS
from simart_pipeline.ckm.grid import tile_key

scene_partitions = dg.DynamicPartitionsDefinition(name="scene")
weather_partitions = dg.StaticPartitionsDefinition(list(WEATHERS))
# A fixed static tiling; each scene's grid says how many of these tiles it uses (ckm.tiles).
tile_partitions = dg.StaticPartitionsDefinition(
    [tile_key(r, c) for r in range(MAX_TILES_PER_AXIS) for c in range(MAX_TILES_PER_AXIS)])

scene_weather = dg.MultiPartitionsDefinition({"scene": scene_partitions, "weather": weather_partitions})
scene_tile = dg.MultiPartitionsDefinition({"scene": scene_partitions, "tile": tile_partitions})

# A (scene, weather) or (scene, tile) partition depends on its scene's partition.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", dg.BetaWarning)  # stable in use since Dagster 1.4
    from_scene = dg.MultiToSingleDimensionPartitionMapping(partition_dimension_name="scene")


def split_key(key: str) -> tuple[str, str | None]:
    """(scene, weather-or-tile) of a partition key; the second is None for scene partitions."""
    if isinstance(key, dg.MultiPartitionKey):
        kb = key.keys_by_dimension
        return kb["scene"], kb.get("weather", kb.get("tile"))
    return str(key), None
