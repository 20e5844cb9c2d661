"""Recordings (CSV files and ROS bags): their formats by file name and the time origins of bags."""

from __future__ import annotations

from pathlib import Path

# Recording formats by file name: a CSV, a ROS1 bag, a rosbag2 storage file, or (no suffix) a rosbag2
# directory with its metadata.yaml (docs/sensor-plugin.md).
RECORDING_FORMATS = {".csv": "csv", ".bag": "ros1", ".db3": "rosbag2", ".mcap": "rosbag2", "": "rosbag2"}


BAG_TIME_ORIGINS = ("first_message", "bag_start")


def recording_format(path: str) -> str:
    """``csv``, ``ros1`` or ``rosbag2`` from a recording's file name; ValueError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in RECORDING_FORMATS:
        raise ValueError(f"{path!r}: unknown recording format {suffix!r}; expected .csv, .bag (ROS1), "
                         ".db3 or .mcap (rosbag2 storage file) or a rosbag2 directory (no suffix)")
    return RECORDING_FORMATS[suffix]


def _bag_time_origin(v):
    if v is None or (isinstance(v, int) and not isinstance(v, bool)) or v in BAG_TIME_ORIGINS:
        return v
    raise ValueError(f"expected {' or '.join(BAG_TIME_ORIGINS)} or an integer stamp in ns, got {v!r}")
