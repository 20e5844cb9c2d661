"""DFT beam codebook of the base-station planar array, beam gains, and frame rotations.

Array geometry (Sionna RT ``PlanarArray``): antennas in the y-z plane of the transmitter's own
frame, boresight +x; ``cols`` elements along y (horizontal spacing), ``rows`` along z.

Sign convention (verified against a real Sionna RT 2.2 ``PathSolver`` run with
``synthetic_array=True``, see ``tests/test_link.py``): for a path leaving along the unit vector
``d`` (transmitter frame) the coefficient of antenna n is ``a_n = a_0 exp(+j 2 pi/lambda p_n . d)``
(``p_n``: antenna position, array centre at the origin). A beam is a *precoder*: the transmitted
signal on antenna n is ``w_n x``, the received one ``sum_n H_n w_n x``, so the beam pointed at
``d`` is ``w_n = exp(-j 2 pi/lambda p_n . d) / sqrt(N)`` and gains use ``|sum_n w_n H_n|^2``
without conjugation.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from simart_pipeline import frames
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS


def _axis_grid(num_elements: int, spacing_wavelengths: float, oversampling: int) -> np.ndarray:
    """Direction cosines of the DFT grid along one array axis: ``[num_elements * oversampling]``.

    Spatial frequency in cycles per element ``psi_i = -1/2 + (i + 1/2) / (O M)``, i = 0..OM-1:
    the half-bin-shifted DFT grid, symmetric about boresight; for O = 1 its steering vectors are
    orthogonal for any element spacing. Direction cosine ``u = psi / spacing_wavelengths``; for
    half-wavelength spacing ``u_i = -1 + (2i + 1) / (O M)``. A one-element axis has no resolution:
    only ``u = 0``.
    """
    if num_elements == 1:
        return np.zeros(1)
    n = num_elements * oversampling
    psi = -0.5 + (np.arange(n) + 0.5) / n
    return psi / spacing_wavelengths


def _spacing_wavelengths(coords_m: np.ndarray, count: int, wavelength_m: float, axis: str) -> float:
    """Element spacing along one axis (in wavelengths) from the antenna coordinates ``[N]``, m,
    checking that they form ``count`` equally spaced values."""
    if count == 1:
        return 0.5  # unused: a one-element axis gets the single beam u = 0
    c = np.sort(coords_m)
    breaks = np.flatnonzero(np.diff(c) > 1e-6)  # 1 um: float32 noise, far below any spacing
    values = np.array([g.mean() for g in np.split(c, breaks + 1)])
    steps = np.diff(values)
    if values.size != count or not np.allclose(steps, steps[0], rtol=1e-4):
        raise ValueError(f"antenna positions are not {count} equally spaced elements along {axis}")
    return float(steps[0]) / wavelength_m


class DftCodebook(NamedTuple):
    """A DFT codebook: precoders and where they point (array frame, boresight +x)."""

    weights: np.ndarray            # [B, N] complex128, unit-norm precoders
    direction_cosines: np.ndarray  # [B, 2] float64, (u_y, u_z) of each beam
    visible: np.ndarray            # [B] bool, u_y^2 + u_z^2 <= 1
    directions: np.ndarray         # [B, 3] float64 unit vectors; NaN rows where not visible


def upa_steering_vectors(ant_positions_m, directions, wavelength_m: float) -> np.ndarray:
    """Array response ``a_n(d) = exp(+j 2 pi/lambda p_n . d)`` (Sionna RT sign, module docstring).

    ``ant_positions_m``: ``[N, 3]``, m, array frame; ``directions``: ``[..., 3]`` unit vectors (or
    any vectors: direction cosines with a zero x for beams beyond end-fire); ``wavelength_m``: m.
    Returns ``[..., N]`` complex128, unit modulus per element.
    """
    pos = np.asarray(ant_positions_m, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    return np.exp(1j * (2.0 * np.pi / wavelength_m) * (d @ pos.T))


def dft_codebook(ant_positions_m, wavelength_m: float, rows: int, cols: int,
                 oversampling: int = 1, visible_only: bool = False) -> DftCodebook:
    """DFT beams of a ``rows x cols`` planar array in the y-z plane, boresight +x.

    - ``ant_positions_m``: ``[N, 3]``, m, in the array's own frame (dataset ``tx_ant_position_m``);
    - ``wavelength_m``: carrier wavelength, m; ``oversampling``: O per axis (1 = orthogonal beams);
    - ``visible_only``: drop beams with ``u_y^2 + u_z^2 > 1`` (no real direction).

    Beams sit on the product grid of :func:`_axis_grid` direction cosines ``(u_y, u_z)``, order
    ``u_y`` index major, ``u_z`` minor: ``rows * cols * O**2`` beams (64 for 8 x 8, O = 1; with
    O = 1 and half-wavelength spacing they form a unitary basis). With 8 x 8 half-wavelength
    elements 12 of the 64 lie beyond end-fire (``visible`` false): they remain valid precoders
    whose main lobe is outside visible space.

    Weights are unit-norm precoders ``w_n = exp(-j 2 pi/lambda (p_y u_y + p_z u_z)) / sqrt(N)``
    (the conjugate of :func:`upa_steering_vectors` towards a visible beam's direction).
    """
    pos = np.asarray(ant_positions_m, dtype=np.float64)
    if pos.ndim != 2 or pos.shape != (rows * cols, 3):
        raise ValueError(f"ant_positions_m must be [{rows * cols}, 3], got {pos.shape}")
    uy = _axis_grid(cols, _spacing_wavelengths(pos[:, 1], cols, wavelength_m, "y"), oversampling)
    uz = _axis_grid(rows, _spacing_wavelengths(pos[:, 2], rows, wavelength_m, "z"), oversampling)
    uy, uz = (g.ravel() for g in np.meshgrid(uy, uz, indexing="ij"))
    visible = uy**2 + uz**2 <= 1.0
    if visible_only:
        uy, uz, visible = uy[visible], uz[visible], visible[visible]
    ux = np.sqrt(np.clip(1.0 - uy**2 - uz**2, 0.0, None))
    # the array lies in the y-z plane (p_x = 0), so u_x never changes the weights
    weights = np.conj(upa_steering_vectors(pos, np.stack([ux, uy, uz], -1), wavelength_m))
    weights /= np.sqrt(pos.shape[0])
    directions = np.where(visible[:, None], np.stack([ux, uy, uz], -1), np.nan)
    return DftCodebook(weights, np.stack([uy, uz], -1), visible, directions)


def scene_codebook_weights(cfg, tx_ant_positions_m, scene_dir=None) -> np.ndarray:
    """The scene's base-station precoders ``[B, N]`` as the ``kpis`` stage uses them: the file
    ``codebook.path`` (relative to ``scene_dir``) or the DFT grid of ``cfg.codebook``
    (oversampling, visible_only) for the base stations' array. ``cfg``: a ``SceneConfig``;
    ``tx_ant_positions_m``: ``[N, 3]``, m (``cirs`` ``tx_ant_position_m``)."""
    pos = np.asarray(tx_ant_positions_m, dtype=np.float64)
    if cfg.codebook.path is not None:
        if scene_dir is None:
            raise ValueError("codebook.path is set: the scene directory is needed to read it")
        return load_codebook(Path(scene_dir) / cfg.codebook.path, pos.shape[0])
    array = cfg.base_stations[0].array   # one transmit array per scene (config validator)
    return dft_codebook(pos, SPEED_OF_LIGHT_MPS / cfg.ofdm.carrier_frequency_hz, array.rows,
                        array.cols, cfg.codebook.oversampling, cfg.codebook.visible_only).weights


def load_codebook(path, num_tx_antennas: int) -> np.ndarray:
    """Precoders ``[B, num_tx_antennas]`` complex128 from a ``.npy`` file (config
    ``codebook.path``); each row must have unit norm (the transmit power is the station's)."""
    path = Path(path)
    try:
        w = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npy codebook: {exc}") from None
    if w.ndim != 2 or w.shape[1] != num_tx_antennas or w.shape[0] < 1:
        raise ValueError(f"{path}: codebook must be [num_beams, {num_tx_antennas}], got {w.shape}")
    w = w.astype(np.complex128)
    if not np.isfinite(w).all():
        raise ValueError(f"{path}: codebook holds NaN or inf")
    norms = np.linalg.norm(w, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-6)
    if bad.size:
        raise ValueError(f"{path}: precoders must have unit norm; beam {bad[0]} has norm "
                         f"{norms[bad[0]]:.6g} ({bad.size} beams off)")
    return w


def beamformed_channel(H, weights) -> np.ndarray:
    """Effective channel of each beam: ``Y[..., r, b, k] = sum_n w_{b,n} H[..., r, n, k]``.

    ``H``: ``[..., rx_ant, tx_ant, subcarrier]``; ``weights``: ``[B, tx_ant]`` (precoders, no
    conjugation). Returns ``[..., rx_ant, B, subcarrier]`` complex128.
    """
    return np.asarray(weights, dtype=np.complex128) @ np.asarray(H, dtype=np.complex128)


def beam_gains_per_subcarrier(H, weights) -> np.ndarray:
    """Beam gain per subcarrier with maximum-ratio combining over the receive antennas.

    ``G[..., b, k] = sum_r |sum_n w_{b,n} H[..., r, n, k]|^2``, 1 (linear power gain);
    ``H``: ``[..., rx_ant, tx_ant, subcarrier]``, ``weights``: ``[B, tx_ant]``.
    Returns ``[..., B, subcarrier]`` float64.
    """
    y = beamformed_channel(H, weights)
    return np.sum(y.real**2 + y.imag**2, axis=-3)


def beam_gains(H, weights) -> np.ndarray:
    """Wideband beam gain: mean over subcarriers of :func:`beam_gains_per_subcarrier`.

    ``H``: ``[..., rx_ant, tx_ant, subcarrier]``; ``weights``: ``[B, tx_ant]``.
    Returns ``[..., B]`` float64, 1 (linear).
    """
    return beam_gains_per_subcarrier(H, weights).mean(axis=-1)


def rotation_local_to_world(orientation_rad) -> np.ndarray:
    """Rotation matrix of a Sionna RT orientation ``[..., 3] = (yaw, pitch, roll)``, rad.

    ``R = Rz(yaw) Ry(pitch) Rx(roll)`` maps vectors of the device's own frame into the world
    frame. Returns ``[..., 3, 3]``.
    """
    ori = np.asarray(orientation_rad, dtype=np.float64)
    mats = frames.rotation_from_sionna_orientation(ori.reshape(-1, 3)).as_matrix()
    return mats.reshape(ori.shape[:-1] + (3, 3))


def world_to_local(directions_world, orientation_rad) -> np.ndarray:
    """World-frame vectors ``[..., 3]`` into the frame of a device with Sionna orientation
    ``orientation_rad [3]`` (or broadcasting ``[..., 3]``), i.e. ``R^T d``. Returns ``[..., 3]``."""
    R = rotation_local_to_world(orientation_rad)
    return np.einsum("...ji,...j->...i", R, np.asarray(directions_world, dtype=np.float64))


def unit_vector(theta_rad, phi_rad) -> np.ndarray:
    """Unit vector ``[..., 3]`` of zenith ``theta_rad`` and azimuth ``phi_rad`` (Sionna RT)."""
    theta = np.asarray(theta_rad, dtype=np.float64)
    phi = np.asarray(phi_rad, dtype=np.float64)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
