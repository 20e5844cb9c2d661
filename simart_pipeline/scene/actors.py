"""Default actor bodies: the project's own simple meshes, one per platform kind, built with trimesh.

Frames (chosen so a pose on the trajectory places the body without offsets):

- quadrotor (``uav``): origin at the body centre, x forward, z up; 0.50 m span rotor tip to rotor
  tip along each diagonal, 0.09 m tall (z from -0.03 to 0.06 m); a 0.16 × 0.16 × 0.06 m body box, four 0.04 × 0.04 m arms
  and four 0.12 m-radius, 0.01 m-thick rotor discs.
- car (``ground_vehicle``): origin at the ground contact centre, x forward, z up; 4.5 × 1.8 × 1.5 m
  overall (a 4.5 × 1.8 × 0.9 m body at 0.2 m clearance and a 2.5 × 1.6 × 0.4 m cabin; no wheels).
- pedestrian (``pedestrian``): origin at the ground contact centre; a 0.5 m-diameter, 1.75 m-tall
  cylinder.

Each face carries a part index; each part a radio material from vocabulary.RADIO_MATERIALS, so the
radio side can use the same bodies. ITU-R P.2040 has no plastic or tissue: rotors and pedestrians
use ``plywood`` as a low-permittivity dielectric stand-in, named here so it is not mistaken for data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from simart_pipeline.vocabulary import RADIO_MATERIALS


@dataclass(frozen=True)
class Body:
    """A platform body in its base_link frame: ``mesh`` (m), ``face_part`` [F] int, ``part_materials``."""

    mesh: trimesh.Trimesh
    face_part: np.ndarray
    part_materials: tuple[str, ...]


def _join(parts: list[tuple[trimesh.Trimesh, int]], materials: tuple[str, ...]) -> Body:
    assert all(m in RADIO_MATERIALS for m in materials), materials
    mesh = trimesh.util.concatenate([p for p, _ in parts])
    face_part = np.concatenate([np.full(len(p.faces), i, np.int32) for p, i in parts])
    return Body(mesh=mesh, face_part=face_part, part_materials=materials)


def _box(extents, centre) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def quadrotor() -> Body:
    """0.50 m rotor-tip span, 0.09 m tall, origin at the body centre (see the module docstring)."""
    rotor_radius_m = 0.12
    hub_m = (0.25 - rotor_radius_m) / np.sqrt(2.0)  # rotor tips 0.25 m from the centre on a diagonal
    parts = [(_box((0.16, 0.16, 0.06), (0, 0, 0)), 0)]
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        c = np.array([sx * hub_m, sy * hub_m, 0.0])
        arm_len = float(np.hypot(*c[:2]))
        arm = trimesh.creation.box(extents=(arm_len, 0.04, 0.03))
        arm.apply_transform(trimesh.transformations.rotation_matrix(np.arctan2(c[1], c[0]), (0, 0, 1)))
        arm.apply_translation(c / 2)
        parts.append((arm, 0))
        disc = trimesh.creation.cylinder(radius=rotor_radius_m, height=0.01, sections=24)
        disc.apply_translation(c + (0, 0, 0.055))
        parts.append((disc, 1))
    return _join(parts, ("metal", "plywood"))


def car() -> Body:
    """4.5 × 1.8 × 1.5 m, origin at the ground contact centre (see the module docstring)."""
    return _join([(_box((4.5, 1.8, 0.9), (0, 0, 0.2 + 0.45)), 0),
                  (_box((2.5, 1.6, 0.4), (-0.3, 0, 1.1 + 0.2)), 1)], ("metal", "glass"))


def pedestrian() -> Body:
    """0.5 m diameter, 1.75 m tall cylinder standing on its origin."""
    body = trimesh.creation.cylinder(radius=0.25, height=1.75, sections=16)
    body.apply_translation((0, 0, 1.75 / 2))
    return _join([(body, 0)], ("plywood",))


DEFAULT_BODIES = {"uav": quadrotor, "ground_vehicle": car, "pedestrian": pedestrian}
