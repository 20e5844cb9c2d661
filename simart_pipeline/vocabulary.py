"""The ground floor: names and constants every layer shares. It imports nothing of the project.

- weathers: the static weather partitions;
- semantic classes of the visual mesh, camera images and LiDAR returns, with their CF flag attrs;
- interaction kinds of a ray-traced path (Sionna RT's ``InteractionType`` values), with flag attrs;
- the names of the axis and quaternion components of every stored vector and rotation;
- physical constants, each with its source.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag
from typing import Literal

import numpy as np
import scipy.constants

# --- weathers -------------------------------------------------------------------------------------
WEATHERS: tuple[str, ...] = ("sunny", "rainy", "night")
WeatherName = Literal["sunny", "rainy", "night"]  # the schema's type of a weather name


# --- radio materials ------------------------------------------------------------------------------
# ITU-R P.2040 materials that Sionna RT's ITURadioMaterial knows, and the project's own (water by
# Klein & Swift 1977, rain-soaked facades by CRIM mixing: their models are in radio/materials.py).
ITU_MATERIALS: tuple[str, ...] = (
    "vacuum", "concrete", "brick", "plasterboard", "wood", "glass", "ceiling_board", "chipboard",
    "plywood", "marble", "floorboard", "metal", "very_dry_ground", "medium_dry_ground", "wet_ground",
)
CUSTOM_MATERIAL_NAMES: tuple[str, ...] = ("sea_water", "fresh_water", "wet_concrete", "wet_brick")
RADIO_MATERIALS: tuple[str, ...] = ITU_MATERIALS + CUSTOM_MATERIAL_NAMES

# What each weather does to the radio materials, by default (a scene's ``materials.rain`` replaces
# the rainy row); sunny and night keep the dry ones. Weathers with equal rows share radio work.
WEATHER_MATERIALS: dict[str, dict[str, str]] = {
    "sunny": {},
    "night": {},
    "rainy": {"medium_dry_ground": "wet_ground", "very_dry_ground": "wet_ground",
              "concrete": "wet_concrete", "brick": "wet_brick"},
}


# --- semantic classes -----------------------------------------------------------------------------
class SemanticClass(IntEnum):
    """Per-face semantic class of the visual mesh (and of camera segmentation images)."""

    UNLABELED = 0
    GROUND = 1
    ROAD = 2
    BUILDING = 3
    VEGETATION = 4
    WATER = 5
    VEHICLE = 6
    UAV = 7          # actor bodies (scene/actors.py): one instance id per actor
    PEDESTRIAN = 8


# Instance ids of actors: ACTOR_INSTANCE_ID_BASE + the actor's index (platforms in config order,
# then static actors). Far above any OSM id (< 2**40), so a map feature and an actor never share one.
ACTOR_INSTANCE_ID_BASE = 1 << 48

SEMANTIC_CLASS_NAMES: tuple[str, ...] = tuple(c.name.lower() for c in SemanticClass)


def _cf_flags(enum, key: str = "flag_values") -> dict:
    """CF flag attrs of an enumeration: ``flag_values`` (or ``flag_masks`` for bit flags) and
    ``flag_meanings``, the member names in lower case."""
    return {key: np.array([int(m) for m in enum], np.uint8),
            "flag_meanings": " ".join(m.name.lower() for m in enum)}


def semantic_flag_attrs() -> dict:
    """CF ``flag_values`` / ``flag_meanings`` of :class:`SemanticClass`, for every label variable."""
    return _cf_flags(SemanticClass)


# --- interaction kinds ----------------------------------------------------------------------------
class InteractionKind(IntEnum):
    """What happens to a path at one bounce: Sionna RT 2's ``InteractionType`` values, bit flags
    (``NONE`` after a path's last bounce; a path with only ``NONE`` is the line of sight)."""

    NONE = 0
    SPECULAR = 1
    DIFFUSE = 2
    REFRACTION = 4
    DIFFRACTION = 8


def interaction_flag_attrs() -> dict:
    """CF ``flag_values`` / ``flag_meanings`` of :class:`InteractionKind`."""
    return _cf_flags(InteractionKind)


class LinkStatus(IntFlag):
    """Why a radio link (base station -> platform, one instant) is not usable; 0: usable."""

    NO_PATH = 1
    RX_INSIDE_BUILDING = 2
    RX_NEAR_TX = 4


def link_status_flag_attrs() -> dict:
    """CF ``flag_masks`` / ``flag_meanings`` of :class:`LinkStatus`."""
    return _cf_flags(LinkStatus, "flag_masks")


# --- axes and quaternions -------------------------------------------------------------------------
AXES = ["x", "y", "z"]                 # components of every stored vector (dim ``axis``)
QUATERNION_COMPONENTS = ["x", "y", "z", "w"]  # scalar last, as ROS geometry_msgs/Quaternion
QUATERNION_ORDER = " ".join(QUATERNION_COMPONENTS)

# --- physical constants ---------------------------------------------------------------------------
# Standard acceleration of gravity g_n: 3rd CGPM (1901), ISO 80000-3; the project has no gravity model.
STANDARD_GRAVITY_MPS2 = 9.80665
# Exact in the SI since 2019 (CODATA, via scipy.constants).
SPEED_OF_LIGHT_MPS = scipy.constants.speed_of_light
BOLTZMANN_J_PER_K = scipy.constants.Boltzmann
