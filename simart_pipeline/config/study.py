"""The beam-prediction case study (``docs/beam-study.md``): which base station, camera and UAV it
uses, how flights are split, and the detector's and classifier's settings."""

from __future__ import annotations

from pydantic import Field

from simart_pipeline.config.base import _Model


class BeamStudy(_Model):
    """Vision- and position-aided beam prediction at one base station for one UAV.

    Each leg of the UAV's waypoint trajectory (waypoint k to k + 1) is one flight; the flights are
    split into training and test sets, never the frames of one flight."""

    base_station: str = Field(description="the base station whose codebook beams are the labels")
    camera: str = Field(description="a camera of that base station that sees the UAV's airspace")
    platform: str = Field(description="the UAV: a platform with a waypoint trajectory and a GPS")
    gps: str = Field("gps", description="the platform's GPS sensor")
    test_fraction: float = Field(0.25, gt=0, lt=1, description="share of the flights held out for testing")
    seed: int = Field(0, description="seed of the flight split, the detector's and the classifier's draws")
    match_margin_px: float = Field(
        4.0, ge=0, description="a detection is correct when its box centre lies in the UAV's visible "
        "ground-truth box grown by this margin on every side")
    classifier_trees: int = Field(300, ge=10, le=5000, description="trees of the random-forest beam classifier")
