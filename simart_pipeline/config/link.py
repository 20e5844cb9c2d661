"""Link and system level: the receiver's noise, the codebook, resource allocation and link adaptation."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from simart_pipeline.config.base import Vec2, _inside_scene_dir, _Model


class Receiver(_Model):
    noise_figure_db: float = Field(7.0, ge=0)
    temperature_k: float = Field(290.0, gt=0)


class Codebook(_Model):
    """DFT codebook of the base-station UPA: oversampling per axis (1 = orthogonal beams).

    ``visible_only`` drops the grid beams whose direction cosines lie outside the unit circle
    (no real direction; 12 of the 64 beams of an 8 x 8 half-wavelength array). ``path`` names a
    ``.npy`` file of complex precoders ``[num_beams, num_tx_antennas]`` (Sionna antenna order,
    relative to the scene directory) that replaces the DFT grid.
    """

    oversampling: int = Field(1, ge=1, le=8)
    visible_only: bool = False
    path: str | None = None
    _inside = field_validator("path")(classmethod(
        lambda cls, v: v if v is None else _inside_scene_dir(v, "the codebook")))


class Link(_Model):
    """Link and system level (docs/link-level.md): resource allocation, TBS overheads, MCS table,
    link adaptation. Downlink: base stations transmit the PDSCH to the platforms."""

    first_resource_block: int = Field(0, ge=0, description="first allocated resource block")
    num_allocated_resource_blocks: int | None = Field(
        None, ge=1, description="allocated resource blocks; None: from first_resource_block to "
                                "the carrier's last")
    dmrs_re_per_prb: int = Field(12, ge=0, le=72, description="DMRS resource elements per PRB "
                                 "and slot, N_DMRS^PRB of TS 38.214 5.1.3.2")
    overhead_re_per_prb: Literal[0, 6, 12, 18] = Field(
        0, description="xOverhead, N_oh^PRB of TS 38.214 5.1.3.2")
    mcs_table: Literal[1, 2] = Field(
        1, description="TS 38.214 Table 5.1.3.1-1 (64QAM) or -2 (256QAM); the EESM beta table "
                       "covers these two")
    bler_target: float = Field(0.1, gt=0, lt=1, description="transport BLER target of link "
                                                              "adaptation")
    link_adaptation: Literal["inner_loop", "outer_loop"] = "inner_loop"
    olla_delta_up_db: float = Field(1.0, gt=0, description="outer loop: offset step on a NACK")
    olla_offset_limits_db: Vec2 = (-20.0, 20.0)

    @model_validator(mode="after")
    def _limits(self):
        if self.olla_offset_limits_db[0] > self.olla_offset_limits_db[1]:
            raise ValueError("olla_offset_limits_db: the lower limit exceeds the upper one")
        return self
