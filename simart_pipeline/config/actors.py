"""Actor bodies and static actors: what every platform looks like to the sensors and the radio, and
the parked vehicles or standing people a scene places without a trajectory (``docs/actors.md``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from simart_pipeline.config.base import Vec3, _inside_scene_dir, _Model
from simart_pipeline.vocabulary import RADIO_MATERIALS

ActorKind = Literal["uav", "ground_vehicle", "pedestrian"]


def _known_material(v: str) -> str:
    if v not in RADIO_MATERIALS:
        raise ValueError(f"unknown radio material {v!r}; known: {', '.join(RADIO_MATERIALS)}")
    return v


class Body(_Model):
    """A platform's or static actor's body.

    ``mesh``: ``default`` (the bundled body of the kind, ``sensing/bodies.py``), ``none`` (no body:
    nothing sees it and it blocks nothing), or a mesh file in the scene folder (PLY, OBJ, STL, GLB;
    metres, x forward, z up, origin at the body's reference point). A file's parts (the geometries
    of a multi-geometry file) take ``part_materials[name]`` or else ``material``.

    ``antenna_point_m``: where the platform's antenna (and pose) sits in the body frame. The body is
    placed so that this point is at the trajectory's position: a car driving at z = 1.5 m with its
    antenna 2 cm above its 1.5 m roof has its wheels on the ground. Default per kind
    (``bodies.ANTENNA_POINT_M``).
    """

    mesh: str = "default"
    material: str = "metal"
    part_materials: dict[str, str] = Field(default_factory=dict)
    scale: float = Field(1.0, gt=0, le=100)
    antenna_point_m: Vec3 | None = None
    scattering_coefficient: float = Field(
        0.3, ge=0, le=1, description="Sionna RT's S of every part (Lambertian diffuse scattering, "
        "used where ray_tracing or a radar enables diffuse reflection): the stand-in for the curved "
        "panels, wheels and edges a simple body does not model; 0 makes a pure mirror")

    _mat = field_validator("material")(classmethod(lambda cls, v: _known_material(v)))

    @field_validator("part_materials")
    @classmethod
    def _parts(cls, v: dict[str, str]) -> dict[str, str]:
        for m in v.values():
            _known_material(m)
        return v

    @field_validator("mesh")
    @classmethod
    def _mesh(cls, v: str) -> str:
        return v if v in ("default", "none") else _inside_scene_dir(v, "body.mesh")

    @property
    def is_file(self) -> bool:
        return self.mesh not in ("default", "none")


class StaticActor(_Model):
    """An actor that does not move: ``position_m`` is its body origin (for the bundled car and
    pedestrian the ground contact centre, for the quadrotor its centre), ``yaw_deg`` its heading
    (counter-clockwise from east)."""

    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: ActorKind
    position_m: Vec3
    yaw_deg: float = 0.0
    body: Body = Body()
