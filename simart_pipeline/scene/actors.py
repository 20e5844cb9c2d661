"""Actors: the bodies of the platforms and of static actors, and where they are at any instant.

One rule places every actor at every instant, for the sensors and the radio alike
(:func:`actor_poses`): a platform's pose comes from ``trajectory.poses_at`` (the same interpolation
that places its own sensors) and its body is placed so that its ``antenna_point_m`` lies on that
pose; a static actor stands at its configured pose.

Default bodies (the project's own meshes, built with trimesh; frames chosen so a pose on the
trajectory places the body without further offsets):

- quadrotor (``uav``): origin at the body centre, x forward, z up; 0.50 m span rotor tip to rotor
  tip along each diagonal, 0.09 m tall (z from -0.03 to 0.06 m); a 0.16 x 0.16 x 0.06 m body box,
  four 0.04 x 0.04 m arms and four 0.12 m-radius, 0.01 m-thick rotor discs. Antenna 2 cm above the
  rotors' plane at the centre: (0, 0, 0.08) m.
- car (``ground_vehicle``): origin at the ground contact centre, x forward, z up; 4.5 x 1.8 x 1.5 m
  overall (a 4.5 x 1.8 x 0.9 m body at 0.2 m clearance and a 2.5 x 1.6 x 0.4 m cabin; no wheels).
  Antenna 2 cm above the roof: (-0.3, 0, 1.52) m.
- pedestrian (``pedestrian``): origin at the ground contact centre; a 0.5 m-diameter, 1.75 m-tall
  cylinder. Antenna (a handset) 0.35 m in front at 1.4 m: (0.35, 0, 1.4) m.

Each face carries a part index; each part a radio material from vocabulary.RADIO_MATERIALS. ITU-R
P.2040 has no plastic or tissue: rotors and pedestrians use ``plywood`` as a low-permittivity
dielectric stand-in, named here so it is not mistaken for data.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline.config import Body as BodyConfig
from simart_pipeline.config import MeshImportRules, SceneConfig
from simart_pipeline.vocabulary import ACTOR_INSTANCE_ID_BASE, RADIO_MATERIALS, SemanticClass


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


# Where a hidden actor goes: its triangles collapse to one point far below the world (zero area,
# never hit), so a ray-casting layer or a radio scene keeps its size (and its compiled kernels).
HIDDEN_POINT_M = (0.0, 0.0, -1.0e7)

DEFAULT_BODIES = {"uav": quadrotor, "ground_vehicle": car, "pedestrian": pedestrian}
ANTENNA_POINT_M = {"uav": (0.0, 0.0, 0.08), "ground_vehicle": (-0.3, 0.0, 1.52),
                   "pedestrian": (0.35, 0.0, 1.4)}
SEMANTIC_CLASS = {"uav": SemanticClass.UAV, "ground_vehicle": SemanticClass.VEHICLE,
                  "pedestrian": SemanticClass.PEDESTRIAN}


def load_body(body: BodyConfig, kind: str, scene_dir: str | Path | None) -> Body | None:
    """The body a config names: the kind's default, a mesh file of the scene folder, or None."""
    if body.mesh == "none":
        return None
    if body.mesh == "default":
        b = DEFAULT_BODIES[kind]()
        if body.scale != 1.0:
            b.mesh.apply_scale(body.scale)
        return b
    from simart_pipeline.scene.mesh_import import MeshImportError, read_parts

    if scene_dir is None:
        raise ValueError(f"body mesh {body.mesh!r} needs the scene directory")
    source = Path(scene_dir) / body.mesh
    parts, _ = read_parts(source, MeshImportRules(scale_m_per_unit=body.scale))
    if not parts:
        raise MeshImportError(f"{source}: no triangles in the body mesh")
    materials, pieces = [], []
    for part in parts:
        name = next((c for c in part.candidates() if c in body.part_materials), None)
        mat = body.part_materials[name] if name else body.material
        if mat not in materials:
            materials.append(mat)
        pieces.append((part.mesh, materials.index(mat)))
    return _join(pieces, tuple(materials))


