"""Code-block error rate (BLER) of an AWGN channel per MCS and code-block size, from tables.

The tables are carried over as data from Sionna SYS (``data/bler_tables/*.json``, simulated
LDPC-coded AWGN links of 5G NR; source and licence in ``data/README.md``). For each MCS they give
the BLER on a grid of SNR (dB) for the code-block sizes 24, 100, 500, 1000 and 2000 bit.

Lookup, as Sionna SYS does it: ``log10 BLER`` is interpolated bilinearly over (code-block size,
SNR dB) (scipy ``RectBivariateSpline`` of degree 1, clamped to the edges of the simulated grid;
exact zeros are carried as ``min log10 - 2`` and set back to 0) onto a fine grid, by default
SNR -5 .. 30 dB in 0.1 dB steps and code-block size 24 .. 8424 bit in steps of 100; a query
takes the nearest grid point (ties to even). Code blocks longer than 2000 bit use the 2000-bit
curve (clamp), which slightly overestimates their BLER (longer LDPC codes have steeper curves).
"""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from typing import Literal

import numpy as np
from scipy.interpolate import RectBivariateSpline

from simart_pipeline.link.mcs import mcs_table as _mcs_table

Category = Literal["pdsch", "pusch"]
_CATEGORY_KEY = {"pusch": 0, "pdsch": 1}   # category numbers used inside the table files
SNR_DB_GRID = (-5.0, 30.01, 0.1)           # start, stop (exclusive), step: dB
CBS_GRID = (24, 8448, 100)                 # start, stop (exclusive), step: bit


def _table_file(category: Category, mcs_table: int):
    return (resources.files("simart_pipeline.link") / "data" / "bler_tables"
            / f"{category.upper()}_table{mcs_table}.json")


def _read_curves(category: Category, mcs_table: int) -> dict[int, tuple]:
    """``{mcs: (cbs [C] bit, snr_db [S], bler [C, S])}`` from one table file."""
    path = _table_file(category, mcs_table)
    if not path.is_file():
        raise ValueError(f"no BLER table for {category.upper()} MCS table {mcs_table} "
                         f"(expected {path})")
    raw = json.loads(path.read_text(encoding="utf-8"))
    try:
        per_mcs = raw["category"][str(_CATEGORY_KEY[category])]["index"][str(mcs_table)]["MCS"]
        curves = {}
        for mcs, entry in per_mcs.items():
            cbs = sorted(entry["CBS"], key=int)
            snr = np.asarray(entry["SNR_db"], dtype=np.float64)
            bler = np.array([entry["CBS"][c]["BLER"] for c in cbs], dtype=np.float64)
            if bler.shape != (len(cbs), snr.size) or np.any(np.diff(snr) <= 0):
                raise ValueError(f"MCS {mcs}: BLER rows do not match the increasing SNR grid")
            if np.any((bler < 0) | (bler > 1)) or not np.isfinite(bler).all():
                raise ValueError(f"MCS {mcs}: BLER values outside [0, 1]")
            curves[int(mcs)] = (np.array([int(c) for c in cbs], dtype=np.float64), snr, bler)
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a BLER table of {category.upper()} MCS table "
                         f"{mcs_table}: missing {exc}") from None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return curves


def _interpolate(cbs, snr_db, bler, cbs_grid, snr_grid) -> np.ndarray:
    """Bilinear interpolation of log10 BLER onto ``[cbs_grid, snr_grid]``, clamped at the edges."""
    zero = bler == 0
    if zero.all():
        return np.zeros((cbs_grid.size, snr_grid.size))
    log_bler = np.log10(np.where(zero, 1.0, bler))
    floor = log_bler[~zero].min()
    log_bler[zero] = floor - 2.0       # zeros: two decades below the smallest measured BLER
    spline = RectBivariateSpline(cbs, snr_db, log_bler, kx=1, ky=1)
    out = 10.0 ** spline(cbs_grid, snr_grid)
    if zero.any():
        out[out < 10.0 ** floor] = 0.0
    return np.clip(out, 0.0, 1.0)


