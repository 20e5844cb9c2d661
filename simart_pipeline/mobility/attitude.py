"""Platform attitude from the motion: quadrotor (thrust-tilted) or level, heading along the velocity.

Quadrotor (differential flatness, Mellinger and Kumar, ICRA 2011): the rotor thrust is along body
z, so body z is the direction of ``f = a + g z_world`` (``a`` the acceleration, gravity excluded).
Yaw is the ZYX (yaw-pitch-roll) yaw, so body x seen from above points along the heading: body x
is perpendicular to body z and to ``h = (-sin yaw, cos yaw, 0)``, the horizontal left of the
heading; body y completes the right-handed frame. Level: body z is world z, body x the heading.
The angular velocity follows in closed form from the time derivatives of the three axes
(``f' = jerk``, ``h' = -yaw_rate (cos yaw, sin yaw, 0)``): with ``R = [x y z]`` (base_link into
world, columns the body axes), ``R^T R' = [omega]x``, so ``omega = (z . y', x . z', y . x')`` in
base_link.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from simart_pipeline.vocabulary import STANDARD_GRAVITY_MPS2


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _unit_and_rate(w: np.ndarray, wd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``w / |w|`` and its time derivative, given ``w`` and ``dw/dt`` ``[n, 3]``."""
    n = np.linalg.norm(w, axis=1, keepdims=True)
    u = w / n
    return u, (wd - u * _dot(u, wd)[:, None]) / n


def continuous_quaternions(rot: Rotation) -> np.ndarray:
    """Scalar-last quaternions ``[n, 4]`` with signs chosen so that neighbours never jump to -q."""
    q = rot.as_quat().reshape(-1, 4)
    if len(q) > 1:
        flip = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0
        sign = np.concatenate([[1.0], np.cumprod(np.where(flip, -1.0, 1.0))])
        q = q * sign[:, None]
    return q


def thrust_attitude(acceleration_mps2: np.ndarray, jerk_mps3: np.ndarray, yaw_rad: np.ndarray,
                    yaw_rate_radps: np.ndarray,
                    gravity_mps2: float = STANDARD_GRAVITY_MPS2) -> tuple[np.ndarray, np.ndarray]:
    """Quadrotor attitude: ``(orientation_xyzw [n, 4], angular_velocity_radps [n, 3] in base_link)``.

    :param acceleration_mps2: ``[n, 3]`` world, gravity excluded; ``|a| < g`` keeps body z upward.
    :param jerk_mps3: ``[n, 3]`` its time derivative.
    :param yaw_rad: ``[n]`` heading of body x (rad from east, counter-clockwise), ``yaw_rate_radps`` its rate.
    """
    a = np.asarray(acceleration_mps2, np.float64).reshape(-1, 3)
    jerk = np.asarray(jerk_mps3, np.float64).reshape(-1, 3)
    yaw = np.asarray(yaw_rad, np.float64).ravel()
    yaw_rate = np.asarray(yaw_rate_radps, np.float64).ravel()
    z, zd = _unit_and_rate(a + [0.0, 0.0, gravity_mps2], jerk)
    zeros = np.zeros_like(yaw)
    h = np.stack([-np.sin(yaw), np.cos(yaw), zeros], -1)
    hd = -yaw_rate[:, None] * np.stack([np.cos(yaw), np.sin(yaw), zeros], -1)
    x, xd = _unit_and_rate(np.cross(h, z), np.cross(hd, z) + np.cross(h, zd))
    y = np.cross(z, x)
    yd = np.cross(zd, x) + np.cross(z, xd)
    rot = Rotation.from_matrix(np.stack([x, y, z], axis=-1))
    omega = np.stack([_dot(z, yd), _dot(x, zd), _dot(y, xd)], -1)
    return continuous_quaternions(rot), omega


def level_attitude(yaw_rad: np.ndarray, yaw_rate_radps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Level platform heading ``yaw_rad``: ``(orientation_xyzw [n, 4], angular_velocity_radps [n, 3])``."""
    yaw = np.asarray(yaw_rad, np.float64).ravel()
    omega = np.zeros((len(yaw), 3))
    omega[:, 2] = np.asarray(yaw_rate_radps, np.float64).ravel()
    return continuous_quaternions(Rotation.from_euler("z", yaw[:, None])), omega