@dataclass(frozen=True)
class Actor:
    """One body in the scene: a platform's (``platform`` set) or a static actor's."""

    name: str
    kind: str
    index: int                  # platforms in config order, then static actors
    body: Body
    antenna_point_m: np.ndarray  # [3] in the body frame; the platform's pose sits here
    platform: str | None        # the trajectory that moves it; None: static
    static_position_m: np.ndarray | None = None
    static_yaw_deg: float = 0.0
    scattering_coefficient: float = 0.0  # of every part (Sionna RT's S; the config's body.scattering_coefficient)

    @property
    def semantic_class(self) -> int:
        return int(SEMANTIC_CLASS[self.kind])

    @property
    def instance_id(self) -> int:
        return ACTOR_INSTANCE_ID_BASE + self.index

    @property
    def bounding_radius_m(self) -> float:
        """Radius of a sphere about the body origin that holds the whole body."""
        return float(np.linalg.norm(self.body.mesh.vertices, axis=1).max())


def scene_actors(cfg: SceneConfig, scene_dir: str | Path | None) -> list[Actor]:
    """Every platform with a body, then every static actor with one (bodies with ``mesh: none``
    keep their index, so instance ids do not shift when one is switched off)."""
    def body_of(key: str, body: BodyConfig, kind: str) -> Body | None:
        try:
            return load_body(body, kind, scene_dir)
        except ValueError as exc:  # MeshImportError names the file and the problem
            raise ValueError(f"{key}.body.mesh: {exc}") from None

    out = []
    for i, p in enumerate(cfg.platforms):
        b = body_of(f"platforms.{i}", p.body, p.kind)
        if b is not None:
            point = p.body.antenna_point_m or ANTENNA_POINT_M[p.kind]
            out.append(Actor(p.name, p.kind, i, b, np.asarray(point, np.float64), p.name,
                             scattering_coefficient=p.body.scattering_coefficient))
    for j, a in enumerate(cfg.static_actors):
        b = body_of(f"static_actors.{j}", a.body, a.kind)
        if b is not None:
            out.append(Actor(a.name, a.kind, len(cfg.platforms) + j, b, np.zeros(3), None,
                             np.asarray(a.position_m, np.float64), float(a.yaw_deg),
                             a.body.scattering_coefficient))
    return out


@dataclass
class ActorPoses:
    """Body-origin poses of actors at ``n`` instants (world frame)."""

    position_m: np.ndarray      # [A, n, 3]
    rotation: list[Rotation]    # A rotations of n each, body into world
    velocity_mps: np.ndarray    # [A, n, 3]

    def to_world(self, a: int, i, points_m: np.ndarray) -> np.ndarray:
        """Points of actor ``a``'s body frame in the world at instant(s) ``i`` (an index or a slice)."""
        return self.rotation[a][i].apply(points_m) + self.position_m[a, i]


def actor_poses(actors: list[Actor], traj: xr.Dataset | None, times_ns: np.ndarray) -> ActorPoses:
    """Where every actor's body is at ``times_ns``: a platform's antenna point on its trajectory
    pose (``poses_at``, the interpolation that also places its sensors), a static actor at its pose."""
    from simart_pipeline.mobility.trajectory import poses_at

    n = len(times_ns)
    pos = np.zeros((len(actors), n, 3))
    vel = np.zeros((len(actors), n, 3))
    rots = []
    for a, act in enumerate(actors):
        if act.platform is not None:
            p = poses_at(traj, act.platform, times_ns)
            r = Rotation.from_quat(p["orientation_xyzw"])
            pos[a] = p["position_m"] - r.apply(act.antenna_point_m)
            vel[a] = p["velocity_mps"]
        else:
            r = Rotation.from_euler("z", np.full((n, 1), act.static_yaw_deg), degrees=True)
            pos[a] = act.static_position_m
        rots.append(r)
    return ActorPoses(pos, rots, vel)
