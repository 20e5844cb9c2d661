"""Case studies built on the datasets (no Dagster)."""
