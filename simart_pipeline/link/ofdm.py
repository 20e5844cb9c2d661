"""OFDM channel frequency response and thermal noise, in float64 / complex128.

The path coefficients ``a`` follow Sionna RT's convention (``Paths.a``, synthetic array): they
exclude the propagation phase, so a line-of-sight path has phase 0 at the array centre and the
full carrier phase ``exp(-j 2 pi f_c tau)`` is applied here, together with the baseband offset.
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.config import Link, Ofdm
from simart_pipeline.vocabulary import BOLTZMANN_J_PER_K


def subcarrier_offsets_hz(ofdm: Ofdm) -> np.ndarray:
    """Baseband offsets of the subcarriers from the carrier: ``[num_subcarriers]``, Hz, float64.

    The grid is symmetric about the carrier, ``f_k = (k - (K - 1) / 2) * subcarrier_spacing_hz``
    for ``k = 0 .. K-1``, so its mean is exactly 0 (for even K no subcarrier sits on the carrier).
    """
    k = np.arange(ofdm.num_subcarriers, dtype=np.float64)
    return (k - (ofdm.num_subcarriers - 1) / 2.0) * float(ofdm.subcarrier_spacing_hz)


def slot_duration_s(ofdm: Ofdm) -> float:
    """Slot duration ``1 ms / 2**mu``, s (TS 38.211 4.3.2: 2**mu slots per 1 ms subframe)."""
    return 1e-3 / 2 ** ofdm.numerology_mu


def symbols_per_slot(ofdm: Ofdm) -> int:
    """OFDM symbols per slot: 14 (normal cyclic prefix) or 12 (extended), TS 38.211 4.3.2."""
    return 12 if ofdm.cyclic_prefix == "extended" else 14


def allocated_resource_blocks(ofdm: Ofdm, link: Link) -> tuple[int, int]:
    """``(first, count)`` of the allocated resource blocks; checks they lie on the carrier."""
    count = (ofdm.num_resource_blocks - link.first_resource_block
             if link.num_allocated_resource_blocks is None else link.num_allocated_resource_blocks)
    if count < 1 or link.first_resource_block + count > ofdm.num_resource_blocks:
        raise ValueError(f"link.first_resource_block ({link.first_resource_block}) + "
                         f"link.num_allocated_resource_blocks ({count}) exceed the carrier's "
                         f"ofdm.num_resource_blocks ({ofdm.num_resource_blocks})")
    return link.first_resource_block, count


def allocated_subcarriers(ofdm: Ofdm, link: Link) -> np.ndarray:
    """Allocated subcarriers: indices ``[12 * count]`` into :func:`subcarrier_offsets_hz`."""
    first, count = allocated_resource_blocks(ofdm, link)
    return np.arange(12 * first, 12 * (first + count))


def channel_frequency_response(a, tau_s, valid, carrier_frequency_hz: float,
                               offsets_hz) -> np.ndarray:
    """Channel frequency response ``H[..., k] = sum_p a_p exp(-j 2 pi (f_c + f_k) tau_p)``.

    Shapes (leading ``...`` dims of ``a``, ``tau_s`` and ``valid`` broadcast together):

    - ``a``: ``[..., rx_ant, tx_ant, path]``, 1 (complex path coefficients, propagation phase
      excluded; Sionna RT ``Paths.a``);
    - ``tau_s``: ``[..., path]``, s (absolute delay; any value, even NaN, where ``valid`` is
      false: the ``cirs`` store holds -1 there);
    - ``valid``: ``[..., path]``, bool (the path exists);
    - ``carrier_frequency_hz``: scalar, Hz;
    - ``offsets_hz``: ``[subcarrier]``, Hz (:func:`subcarrier_offsets_hz`).

    Returns ``[..., rx_ant, tx_ant, subcarrier]`` complex128. Invalid paths contribute exactly 0:
    their coefficient and delay are replaced by 0 before use, so placeholders never leak.
    """
    valid = np.asarray(valid, dtype=bool)
    tau = np.where(valid, np.asarray(tau_s, dtype=np.float64), 0.0)
    a = np.where(valid[..., None, None, :], np.asarray(a).astype(np.complex128, copy=False), 0.0)
    freqs_hz = float(carrier_frequency_hz) + np.asarray(offsets_hz, dtype=np.float64)
    # [..., path, subcarrier]; float64 phase: ~1e-11 rad rounding at 2 pi x 3.5 GHz x 1 us.
    phase = np.exp(-2j * np.pi * (tau[..., :, None] * freqs_hz))
    # one [rx*tx, path] @ [path, subcarrier] product per leading index: a broadcast over the
    # antenna dims instead would take numpy's slow non-BLAS path (9x slower, measured)
    lead = np.broadcast_shapes(a.shape[:-3], phase.shape[:-2])
    r, n, P = a.shape[-3:]
    a = np.broadcast_to(a, lead + (r, n, P)).reshape(lead + (r * n, P))
    H = a @ np.broadcast_to(phase, lead + phase.shape[-2:])
    return H.reshape(lead + (r, n, freqs_hz.size))


def thermal_noise_power_w(bandwidth_hz, temperature_k, noise_figure_db) -> np.ndarray | float:
    """Receiver noise power ``k_B T B 10^(NF/10)`` in W (k_B exact in the SI: vocabulary.BOLTZMANN_J_PER_K).

    ``bandwidth_hz``: Hz; ``temperature_k``: K; ``noise_figure_db``: dB. Broadcasts.
    """
    return (BOLTZMANN_J_PER_K * np.asarray(temperature_k, dtype=np.float64)
            * np.asarray(bandwidth_hz, dtype=np.float64)
            * 10.0 ** (np.asarray(noise_figure_db, dtype=np.float64) / 10.0))
