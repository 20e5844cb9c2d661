"""Ray casting against the visual mesh with Mitsuba 3 (the process's one Mitsuba variant).

The visual mesh becomes ONE Mitsuba mesh built from the arrays (no file round trip), so the
primitive index of a hit is the face index of :class:`SceneMeshes.visual` and indexes
``face_class`` / ``face_instance`` directly. The variant is whatever :func:`engine.init` selected
(the one Sionna RT uses); this module never sets a variant.

Two ways in:

- :class:`RayBundle`: a sensor's fixed ray directions (a camera's pixels, a LiDAR's beams) kept in
  drjit and cast frame after frame from a pose; the pose enters as opaque values so every frame
  reuses one compiled kernel (the camera fuses its shading into the same kernel).
- :meth:`RayCaster.intersect` / :meth:`RayCaster.occluded`: arbitrary numpy rays in batches.

Normals are the mesh's flat face normals, looked up by face index.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simart_pipeline import engine
from simart_pipeline.scene.meshes import SceneMeshes

# Rays per Mitsuba call: big enough to amortise the call, small enough to bound memory.
MAX_RAYS_PER_CALL = 2_000_000


@dataclass
class Hits:
    """Results of casting ``n`` rays (directions unit length)."""

    t: np.ndarray        # [n] float64 m along the ray; inf where nothing was hit
    face: np.ndarray     # [n] int64 face index of the visual mesh; -1 where nothing was hit
    normal: np.ndarray   # [n, 3] float64 unit face normal (world), zeros where nothing was hit

    @property
    def hit(self) -> np.ndarray:
        return self.face >= 0


def build_scene(meshes: SceneMeshes):
    """A Mitsuba scene holding the visual mesh as one shape (face order kept)."""
    engine.init()
    import mitsuba as mi

    v = np.ascontiguousarray(meshes.visual.vertices, dtype=np.float32)
    f = np.ascontiguousarray(meshes.visual.faces, dtype=np.uint32)
    if len(f) == 0:
        raise ValueError("the visual mesh has no faces to ray-cast against")
    mesh = mi.Mesh("visual", len(v), len(f), has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.ravel())
    params["faces"] = mi.UInt32(f.ravel())
    params.update()
    return mi.load_dict({"type": "scene", "visual": mesh})


class RayCaster:
    """Casts batches of rays at the visual mesh of one scene."""

    def __init__(self, meshes: SceneMeshes):
        self.meshes = meshes
        self.scene = build_scene(meshes)
        self.face_normals = np.asarray(meshes.visual.face_normals, dtype=np.float64)

    @staticmethod
    def _ray(origins: np.ndarray, dirs: np.ndarray, max_t: np.ndarray | None = None):
        import mitsuba as mi

        o = np.ascontiguousarray(np.asarray(origins, np.float32).T)
        d = np.ascontiguousarray(np.asarray(dirs, np.float32).T)
        ray = mi.Ray3f(mi.Point3f(o[0], o[1], o[2]), mi.Vector3f(d[0], d[1], d[2]))
        if max_t is not None:
            ray.maxt = mi.Float(np.ascontiguousarray(max_t, np.float32))
        return ray

    def _batches(self, origins, dirs, max_t=None):
        dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
        origins = np.broadcast_to(np.asarray(origins, np.float64), dirs.shape)
        if max_t is not None:
            max_t = np.broadcast_to(np.asarray(max_t, np.float64), (len(dirs),))
        for s in range(0, len(dirs), MAX_RAYS_PER_CALL):
            e = min(len(dirs), s + MAX_RAYS_PER_CALL)
            yield s, e, self._ray(origins[s:e], dirs[s:e], None if max_t is None else max_t[s:e])

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """Closest hit of each ray; ``origins`` [n, 3] or [3], ``dirs`` [n, 3] unit, world frame."""
        n = len(np.reshape(dirs, (-1, 3)))
        t = np.full(n, np.inf)
        face = np.full(n, -1, np.int64)
        for s, e, ray in self._batches(origins, dirs):
            pi = self.scene.ray_intersect_preliminary(ray, coherent=True)
            valid = np.array(pi.is_valid(), dtype=bool)
            t[s:e] = np.where(valid, np.array(pi.t, dtype=np.float64), np.inf)
            face[s:e] = np.where(valid, np.array(pi.prim_index, dtype=np.int64), -1)
        normal = np.zeros((n, 3))
        hit = face >= 0
        normal[hit] = self.face_normals[face[hit]]
        return Hits(t, face, normal)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, max_t: float | np.ndarray | None = None
                 ) -> np.ndarray:
        """[n] bool: a surface lies on each ray closer than ``max_t`` (m; none: any distance)."""
        n = len(np.reshape(dirs, (-1, 3)))
        out = np.zeros(n, bool)
        for s, e, ray in self._batches(origins, dirs, max_t):
            out[s:e] = np.array(self.scene.ray_test(ray), dtype=bool)
        return out


class RayBundle:
    """A fixed set of unit ray directions in a sensor frame, kept as drjit arrays.

    :meth:`cast` rotates them by a pose given as opaque drjit values, so casting the bundle from
    frame after frame reuses one compiled kernel.
    """

    def __init__(self, caster: "RayCaster", local_dirs: np.ndarray):
        import drjit as dr
        import mitsuba as mi

        self.caster, self.dr, self.mi = caster, dr, mi
        d = np.asarray(local_dirs, np.float32).reshape(-1, 3)
        self.local = mi.Vector3f(*[mi.Float(np.ascontiguousarray(d[:, k])) for k in range(3)])
        dr.make_opaque(self.local)

    def world_rays(self, position_m: np.ndarray, rotation_matrix: np.ndarray):
        """(origin Point3f, direction Vector3f) of the bundle from a pose (sensor into world)."""
        dr, mi = self.dr, self.mi
        o = mi.Point3f(*[dr.opaque(mi.Float, float(x)) for x in np.ravel(position_m)])
        r = [[dr.opaque(mi.Float, float(rotation_matrix[i, j])) for j in range(3)] for i in range(3)]
        lo = self.local
        return o, mi.Vector3f(*[r[i][0] * lo.x + r[i][1] * lo.y + r[i][2] * lo.z for i in range(3)])

    def cast(self, position_m: np.ndarray, rotation_matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """-> (t [n] float32 m, inf where no hit; face [n] int64, -1 where no hit)."""
        dr, mi = self.dr, self.mi
        o, d = self.world_rays(position_m, rotation_matrix)
        pi = self.caster.scene.ray_intersect_preliminary(mi.Ray3f(o, d), coherent=True)
        valid = pi.is_valid()
        t = dr.select(valid, pi.t, dr.inf)
        face = dr.select(valid, mi.Int32(pi.prim_index), -1)
        dr.eval(t, face)
        return np.array(t, dtype=np.float32), np.array(face, dtype=np.int64)
