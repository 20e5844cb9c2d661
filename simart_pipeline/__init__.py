"""simart-pipeline: scenes to synchronized multimodal ISAC datasets (Sionna RT + Dagster + Zarr)."""

__version__ = "0.1.0"
