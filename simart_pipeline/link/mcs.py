"""Modulation and coding schemes of the NR PDSCH (3GPP TS 38.214 V17, Tables 5.1.3.1-1 to -4).

Each table maps an MCS index ``I_MCS`` to a modulation order ``Q_m`` (bits per symbol) and a
target code rate ``R x 1024``. The PUSCH without transform precoding uses the same tables
(TS 38.214 6.1.4.1). Reserved indices (retransmission only) are not listed.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class McsTable(NamedTuple):
    """One MCS table: index ``m`` of each array is ``I_MCS = m``."""

    table: int                      # TS 38.214 Table 5.1.3.1-<table>
    modulation_order: np.ndarray    # [M] int64, Q_m, bit per symbol
    code_rate_x1024: np.ndarray     # [M] float64, target code rate R times 1024

    @property
    def code_rate(self) -> np.ndarray:
        """Target code rate ``R`` ([M] float64, 1)."""
        return self.code_rate_x1024 / 1024.0

    @property
    def spectral_efficiency(self) -> np.ndarray:
        """``Q_m R`` ([M] float64, bit per resource element)."""
        return self.modulation_order * self.code_rate

    @property
    def num_mcs(self) -> int:
        return self.modulation_order.size


# 3GPP TS 38.214 Table 5.1.3.1-1: MCS index table 1 for PDSCH (up to 64QAM), I_MCS 0..28.
_TABLE_1 = (
    [2] * 10 + [4] * 7 + [6] * 12,
    [120, 157, 193, 251, 308, 379, 449, 526, 602, 679,
     340, 378, 434, 490, 553, 616, 658,
     438, 466, 517, 567, 616, 666, 719, 772, 822, 873, 910, 948])
# 3GPP TS 38.214 Table 5.1.3.1-2: MCS index table 2 for PDSCH (up to 256QAM), I_MCS 0..27.
_TABLE_2 = (
    [2] * 5 + [4] * 6 + [6] * 9 + [8] * 8,
    [120, 193, 308, 449, 602,
     378, 434, 490, 553, 616, 658,
     466, 517, 567, 616, 666, 719, 772, 822, 873,
     682.5, 711, 754, 797, 841, 885, 916.5, 948])
# 3GPP TS 38.214 Table 5.1.3.1-3: MCS index table 3 for PDSCH (low spectral efficiency), 0..28.
_TABLE_3 = (
    [2] * 15 + [4] * 6 + [6] * 8,
    [30, 40, 50, 64, 78, 99, 120, 157, 193, 251, 308, 379, 449, 526, 602,
     340, 378, 434, 490, 553, 616,
     438, 466, 517, 567, 616, 666, 719, 772])
# 3GPP TS 38.214 Table 5.1.3.1-4: MCS index table 4 for PDSCH (up to 1024QAM), I_MCS 0..26.
_TABLE_4 = (
    [2] * 3 + [4] * 3 + [6] * 9 + [8] * 8 + [10] * 4,
    [120, 193, 449,
     378, 490, 616,
     466, 517, 567, 616, 666, 719, 772, 822, 873,
     682.5, 711, 754, 797, 841, 885, 916.5, 948,
     805.5, 853, 900.5, 948])
_TABLES = {1: _TABLE_1, 2: _TABLE_2, 3: _TABLE_3, 4: _TABLE_4}


def mcs_table(table: int) -> McsTable:
    """The PDSCH MCS table ``table`` (1..4) of TS 38.214 5.1.3.1."""
    if table not in _TABLES:
        raise ValueError(f"MCS table {table!r}: TS 38.214 defines tables 1, 2, 3, 4")
    qm, r = _TABLES[table]
    return McsTable(table, np.asarray(qm, dtype=np.int64), np.asarray(r, dtype=np.float64))
