"""OFDM radar processing for a monostatic base-station radar, in float64 / complex128.

The base station transmits an OFDM frame and receives its own echoes. Per path ``p`` (Sionna RT
convention: ``a_p`` excludes the propagation phase, ``tau_p`` is the two-way delay, ``f_D,p`` the
Doppler shift in Hz), the channel seen on subcarrier ``k`` of symbol ``n`` is

    H[n, k] = sum_p a_p exp(-j 2 pi (f_c + f_k) tau_p) exp(+j 2 pi f_D,p t_n)

(the subcarrier grid ``f_k`` of :func:`~simart_pipeline.link.ofdm.subcarrier_offsets_hz`, the
symbol start times ``t_n``; the Doppler phase is constant within a symbol, i.e. inter-carrier
interference is neglected). The range-Doppler map is the windowed 2-D transform of ``H``: an
inverse DFT over subcarriers to delay, a DFT over symbols to Doppler.

Sign conventions: Doppler as in Sionna RT, so a reflector receding from the radar has a negative
Doppler ``f_D = -2 v_r / lambda``; radial velocity ``v_r`` (range rate) is positive when receding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simart_pipeline.config import Ofdm
from simart_pipeline.link.ofdm import (channel_frequency_response, slot_duration_s,
                                       subcarrier_offsets_hz, symbols_per_slot)
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS


def symbol_duration_s(ofdm: Ofdm) -> float:
    """Mean OFDM symbol duration including the cyclic prefix, s: slot duration / symbols per slot.

    (The first symbol of each half subframe carries a slightly longer cyclic prefix in TS 38.211;
    the radar processing treats symbols as evenly spaced by this mean.)
    """
    return slot_duration_s(ofdm) / symbols_per_slot(ofdm)


def frame_response(a, tau_s, doppler_hz, valid, carrier_frequency_hz: float, offsets_hz,
                   symbol_times_s) -> np.ndarray:
    """Frame response ``H[n, k] = sum_p a_p exp(-j 2 pi (f_c + f_k) tau_p) exp(+j 2 pi f_D,p t_n)``.

    - ``a``: ``[path]``, 1 (complex path coefficients, propagation phase excluded, reduced to one
      antenna pair or a beamformed scalar per path);
    - ``tau_s``: ``[path]``, s (two-way delay of the echo);
    - ``doppler_hz``: ``[path]``, Hz (Sionna sign: negative for a receding reflector);
    - ``valid``: ``[path]``, bool (the path exists);
    - ``carrier_frequency_hz``: scalar, Hz;
    - ``offsets_hz``: ``[subcarrier]``, Hz (:func:`~simart_pipeline.link.ofdm.subcarrier_offsets_hz`);
    - ``symbol_times_s``: ``[symbol]``, s (start time of each OFDM symbol).

    Returns ``[symbol, subcarrier]`` complex128. Invalid paths contribute exactly 0: their
    coefficient, delay and Doppler are replaced by 0 before use, so placeholders (NaN, -1) never
    leak.
    """
    valid = np.asarray(valid, dtype=bool)
    a = np.where(valid, np.asarray(a).astype(np.complex128, copy=False), 0.0)
    tau = np.where(valid, np.asarray(tau_s, dtype=np.float64), 0.0)
    doppler = np.where(valid, np.asarray(doppler_hz, dtype=np.float64), 0.0)
    t = np.asarray(symbol_times_s, dtype=np.float64)
    # The Doppler rotation folds into a per-symbol path coefficient [symbol, path]; the delay
    # phase over subcarriers is then ofdm.channel_frequency_response with the symbol as a leading
    # dim and a 1 x 1 antenna pair.
    a_n = a[None, :] * np.exp(2j * np.pi * (t[:, None] * doppler[None, :]))
    H = channel_frequency_response(a_n[:, None, None, :], tau, valid, carrier_frequency_hz,
                                   offsets_hz)
    return H[:, 0, 0, :]


@dataclass(frozen=True, eq=False)
class RangeDoppler:
    """A monostatic range-Doppler map.

    - ``power``: ``[range_bin, velocity_bin]``, 1 (linear, float64; a single path of coefficient
      ``a`` exactly on a bin gives ``|a|**2`` there);
    - ``range_m``: ``[range_bin]``, m (one-way range ``c tau / 2`` of each bin, from 0 up to just
      below ``max_range_m``);
    - ``radial_velocity_mps``: ``[velocity_bin]``, m/s (ascending; positive = receding);
    - ``window``: the scipy window name used over subcarriers and over symbols;
    - ``range_resolution_m``: m, ``c / (2 K df)`` (the bin spacing is this / range_oversampling);
    - ``velocity_resolution_mps``: m/s, ``lambda / (2 N T_sym)`` (bin spacing is this /
      doppler_oversampling);
    - ``max_range_m``: m, unambiguous range ``c / (2 df)``;
    - ``max_radial_velocity_mps``: m/s, unambiguous speed ``lambda / (4 T_sym)``: velocities in
      ``[-max, +max)`` map to themselves, others alias.
    """

    power: np.ndarray
    range_m: np.ndarray
    radial_velocity_mps: np.ndarray
    window: str
    range_resolution_m: float
    velocity_resolution_mps: float
    max_range_m: float
    max_radial_velocity_mps: float


def range_doppler_map(H, ofdm: Ofdm, *, range_oversampling: int = 1, doppler_oversampling: int = 1,
                      window: str = "hann") -> RangeDoppler:
    """Range-Doppler map of a frame response ``H`` ``[symbol, subcarrier]`` (:func:`frame_response`).

    The rows of ``H`` are consecutive OFDM symbols spaced by :func:`symbol_duration_s`; its columns
    are all ``ofdm.num_subcarriers`` subcarriers of :func:`~simart_pipeline.link.ofdm.subcarrier_offsets_hz`.
    ``window`` (any :func:`scipy.signal.get_window` name, e.g. ``"hann"`` or ``"rect"``; periodic,
    i.e. ``fftbins=True``) is applied over subcarriers and over symbols. The subcarrier transform is
    zero-padded to ``K * range_oversampling`` delay bins ``tau_i = i / (K df range_oversampling)``,
    all kept (``range_m = c tau_i / 2``); the symbol transform to ``N * doppler_oversampling``
    Doppler bins.

    Normalisation: divided by the sums of the two windows (size x coherent gain), so a single path
    of coefficient ``a`` exactly on a bin gives power ``|a|**2`` at its cell. Then, by Parseval,
    ``power.sum() == N_r N_d sum |v_n w_k H[n, k]|**2 / (sum w)**2 / (sum v)**2`` with ``N_r``,
    ``N_d`` the padded sizes.
    """
    H = np.asarray(H).astype(np.complex128, copy=False)
    if H.ndim != 2 or H.shape[1] != ofdm.num_subcarriers:
        raise ValueError(f"H: expected [symbol, {ofdm.num_subcarriers}] (ofdm.num_subcarriers), "
                         f"got shape {H.shape}")
    for name, ovs in (("range_oversampling", range_oversampling),
                      ("doppler_oversampling", doppler_oversampling)):
        if int(ovs) != ovs or ovs < 1:
            raise ValueError(f"{name}: a positive integer, got {ovs!r}")
    num_symbols, num_subcarriers = H.shape
    n_range = num_subcarriers * int(range_oversampling)
    n_doppler = num_symbols * int(doppler_oversampling)
    spacing_hz = float(ofdm.subcarrier_spacing_hz)
    t_sym = symbol_duration_s(ofdm)
    wavelength_m = SPEED_OF_LIGHT_MPS / float(ofdm.carrier_frequency_hz)

    import scipy.signal  # here, not at module level: its import takes about 0.9 s, which every
    #                      `simart run` (an unchanged rerun included) paid on loading the assets

    w_k = scipy.signal.get_window(window, num_subcarriers, fftbins=True)
    v_n = scipy.signal.get_window(window, num_symbols, fftbins=True)
    X = H * v_n[:, None] * w_k[None, :]

    # Delay transform: sum_k X[n, k] exp(+j 2 pi k i / N_r), peaking at tau_i = i / (N_r df).
    X = np.fft.ifft(X, n=n_range, axis=1) * n_range
    tau_s = np.arange(n_range, dtype=np.float64) / (n_range * spacing_hz)
    # The grid starts at f_0 = offsets_hz[0] (= -(K-1)/2 df), not at the carrier, so a path of
    # delay tau carries an extra exp(-j 2 pi f_0 tau) that the index-based transform does not see.
    # Removing it at each bin's delay leaves a path on a bin with the phase of a exp(-j 2 pi f_c
    # tau), as for a grid starting at the carrier. |X| does not depend on it: the power map is the
    # same either way, the phase matters to whoever reads the complex profile (or extends this).
    f0_hz = subcarrier_offsets_hz(ofdm)[0]
    X = X * np.exp(2j * np.pi * f0_hz * tau_s)[None, :]

    # Doppler transform: H ~ exp(+j 2 pi f_D n T_sym), so the DFT's kernel exp(-j 2 pi m n / N_d)
    # peaks at f_D = m / (N_d T_sym).
    X = np.fft.fftshift(np.fft.fft(X, n=n_doppler, axis=0), axes=0)
    doppler_hz = np.fft.fftshift(np.fft.fftfreq(n_doppler, d=t_sym))
    X = X / (w_k.sum() * v_n.sum())

    # v_r = -f_D lambda / 2 decreases along the ascending Doppler axis: flip to ascending velocity.
    power = np.abs(X.T[:, ::-1]) ** 2
    radial_velocity_mps = (-doppler_hz * wavelength_m / 2.0)[::-1]
    return RangeDoppler(
        power=np.ascontiguousarray(power),
        range_m=SPEED_OF_LIGHT_MPS * tau_s / 2.0,
        radial_velocity_mps=np.ascontiguousarray(radial_velocity_mps),
        window=window,
        range_resolution_m=SPEED_OF_LIGHT_MPS / (2.0 * num_subcarriers * spacing_hz),
        velocity_resolution_mps=wavelength_m / (2.0 * num_symbols * t_sym),
        max_range_m=SPEED_OF_LIGHT_MPS / (2.0 * spacing_hz),
        max_radial_velocity_mps=wavelength_m / (4.0 * t_sym),
    )


def radar_truth(radar_position_m, target_position_m, target_velocity_mps) -> dict[str, np.ndarray]:
    """Ground truth of targets seen by a monostatic radar (static radar), world ENU.

    - ``radar_position_m``: ``[3]``, m;
    - ``target_position_m``: ``[n, 3]``, m;
    - ``target_velocity_mps``: ``[n, 3]``, m/s.

    Returns ``range_m`` ``[n]`` (m, one-way distance), ``radial_velocity_mps`` ``[n]`` (m/s, the
    velocity projected on the unit line of sight from radar to target: positive receding),
    ``azimuth_rad`` ``[n]`` (rad, ``atan2(dy, dx)``, from east towards north) and ``elevation_rad``
    ``[n]`` (rad, ``asin(dz / range)``).
    """
    d = (np.asarray(target_position_m, dtype=np.float64)
         - np.asarray(radar_position_m, dtype=np.float64))
    v = np.asarray(target_velocity_mps, dtype=np.float64)
    range_m = np.linalg.norm(d, axis=-1)
    los = d / range_m[..., None]
    return {
        "range_m": range_m,
        "radial_velocity_mps": np.sum(v * los, axis=-1),
        "azimuth_rad": np.arctan2(d[..., 1], d[..., 0]),
        # clip: rounding can put |dz| / range a hair above 1 for a target straight overhead
        "elevation_rad": np.arcsin(np.clip(d[..., 2] / range_m, -1.0, 1.0)),
    }


def peak(rd: RangeDoppler) -> tuple[float, float, float]:
    """``(range_m, radial_velocity_mps, power)`` of the map's largest cell: m, m/s, 1 (linear)."""
    i, j = np.unravel_index(np.argmax(rd.power), rd.power.shape)
    return float(rd.range_m[i]), float(rd.radial_velocity_mps[j]), float(rd.power[i, j])
