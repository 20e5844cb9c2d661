"""Beams, serving cell and SINR with interference, per resource element (float64).

Model, at one radio-clock instant and on the allocated subcarriers ``k``:

- Base station ``l`` transmits with the unit-norm precoder ``w_b`` (a beam of its codebook) and
  power ``p_l`` per resource element; the receiver combines its antennas with maximum-ratio
  combining (MRC) matched to the serving beam, per subcarrier: ``v = y / |y|``,
  ``y = H_l[k] w_b``. Signal ``S_lb[k] = p_l |y|^2 = p_l G_lb[k]``.
- Interference (the documented beam rule): every other base station ``j`` that reaches the same
  receiver transmits on the same resource elements with a beam drawn uniformly from its
  codebook; its expected power after the combiner is ``p_j v^H M_j[k] v`` with
  ``M_j[k] = mean_b' (H_j[k] w_b')(H_j[k] w_b')^H``.
- Noise per resource element ``N = k_B T df 10^(NF/10)``.
- ``SINR_lb[k] = S_lb[k] / (I_lb[k] + N)``; the wideband ``SINR_lb = sum_k S / sum_k (I + N)``.
  A link's best beam maximises its wideband SINR; each receiver is served by the candidate link
  (base station) whose best-beam wideband SINR is highest (ties: lowest link index).
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.link.beams import beamformed_channel
from simart_pipeline.link.budget import serving_station
from simart_pipeline.link.ofdm import channel_frequency_response

INTERFERENCE_RULE = (
    "every other base station that reaches the receiver transmits on the same resource elements "
    "with a beam drawn uniformly from its codebook; the SINR uses the expected interference power "
    "after the receiver's MRC combiner matched to the serving beam, per subcarrier")


def interference_pairs(rx_of_link) -> tuple[np.ndarray, np.ndarray]:
    """Ordered pairs ``(l, j)``, ``l != j``, of links that end at the same receiver."""
    rx = np.asarray(rx_of_link)
    same = (rx[:, None] == rx[None, :]) & ~np.eye(rx.size, dtype=bool)
    return np.nonzero(same)


def sinr_chunk(a, tau_s, valid, carrier_frequency_hz, offsets_hz, weights, p_re_w, noise_w,
               rx_of_link, candidate, num_rx) -> dict:
    """Beam gains, per-beam SINR, best beam, serving link and per-subcarrier SINR terms.

    - ``a [T, L, r, n, P]``, ``tau_s``/``valid [T, L, P]``: CIRs (``cirs`` store);
    - ``offsets_hz [K]``: allocated subcarriers; ``weights [B, n]``: precoders;
    - ``p_re_w [L]``: transmit power per resource element, W; ``noise_w``: W per RE;
    - ``rx_of_link [L]``: receiver index of each link; ``candidate [T, L]``: links that may serve
      (a path, no flag); ``num_rx``: number of receivers R.

    Returns linear arrays: ``gain [T, L, B]`` (wideband beam gain, mean over K), ``beam_sinr
    [T, L, B]`` (wideband SINR if the link served with the beam), ``best [T, L]``, ``served
    [T, R]``, ``serving [T, R]`` (link index), ``signal_w``/``interference_w [T, R, K]`` of the
    serving link and beam (zeros where not served).
    """
    p_re_w = np.asarray(p_re_w, dtype=np.float64)
    rx_of_link = np.asarray(rx_of_link)
    H = channel_frequency_response(a, tau_s, valid, carrier_frequency_hz, offsets_hz)
    Y = beamformed_channel(H, weights)                                   # [T, L, r, B, K]
    del H
    T, L, r, B, K = Y.shape
    G = np.sum(Y.real**2 + Y.imag**2, axis=2)                            # [T, L, B, K]
    norm = np.sqrt(G)
    v = Y / np.where(norm > 0, norm, 1.0)[:, :, None]                    # MRC combiners
    # Interference covariance of each link under a uniformly random beam: [T, L, r, r, K].
    M = np.einsum("tlrbk,tlsbk->tlrsk", Y, Y.conj()) / B
    del Y
    lp, jp = interference_pairs(rx_of_link)
    interference = np.zeros((T, L, B, K))
    if lp.size:
        if r == 1:   # |v|^2 is 1 (or 0 without signal): no contraction needed
            E = (v[:, lp, 0].real**2 + v[:, lp, 0].imag**2) * M[:, jp, 0, 0].real[:, :, None, :]
        else:
            vp = v[:, lp]
            E = np.einsum("tprbk,tprsk,tpsbk->tpbk", vp.conj(), M[:, jp], vp).real
        # sum over the interferers j of each serving candidate l, weighted by their power
        onto = (lp[None, :] == np.arange(L)[:, None]) * p_re_w[jp][None, :]    # [L, pairs]
        interference = np.einsum("lp,tpbk->tlbk", onto, E)
    signal = p_re_w[None, :, None, None] * G                             # [T, L, B, K]
    beam_sinr = signal.sum(-1) / (interference.sum(-1) + K * noise_w)    # [T, L, B]
    best = beam_sinr.argmax(axis=-1)                                     # [T, L]
    best_sinr = np.take_along_axis(beam_sinr, best[..., None], -1)[..., 0]

    on_rx = rx_of_link[None, :] == np.arange(num_rx)[:, None]             # [R, L]
    cand = candidate[:, None, :] & on_rx[None]                           # [T, R, L]
    served, serving = serving_station(best_sinr[:, None, :], cand, axis=-1)  # [T, R]
    serving_beam = np.take_along_axis(best, serving, axis=1)
    t = np.arange(T)[:, None]
    signal_w = signal[t, serving, serving_beam] * served[..., None]      # [T, R, K]
    interference_w = interference[t, serving, serving_beam] * served[..., None]
    return dict(gain=G.mean(-1), beam_sinr=beam_sinr, best=best, served=served,
                serving=serving, signal_w=signal_w, interference_w=interference_w)


def chunk_steps(sizes: dict, num_beams: int, num_subcarriers: int, max_bytes: int) -> int:
    """Time steps per chunk so that the working set of :func:`sinr_chunk` stays under
    ``max_bytes`` (complex128: 16 bytes, float64: 8)."""
    L, r, n, P, K, B = (sizes["link"], sizes["rx_ant"], sizes["tx_ant"], sizes["path"],
                        num_subcarriers, num_beams)
    pairs = max(1, L * (L - 1))
    per_step = (16 * L * (r * n * P + P * K + 2 * r * n * K + 2 * r * B * K + r * r * K)
                + 8 * (3 * L * B * K + pairs * B * K) + 16 * pairs * r * B * K)
    return max(1, int(max_bytes // per_step))