class BlerTable:
    """Interpolated BLER of one (category, MCS table): ``bler(mcs, cbs, sinr)``.

    - ``category``: ``"pdsch"`` (downlink) or ``"pusch"``; ``mcs_table``: TS 38.214 table 1..4;
    - ``snr_db_grid``: ``(start, stop, step)`` dB, ``cbs_grid``: ``(start, stop, step)`` bit: the
      lookup grids (``np.arange`` semantics; defaults as Sionna SYS).

    ``available[m]`` says whether MCS ``m`` has a simulated curve; others look up as NaN.
    """

    def __init__(self, category: Category = "pdsch", mcs_table: int = 1,
                 snr_db_grid: tuple[float, float, float] = SNR_DB_GRID,
                 cbs_grid: tuple[int, int, int] = CBS_GRID):
        if category not in _CATEGORY_KEY:
            raise ValueError(f"category must be 'pdsch' or 'pusch', got {category!r}")
        self.category, self.mcs_table = category, mcs_table
        self.snr_db_grid, self.cbs_grid = tuple(snr_db_grid), tuple(cbs_grid)
        self.snr_db = np.arange(*self.snr_db_grid)
        self.cbs_bits = np.arange(*self.cbs_grid)
        num_mcs = _mcs_table(mcs_table).num_mcs
        curves = _read_curves(category, mcs_table)
        extra = sorted(m for m in curves if m >= num_mcs)
        if extra:
            raise ValueError(f"BLER table {category.upper()} {mcs_table}: MCS {extra} beyond "
                             f"TS 38.214 table {mcs_table}")
        self.available = np.zeros(num_mcs, dtype=bool)
        self.table = np.full((num_mcs, self.cbs_bits.size, self.snr_db.size), np.nan)
        for m, (cbs, snr, bler) in curves.items():
            self.table[m] = _interpolate(cbs, snr, bler, self.cbs_bits.astype(np.float64),
                                         self.snr_db)
            self.available[m] = True
        self.table.flags.writeable = False       # shared through the bler_table cache
        self.available.flags.writeable = False

    def snr_index(self, sinr) -> np.ndarray:
        """Nearest index on the SNR grid of linear SINRs (clamped; NaN and <= 0 give 0)."""
        start, _, step = self.snr_db_grid
        with np.errstate(divide="ignore", invalid="ignore"):
            idx = np.round((10.0 * np.log10(np.asarray(sinr, dtype=np.float64)) - start) / step)
        idx = np.where(np.isnan(idx), 0.0, idx)      # clip maps -inf/+inf to the grid's ends
        return np.clip(idx, 0, self.snr_db.size - 1).astype(np.int64)

    def cbs_index(self, cbs_bits) -> np.ndarray:
        """Nearest index on the code-block-size grid (clamped)."""
        start, _, step = self.cbs_grid
        idx = np.round((np.asarray(cbs_bits, dtype=np.float64) - start) / step)
        return np.clip(idx, 0, self.cbs_bits.size - 1).astype(np.int64)

    def bler(self, mcs, cbs_bits, sinr) -> np.ndarray:
        """BLER of one code block of ``cbs_bits`` bit at MCS ``mcs`` and linear SINR ``sinr``
        (broadcasting; float64). NaN where the MCS has no curve or the SINR is NaN."""
        mcs = np.asarray(mcs, dtype=np.int64)
        if np.any((mcs < 0) | (mcs >= self.available.size)):
            raise ValueError(f"MCS index outside 0..{self.available.size - 1} of table "
                             f"{self.mcs_table}")
        sinr = np.asarray(sinr, dtype=np.float64)
        out = self.table[mcs, self.cbs_index(cbs_bits), self.snr_index(sinr)]
        return np.where(np.isnan(sinr), np.nan, out)


@lru_cache(maxsize=8)
def bler_table(category: Category = "pdsch", mcs_table: int = 1) -> BlerTable:
    """The :class:`BlerTable` with the default grids, built once per process."""
    return BlerTable(category, mcs_table)
