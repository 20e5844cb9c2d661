"""Ray casting against the visual mesh with Mitsuba 3 (the process's one Mitsuba variant).

The visual mesh becomes ONE Mitsuba mesh built from the arrays (no file round trip), so the
primitive index of a hit is the face index of :class:`SceneMeshes.visual` and indexes
``face_class`` / ``face_instance`` directly. The variant is whatever :func:`engine.init` selected
(the one Sionna RT uses); this module never sets a variant.

Rays go to Mitsuba as whole batches (a frame or several at once) of drjit arrays; results come
back as numpy arrays. Normals are the mesh's flat face normals, looked up by face index.
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
        normals = np.asarray(meshes.visual.face_normals, dtype=np.float64)
        self.face_normals = normals

    @staticmethod
    def _ray(origins: np.ndarray, dirs: np.ndarray, max_t: np.ndarray | float | None = None):
        import mitsuba as mi

        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(dirs, dtype=np.float32)
        ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        if max_t is not None:
            ray.maxt = mi.Float(np.broadcast_to(np.asarray(max_t, np.float32), (len(o),)).copy())
        return ray

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """Closest hit of each ray; ``origins`` and ``dirs`` [n, 3] in world (dirs unit length)."""
        origins = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        n = len(dirs)
        t = np.full(n, np.inf)
        face = np.full(n, -1, np.int64)
        for s in range(0, n, MAX_RAYS_PER_CALL):
            e = min(n, s + MAX_RAYS_PER_CALL)
            pi = self.scene.ray_intersect_preliminary(self._ray(origins[s:e], dirs[s:e]), coherent=True)
            valid = np.array(pi.is_valid(), dtype=bool)
            tt = np.array(pi.t, dtype=np.float64)
            prim = np.array(pi.prim_index, dtype=np.int64)
            t[s:e] = np.where(valid, tt, np.inf)
            face[s:e] = np.where(valid, prim, -1)
        normal = np.zeros((n, 3))
        hit = face >= 0
        normal[hit] = self.face_normals[face[hit]]
        return Hits(t, face, normal)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, max_t: float | np.ndarray | None = None
                 ) -> np.ndarray:
        """[n] bool: something lies on each ray before ``max_t`` (shadow rays)."""
        origins = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        n = len(dirs)
        out = np.zeros(n, bool)
        for s in range(0, n, MAX_RAYS_PER_CALL):
            e = min(n, s + MAX_RAYS_PER_CALL)
            mt = None if max_t is None or np.isscalar(max_t) and not np.isfinite(max_t) else (
                max_t if np.isscalar(max_t) else np.asarray(max_t)[s:e])
            out[s:e] = np.array(self.scene.ray_test(self._ray(origins[s:e], dirs[s:e], mt)), dtype=bool)
        return out


def offset_origins(points: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Push surface points off their surface (on the side ``dirs`` leave to) against self-hits."""
    side = np.sign(np.einsum("ij,ij->i", normals, dirs))[:, None]
    eps = 1e-3 + 1e-5 * np.abs(points).max(axis=1, keepdims=True)
    return points + normals * side * eps
