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

Moving actors (:class:`ActorLayer`): every actor body of the scene is a second Mitsuba mesh in a
second scene whose vertices are rewritten frame by frame (no kernel is recompiled: measured 1.3 ms
per frame for the bundled car); a ray takes the nearer of the two hits. Face indices at or above
``num_static_faces`` are actor faces (``face - num_static_faces`` into the layer's tables).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simart_pipeline import engine
from simart_pipeline.scene.actors import HIDDEN_POINT_M
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



class ActorLayer:
    """The bodies of ``actors`` as one Mitsuba mesh placed frame by frame (:meth:`place`).

    Tables per actor face: ``face_actor`` (index into ``actors``), ``face_class``,
    ``face_instance``; the world face normals of the last placement in ``face_normals``.
    """

    def __init__(self, actors):
        engine.init()
        import mitsuba as mi

        self.actors = list(actors)
        meshes = [act.body.mesh for act in self.actors]
        # the bodies one after another: actor a owns vertices and faces [start[a], start[a + 1])
        self.vertex_start = np.cumsum([0] + [len(m.vertices) for m in meshes])
        self.face_start = np.cumsum([0] + [len(m.faces) for m in meshes])
        self.face_actor = np.repeat(np.arange(len(meshes)), np.diff(self.face_start))
        self.face_class = np.array([self.actors[a].semantic_class for a in self.face_actor], np.uint8)
        self.face_instance = np.array([self.actors[a].instance_id for a in self.face_actor], np.int64)
        self.body_normals = np.concatenate([np.asarray(m.face_normals) for m in meshes])
        self.body_vertices = np.concatenate([np.asarray(m.vertices, np.float64) for m in meshes])
        faces = np.concatenate([np.asarray(m.faces, np.int64) + s for m, s in zip(meshes, self.vertex_start)])
        mesh = mi.Mesh("actors", len(self.body_vertices), len(faces), has_vertex_normals=False,
                       has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(np.full(3 * len(self.body_vertices), 0.0, np.float32))
        params["faces"] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).ravel())
        params.update()
        self.scene = mi.load_dict({"type": "scene", "actors": mesh})
        self.params = mi.traverse(self.scene)
        self.face_normals = np.zeros_like(self.body_normals)

    def place(self, poses, i: int, hidden=()) -> None:
        """Put every actor at its pose of instant ``i`` of ``poses`` (:class:`ActorPoses`); the
        actors whose indices into ``actors`` are in ``hidden`` are left out."""
        import mitsuba as mi

        world = np.empty_like(self.body_vertices)
        normals = np.empty_like(self.body_normals)
        for a in range(len(self.actors)):
            v = slice(self.vertex_start[a], self.vertex_start[a + 1])
            f = slice(self.face_start[a], self.face_start[a + 1])
            if a in hidden:
                world[v] = HIDDEN_POINT_M
                normals[f] = 0.0
                continue
            world[v] = poses.to_world(a, i, self.body_vertices[v])
            normals[f] = poses.rotation[a][i].apply(self.body_normals[f])
        self.face_normals = normals
        self.params["actors.vertex_positions"] = mi.Float(np.ascontiguousarray(world, np.float32).ravel())
        self.params.update()


@dataclass
class ActorView:
    """The actors as one sensor sees them: their poses at the sensor's instants and the ones it
    never sees (its own platform's body, unless the mount says ``sees_own_body``)."""

    actors: list
    poses: object               # scene.actors.ActorPoses at the sensor's instants
    own: tuple[int, ...] = ()

    def place(self, layer: ActorLayer, i: int, sensor_position_m: np.ndarray, max_range_m: float) -> None:
        """Place the actors of instant ``i``; an actor whose bounding sphere lies wholly beyond the
        sensor's range is left out (exact: nothing of it could be seen)."""
        far = [a for a, act in enumerate(self.actors)
               if np.linalg.norm(self.poses.position_m[a, i] - sensor_position_m)
               > max_range_m + act.bounding_radius_m]
        layer.place(self.poses, i, hidden=set(self.own) | set(far))


class RayCaster:
    """Casts batches of rays at the visual mesh of one scene, and at its actors once
    :attr:`actors` holds an :class:`ActorLayer`."""

    def __init__(self, meshes: SceneMeshes):
        self.meshes = meshes
        self.scene = build_scene(meshes)
        self.face_normals = np.asarray(meshes.visual.face_normals, dtype=np.float64)
        self.num_static_faces = len(self.face_normals)
        self.actors: ActorLayer | None = None

    def face_labels(self, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(semantic class uint8, instance id int64) of hit faces; 0 where ``face`` is -1."""
        face = np.asarray(face)
        cls = np.zeros(face.shape, np.uint8)
        inst = np.zeros(face.shape, np.int64)
        st = (face >= 0) & (face < self.num_static_faces)
        cls[st], inst[st] = self.meshes.face_class[face[st]], self.meshes.face_instance[face[st]]
        if self.actors is not None:
            ac = face >= self.num_static_faces
            k = face[ac] - self.num_static_faces
            cls[ac], inst[ac] = self.actors.face_class[k], self.actors.face_instance[k]
        return cls, inst

    def closest(self, ray):
        """drjit (t, face) of the nearest hit among the scene and the placed actors (inf, -1: none);
        actor faces are numbered from :attr:`num_static_faces`."""
        import drjit as dr
        import mitsuba as mi

        pi = self.scene.ray_intersect_preliminary(ray, coherent=True)
        valid = pi.is_valid()
        t = dr.select(valid, pi.t, dr.inf)
        face = dr.select(valid, mi.Int32(pi.prim_index), -1)
        if self.actors is not None:
            pa = self.actors.scene.ray_intersect_preliminary(ray, coherent=True)
            nearer = pa.is_valid() & (pa.t < t)
            t = dr.select(nearer, pa.t, t)
            face = dr.select(nearer, mi.Int32(pa.prim_index) + self.num_static_faces, face)
        return t, face

    def blocked(self, ray, active):
        """drjit bool: the scene or a placed actor lies on ``ray`` (shadow rays)."""
        hit = self.scene.ray_test(ray, active=active)
        if self.actors is not None:
            hit = hit | self.actors.scene.ray_test(ray, active=active)
        return hit

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
        t, face = self.caster.closest(mi.Ray3f(o, d))
        dr.eval(t, face)
        return np.array(t, dtype=np.float32), np.array(face, dtype=np.int64)
