"""Transport block size (3GPP TS 38.214 V17 5.1.3.2) and code-block segmentation (TS 38.212 V17
5.2.2, LDPC base graph per 7.2.2), vectorised and in exact integer arithmetic.

The intermediate number of information bits ``N_info = N_RE R Q_m v`` is kept as the integer
``N_RE Q_m v (2048 R)`` (every tabulated ``R x 1024`` is a multiple of 1/2), so every floor,
rounding and comparison of the standard is exact; no float32 rounding can move a TBS.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# 3GPP TS 38.214 Table 5.1.3.2-1: TBS for N_info <= 3824.
TBS_TABLE = np.array([
    24, 32, 40, 48, 56, 64, 72, 80, 88, 96, 104, 112, 120, 128, 136, 144, 152, 160, 168, 176,
    184, 192, 208, 224, 240, 256, 272, 288, 304, 320, 336, 352, 368, 384, 408, 432, 456, 480,
    504, 528, 552, 576, 608, 640, 672, 704, 736, 768, 808, 848, 888, 928, 984, 1032, 1064, 1128,
    1160, 1192, 1224, 1256, 1288, 1320, 1352, 1416, 1480, 1544, 1608, 1672, 1736, 1800, 1864,
    1928, 2024, 2088, 2152, 2216, 2280, 2408, 2472, 2536, 2600, 2664, 2728, 2792, 2856, 2976,
    3104, 3240, 3368, 3496, 3624, 3752, 3824], dtype=np.int64)

MAX_RE_PER_PRB = 156  # TS 38.214 5.1.3.2 step 1: N_RE = min(156, N'_RE) n_PRB


class TransportBlock(NamedTuple):
    """Arrays of one shape (the broadcast of the inputs), all int64 except ``n_info``."""

    tbs_bits: np.ndarray             # transport block size A, bit (information bits per slot)
    num_code_blocks: np.ndarray      # C
    code_block_size_bits: np.ndarray  # K' = B'/C, bit (information + CRC bits per code block)
    ldpc_base_graph: np.ndarray      # 1 or 2 (TS 38.212 7.2.2)
    tb_crc_bits: np.ndarray          # L_TB: 24 if A > 3824 else 16 (TS 38.212 7.2.1)
    cb_crc_bits: np.ndarray          # L: 24 when C > 1 else 0 (TS 38.212 5.2.2)
    n_info: np.ndarray               # N_info = N_RE R Q_m v, bit (float64, exact)


def num_re_for_tbs(num_prb, num_symbols, dmrs_re_per_prb, overhead_re_per_prb=0) -> np.ndarray:
    """``N_RE = min(156, 12 N_symb - N_DMRS - N_oh) n_PRB`` (TS 38.214 5.1.3.2 step 1), int64."""
    per_prb = (12 * np.asarray(num_symbols, dtype=np.int64) - np.asarray(dmrs_re_per_prb)
               - np.asarray(overhead_re_per_prb))
    if np.any(per_prb < 1):
        raise ValueError("12 * num_symbols - dmrs_re_per_prb - overhead_re_per_prb must be >= 1")
    return np.minimum(MAX_RE_PER_PRB, per_prb) * np.asarray(num_prb, dtype=np.int64)


def _floor_log2(x: np.ndarray) -> np.ndarray:
    """``floor(log2(x))`` of positive integers below 2**53, exactly (via the float exponent)."""
    return np.frexp(x.astype(np.float64))[1].astype(np.int64) - 1


def _ceil_div(a, b):
    return -(-a // b)


def transport_block(modulation_order, code_rate_x1024, num_re, num_layers=1) -> TransportBlock:
    """TBS and code-block segmentation of one PDSCH/PUSCH transport block.

    - ``modulation_order``: ``Q_m``, bit per symbol (int, broadcasts);
    - ``code_rate_x1024``: target code rate ``R x 1024`` of the MCS table (multiples of 1/2);
    - ``num_re``: ``N_RE``, resource elements for the TBS (:func:`num_re_for_tbs`), >= 1;
    - ``num_layers``: ``v``, MIMO layers.

    Steps of TS 38.214 5.1.3.2: ``N_info <= 3824``: quantise with ``n = max(3, floor(log2
    N_info) - 6)`` and take the smallest Table 5.1.3.2-1 entry not below ``N'_info``; otherwise
    ``n = floor(log2(N_info - 24)) - 5``, ``N'_info = max(3840, 2^n round((N_info - 24) / 2^n))``
    (ties up) and ``TBS = 8 C ceil((N'_info + 24) / (8 C)) - 24`` with ``C`` code blocks of at
    most 3816 (R <= 1/4) or 8424 information bits. Segmentation per TS 38.212 5.2.2 with the
    LDPC base graph of 7.2.2 (graph 2 if ``A <= 292``, or ``A <= 3824`` and ``R <= 0.67``, or
    ``R <= 0.25``); ``K' = (A + L_TB) / C + L``.
    """
    qm = np.asarray(modulation_order, dtype=np.int64)
    r2048 = np.asarray(code_rate_x1024, dtype=np.float64) * 2.0
    if not np.array_equal(r2048, np.round(r2048)):
        raise ValueError("code_rate_x1024 must be a multiple of 1/2 (TS 38.214 MCS tables)")
    r2048 = r2048.astype(np.int64)
    n_re = np.asarray(num_re, dtype=np.int64)
    v = np.asarray(num_layers, dtype=np.int64)
    if np.any(n_re < 1) or np.any(qm < 1) or np.any(r2048 < 1) or np.any(v < 1):
        raise ValueError("num_re, modulation_order, code_rate_x1024 and num_layers must be > 0")
    qm, r2048, n_re, v = np.broadcast_arrays(qm, r2048, n_re, v)
    num = n_re * qm * v * r2048                 # N_info * 2048, exact
    unit = np.int64(2048)

    # Step 3: N_info <= 3824.
    small = num <= 3824 * unit
    n_s = np.maximum(3, _floor_log2(np.maximum(num, 1)) - 11 - 6)
    nq_small = np.maximum(24, (num // (unit << n_s)) << n_s)
    tbs_small = TBS_TABLE[np.minimum(np.searchsorted(TBS_TABLE, nq_small), TBS_TABLE.size - 1)]

    # Step 4: N_info > 3824 (the small branch's values are computed too, then discarded).
    num24 = np.maximum(num - 24 * unit, 1)
    n_l = np.maximum(_floor_log2(num24) - 11 - 5, 0)
    step = unit << n_l                          # 2^n in units of 1/2048
    nq_large = np.maximum(3840, ((2 * num24 + step) // (2 * step)) << n_l)   # ties round up
    low_rate = r2048 <= 512                     # R <= 1/4
    c_tbs = np.where(low_rate, _ceil_div(nq_large + 24, 3816),
                     np.where(nq_large > 8424, _ceil_div(nq_large + 24, 8424), 1))
    tbs_large = 8 * c_tbs * _ceil_div(nq_large + 24, 8 * c_tbs) - 24
    tbs = np.where(small, tbs_small, tbs_large)

    # TS 38.212: CRC, base graph, segmentation.
    rate = r2048 / 2048.0
    l_tb = np.where(tbs > 3824, 24, 16)
    bg2 = (tbs <= 292) | ((tbs <= 3824) & (rate <= 0.67)) | (rate <= 0.25)
    k_cb = np.where(bg2, 3840, 8448)
    b = tbs + l_tb
    single = b <= k_cb
    c = np.where(single, 1, _ceil_div(b, k_cb - 24))
    l_cb = np.where(single, 0, 24)
    b_prime = b + c * l_cb
    if np.any(b_prime % c):
        raise AssertionError("TBS + CRC not divisible by the number of code blocks")  # by design
    return TransportBlock(tbs, c, b_prime // c, np.where(bg2, 2, 1), l_tb, l_cb, num / 2048.0)
