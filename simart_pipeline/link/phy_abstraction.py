"""PHY abstraction of 3GPP-style system-level simulation, as Sionna SYS does it, in numpy.

For one receiver and slot: per-resource-element SINR -> EESM effective SINR with the beta of the
MCS (:mod:`.eesm`) -> BLER of one code block from the AWGN tables at that SINR and the code-block
size of the transport block (:mod:`.bler`, :mod:`.tbs`) -> transport BLER
``TBLER = 1 - (1 - BLER)^C`` over the ``C`` code blocks (every code block must be decoded).
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.link.bler import Category, bler_table
from simart_pipeline.link.eesm import eesm_beta, effective_sinr
from simart_pipeline.link.mcs import mcs_table
from simart_pipeline.link.tbs import transport_block


class PhyAbstraction:
    """EESM, BLER, TBS and TBLER for every MCS of one TS 38.214 MCS table.

    - ``num_re``: ``N_RE`` of the allocation for the TBS (:func:`.tbs.num_re_for_tbs`);
    - ``mcs_table``: 1 or 2 (the EESM beta table covers these); ``category``: BLER tables of the
      ``"pdsch"`` (default) or ``"pusch"``; ``num_layers``: MIMO layers ``v``.

    Per-MCS arrays ``[M]``: ``modulation_order``, ``code_rate``, ``beta``, ``available`` (a BLER
    curve exists), ``transport_block`` (a :class:`.tbs.TransportBlock` of ``[M]`` arrays).
    """

    def __init__(self, num_re: int, mcs_table_index: int = 1, category: Category = "pdsch",
                 num_layers: int = 1):
        self.mcs = mcs_table(mcs_table_index)
        self.beta = eesm_beta(mcs_table_index)
        if self.beta.size != self.mcs.num_mcs:
            raise ValueError(f"EESM beta table {mcs_table_index} has {self.beta.size} values for "
                             f"{self.mcs.num_mcs} MCS indices")
        self.bler_table = bler_table(category, mcs_table_index)
        self.available = np.asarray(self.bler_table.available)
        self.num_re = int(num_re)
        self.transport_block = transport_block(self.mcs.modulation_order,
                                               self.mcs.code_rate_x1024, self.num_re, num_layers)

    @property
    def num_mcs(self) -> int:
        return self.mcs.num_mcs

    def effective_sinr(self, sinr, mcs, axis=-1) -> np.ndarray:
        """EESM effective SINR (linear) of ``sinr`` (linear, resource elements along ``axis``)
        with the beta of MCS ``mcs`` (broadcasting against ``sinr`` without ``axis``)."""
        return effective_sinr(sinr, self.beta[np.asarray(mcs, dtype=np.int64)], axis=axis)

    def effective_sinr_all_mcs(self, sinr, axis=-1) -> np.ndarray:
        """EESM effective SINR for every MCS: ``[..., M]`` (``axis`` of ``sinr`` removed)."""
        x = np.moveaxis(np.asarray(sinr, dtype=np.float64), axis, -1)[..., None, :]
        return effective_sinr(x, self.beta, axis=-1)

    def bler(self, sinr_eff, mcs) -> tuple[np.ndarray, np.ndarray]:
        """``(bler, tbler)`` at effective SINR ``sinr_eff`` (linear) and MCS ``mcs``
        (broadcasting). NaN where the MCS has no BLER curve or ``sinr_eff`` is NaN."""
        mcs = np.asarray(mcs, dtype=np.int64)
        tb = self.transport_block
        bler = self.bler_table.bler(mcs, tb.code_block_size_bits[mcs], sinr_eff)
        return bler, tbler_from_bler(bler, tb.num_code_blocks[mcs])


def tbler_from_bler(bler, num_code_blocks) -> np.ndarray:
    """``1 - (1 - BLER)^C``: the transport block fails if any of its ``C`` code blocks fails
    (independent code-block errors). Computed as ``-expm1(C log1p(-BLER))`` for accuracy at
    small BLER."""
    bler = np.asarray(bler, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return -np.expm1(np.asarray(num_code_blocks) * np.log1p(-bler))
