"""Radio: materials per semantic class and OSM tag, ray-tracing settings, OFDM numerology."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from simart_pipeline.config.base import _Model
from simart_pipeline.vocabulary import RADIO_MATERIALS, WEATHER_MATERIALS


class Materials(_Model):
    """Radio material per semantic class, and OSM tag rules that override it.

    Materials are :data:`simart_pipeline.vocabulary.RADIO_MATERIALS` names (ITU-R P.2040-3
    Table 3, valid 1-100 GHz, plus water and wet facades). ``tags`` maps an OSM key to a mapping
    of its values to materials; it is merged over :data:`DEFAULT_TAG_MATERIALS` (a key given here
    replaces single values, not the whole key). A feature takes the material of the first rule
    whose key and value it carries (keys in the order of the merged mapping), else its class's.
    """

    building: str = "concrete"
    road: str = "concrete"
    ground: str = "medium_dry_ground"
    vegetation: str = "medium_dry_ground"
    water: str = "fresh_water"
    thickness_m: float = Field(0.2, gt=0)
    tags: dict[str, dict[str, str]] = Field(default_factory=dict)
    rain: dict[str, str] = Field(
        default_factory=lambda: dict(WEATHER_MATERIALS["rainy"]),
        description="what rain does: each dry material -> the wet material that replaces it in the rainy "
        "radio scene (default: wet ground and rain-soaked facades); sunny and night keep the dry ones")

    @model_validator(mode="after")
    def _known(self):
        for key in ("building", "road", "ground", "vegetation", "water"):
            if getattr(self, key) not in RADIO_MATERIALS:
                raise ValueError(f"{key}: unknown radio material {getattr(self, key)!r}; "
                                 f"known: {', '.join(RADIO_MATERIALS)}")
        for dry, wet in self.rain.items():
            for name in (dry, wet):
                if name not in RADIO_MATERIALS:
                    raise ValueError(f"rain.{dry}: unknown radio material {name!r}; known: {', '.join(RADIO_MATERIALS)}")
        for key, values in self.tags.items():
            for value, mat in values.items():
                if mat not in RADIO_MATERIALS:
                    raise ValueError(f"tags.{key}.{value}: unknown radio material {mat!r}; "
                                     f"known: {', '.join(RADIO_MATERIALS)}")
        return self

    def weather_table(self) -> dict[str, dict[str, str]]:
        """Weather -> {material: the one that replaces it}: the defaults with this scene's rain."""
        return {**{w: dict(v) for w, v in WEATHER_MATERIALS.items()}, "rainy": dict(self.rain)}

    def tag_rules(self) -> dict[str, dict[str, str]]:
        """:data:`DEFAULT_TAG_MATERIALS` with this config's ``tags`` merged over it."""
        merged = {k: dict(v) for k, v in DEFAULT_TAG_MATERIALS.items()}
        for key, values in self.tags.items():
            merged.setdefault(key, {}).update(values)
        return merged


# OSM tag values to radio materials. P.2040-3 has no asphalt or stone: asphalt and paved surfaces
# use concrete (the usual proxy), natural stone uses marble (its only stone); loose surfaces use
# the ground classes. Water bodies use the Debye water models of radio.materials.
DEFAULT_TAG_MATERIALS: dict[str, dict[str, str]] = {
    "building:material": {
        "brick": "brick", "concrete": "concrete", "reinforced_concrete": "concrete",
        "cement_block": "concrete", "plaster": "concrete", "glass": "glass", "mirror": "glass",
        "metal": "metal", "steel": "metal", "aluminium": "metal", "copper": "metal", "gold": "metal",
        "wood": "wood", "timber_framing": "wood", "stone": "marble", "sandstone": "marble",
        "limestone": "marble", "granite": "marble", "marble": "marble"},
    "surface": {
        "asphalt": "concrete", "concrete": "concrete", "concrete:plates": "concrete",
        "concrete:lanes": "concrete", "paved": "concrete", "paving_stones": "concrete",
        "sett": "marble", "cobblestone": "marble", "unhewn_cobblestone": "marble", "stone": "marble",
        "metal": "metal", "wood": "wood", "gravel": "very_dry_ground", "fine_gravel": "very_dry_ground",
        "sand": "very_dry_ground", "unpaved": "medium_dry_ground", "compacted": "medium_dry_ground",
        "dirt": "medium_dry_ground", "earth": "medium_dry_ground", "ground": "medium_dry_ground",
        "grass": "medium_dry_ground", "mud": "wet_ground"},
    "natural": {"water": "fresh_water", "bay": "sea_water", "strait": "sea_water", "wetland": "wet_ground"},
    "water": {"lagoon": "sea_water", "sea": "sea_water"},
    "landuse": {"reservoir": "fresh_water", "basin": "fresh_water"},
}


