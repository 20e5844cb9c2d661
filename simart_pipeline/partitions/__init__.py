"""Partitions: a dynamic ``scene`` dimension, crossed with the static weathers and CKM tiles."""

import warnings

import dagster as dg

from simart_pipeline.config import MAX_TILES_PER_AXIS
from simart_pipeline.radio.materials import WEATHER_GROUP, WEATHER_GROUPS
from simart_pipeline.vocabulary import WEATHERS
from simart_pipeline.ckm.grid import tile_key

scene_partitions = dg.DynamicPartitionsDefinition(name="scene")
weather_partitions = dg.StaticPartitionsDefinition(list(WEATHERS))
# A fixed static tiling; each scene's grid says how many of these tiles it uses (ckm.tiles).
tile_partitions = dg.StaticPartitionsDefinition(
    [tile_key(r, c) for r in range(MAX_TILES_PER_AXIS) for c in range(MAX_TILES_PER_AXIS)])

scene_weather = dg.MultiPartitionsDefinition({"scene": scene_partitions, "weather": weather_partitions})
# Radio work (the CIRs) is partitioned by weather group: the weathers that share radio materials
# (radio.materials.WEATHER_GROUP: sunny and night share the dry group "sunny", rain is "rainy").
weather_group_partitions = dg.StaticPartitionsDefinition(list(WEATHER_GROUPS))
scene_weather_group = dg.MultiPartitionsDefinition({"scene": scene_partitions,
                                                    "weather_group": weather_group_partitions})
scene_tile = dg.MultiPartitionsDefinition({"scene": scene_partitions, "tile": tile_partitions})

# A (scene, weather) or (scene, tile) partition depends on its scene's partition; a (scene, weather)
# partition on its weather group's radio partition (night reads sunny's CIRs, visibly in the lineage).
with warnings.catch_warnings():
    warnings.simplefilter("ignore", dg.BetaWarning)  # stable in use since Dagster 1.4
    from_scene = dg.MultiToSingleDimensionPartitionMapping(partition_dimension_name="scene")
    from_weather_group = dg.MultiPartitionMapping({
        "scene": dg.DimensionPartitionMapping("scene", dg.IdentityPartitionMapping()),
        "weather_group": dg.DimensionPartitionMapping("weather", dg.StaticPartitionMapping(
            {g: [w for w in WEATHERS if WEATHER_GROUP[w] == g] for g in WEATHER_GROUPS})),
    })


def split_key(key: str) -> tuple[str, str | None]:
    """(scene, weather, weather group or tile) of a partition key; the second is None for scene
    partitions."""
    if isinstance(key, dg.MultiPartitionKey):
        kb = key.keys_by_dimension
        return kb["scene"], next(v for k, v in kb.items() if k != "scene")
    return str(key), None
