"""Exponential effective SINR mapping (EESM), in float64 with log-sum-exp.

``SINR_eff = -beta ln( (1/N) sum_k exp(-SINR_k / beta) )`` over the N used resource elements, with
a calibration factor ``beta`` per MCS (Brueninger et al., "Link performance models for system
level simulations of broadband radio access systems", PIMRC 2005; 3GPP TR 25.892 Annex A). The
log-mean is evaluated as a log-sum-exp shifted by the smallest SINR, so it never underflows at
high SINR (``exp(-SINR/beta)`` is 0 in float64 beyond ``SINR/beta ~ 745``, in float32 beyond
~103) and keeps the smallest SINR, which dominates the sum.

The beta values per MCS are carried over as data from Sionna SYS (``data/eesm_beta_table.json``,
see ``data/README.md``): MCS tables 1 and 2 of TS 38.214, shared by PDSCH and PUSCH.
"""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources

import numpy as np

BETA_TABLE_FILE = "eesm_beta_table.json"


@lru_cache(maxsize=None)
def _beta_tables() -> dict[int, tuple[float, ...]]:
    path = resources.files("simart_pipeline.link") / "data" / BETA_TABLE_FILE
    raw = json.loads(path.read_text(encoding="utf-8"))
    try:
        tables = {int(k): tuple(float(b) for b in v) for k, v in raw["index"].items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not an EESM beta table ({exc})") from None
    for k, betas in tables.items():
        if not betas or not all(np.isfinite(b) and b > 0 for b in betas):
            raise ValueError(f"{path}: table {k} must hold finite positive beta values")
    return tables


def eesm_beta(mcs_table: int) -> np.ndarray:
    """EESM ``beta`` per MCS index of TS 38.214 MCS table ``mcs_table``: ``[M]`` float64, 1."""
    tables = _beta_tables()
    if mcs_table not in tables:
        raise ValueError(f"no EESM beta values for MCS table {mcs_table}; the table covers "
                         f"{sorted(tables)}")
    return np.asarray(tables[mcs_table], dtype=np.float64)


def effective_sinr(sinr, beta, axis=-1, where=None) -> np.ndarray:
    """EESM effective SINR (linear) of the SINRs ``sinr`` (linear) along ``axis``.

    - ``sinr``: ``[..., K, ...]`` linear SINR per resource element, >= 0;
    - ``beta``: calibration factor, broadcasting against ``sinr`` with ``axis`` removed;
    - ``where``: optional bool mask like ``sinr``: the resource elements that are used (all if
      None). A row with no used element gives NaN.

    Returns float64 with ``axis`` removed. A flat SINR returns itself exactly up to rounding.
    """
    x = np.asarray(sinr, dtype=np.float64)
    axis = axis % x.ndim
    beta = np.asarray(beta, dtype=np.float64)
    reduced = tuple(np.delete(np.array(x.shape), axis))
    b = np.expand_dims(np.broadcast_to(beta, np.broadcast_shapes(reduced, beta.shape)), axis)
    where = (np.ones(x.shape, bool) if where is None
             else np.broadcast_to(np.asarray(where, dtype=bool), x.shape))
    n = where.sum(axis=axis)
    # log-sum-exp shifted by the largest exponent -min(SINR)/beta: every term lies in (0, 1] and
    # the smallest SINR's is exactly 1, so nothing under- or overflows and a flat SINR comes back
    # exactly: SINR_eff = min - beta ln( mean exp(-(SINR - min) / beta) )
    low = np.min(np.where(where, x, np.inf), axis=axis, keepdims=True)
    low = np.where(np.isfinite(low), low, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        terms = np.where(where, np.exp(-(x - low) / b), 0.0)
        out = (np.squeeze(low, axis) - np.squeeze(b, axis)
               * np.log(terms.sum(axis=axis) / np.maximum(n, 1)))
    return np.where(np.asarray(n) > 0, out, np.nan)