class RayTracing(_Model):
    """Sionna RT PathSolver settings (always run in its deterministic mode, with ``seed``)."""

    max_depth: int = Field(3, ge=0, le=10)
    samples_per_src: int = Field(100_000, ge=1_000, le=100_000_000)
    max_num_paths_per_src: int = Field(1_000_000, ge=1)
    los: bool = True
    specular_reflection: bool = True
    diffuse_reflection: bool = False
    # Diffraction and refraction are on by default because the run-time/error front chose them
    # (benchmarks/raytracing_front, docs/ray-tracing.md): LoS and specular reflection alone leave 12
    # of the demo's 80 links without a path and 27 / 39 % of its outdoor CKM cells without a value
    # from one station or the other (shadowed streets); wedge and edge diffraction reach every link
    # and cell for 1.34x the trace time. Refraction (transmission through walls and windows of
    # Sionna's ITU materials) carries much of the power behind buildings: without it the one-pass
    # CKM is 7.9 dB low in the median cell of the street canyon and 27 dB off at p95 on Munich, for
    # 1.2-2x the CKM's trace time (docs/ckm-one-pass.md, "Session 28"). Diffuse reflection needs
    # materials that scatter (Sionna's ITU materials do not).
    refraction: bool = True
    diffraction: bool = True
    edge_diffraction: bool = True
    seed: int = 42
    max_receivers_per_call: int = Field(2000, ge=1)
    max_solver_memory_gib: float = Field(
        4.0, gt=0, description="receivers per PathSolver call are capped so that the deterministic "
        "solver's working set (about 48 B x depth x samples x receivers, measured) stays below this")
    store_interaction_points: bool = Field(
        False, description="store every path's interaction points (time x link x depth x path x 3)")
    actor_max_excess_path_m: float | None = Field(
        200.0, gt=0, description="an actor is left out of a link's trace at an instant when every "
        "path via its bounding sphere is longer than the direct tx-rx distance by more than this "
        "(m); None keeps every actor in every trace (docs/actors.md: the rule and its measured error)")


class Ofdm(_Model):
    """OFDM numerology (3GPP TS 38.211 4.2): subcarrier spacing 15 * 2**mu kHz."""

    carrier_frequency_hz: float = Field(3.5e9, gt=1e8, lt=1e12)
    numerology_mu: int = Field(1, ge=0, le=6)
    num_resource_blocks: int = Field(51, ge=1, le=275)
    num_ofdm_symbols: int = Field(14, ge=1)
    cyclic_prefix: Literal["normal", "extended"] = "normal"

    @model_validator(mode="after")
    def _cyclic_prefix(self):
        # TS 38.211 Table 4.2-1: the extended cyclic prefix exists only for mu = 2; a slot holds
        # 14 OFDM symbols with the normal prefix and 12 with the extended one (Table 4.3.2-1/-2).
        per_slot = 12 if self.cyclic_prefix == "extended" else 14
        if self.cyclic_prefix == "extended" and self.numerology_mu != 2:
            raise ValueError("cyclic_prefix: 'extended' exists only for numerology_mu 2 (60 kHz)")
        if self.num_ofdm_symbols > per_slot:
            raise ValueError(f"num_ofdm_symbols: at most {per_slot} per slot with the "
                             f"{self.cyclic_prefix} cyclic prefix")
        return self

    @property
    def subcarrier_spacing_hz(self) -> float:
        return 15e3 * 2 ** self.numerology_mu

    @property
    def num_subcarriers(self) -> int:
        return 12 * self.num_resource_blocks  # TS 38.211: 12 subcarriers per resource block

    @property
    def bandwidth_hz(self) -> float:
        return self.num_subcarriers * self.subcarrier_spacing_hz
