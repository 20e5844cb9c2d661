"""Pinhole cameras: RGB, z-depth, semantic class and instance id images by ray casting.

Optical frame ``<device>/<sensor>_optical``: z forward, x right, y down (REP 103). Intrinsics from
the image size and the horizontal field of view, square pixels, OpenCV convention (pixel ``(u, v)``
has its centre at integer coordinates, the image spans ``-0.5 .. width - 0.5``):

    fx = fy = (width / 2) / tan(hfov / 2),  cx = (width - 1) / 2,  cy = (height - 1) / 2

One ray per pixel centre. ``depth_m`` is the z-depth along the optical axis (the optical-frame z of
the hit point), not the ray length. The camera sees nothing beyond ``max_depth_m`` (a far clipping
plane on z-depth): there depth is NaN, the labels are 0 and the pixel shows the sky. Shading:
:mod:`simart_pipeline.sensing.weather`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
import xarray as xr
from scipy.spatial.transform import Rotation

from simart_pipeline.config import Camera
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.vocabulary import SemanticClass
from simart_pipeline.sensing import contract
from simart_pipeline.sensing.raycast import ActorView, RayBundle, RayCaster
from simart_pipeline.sensing.weather import WeatherModel

# Linear albedo per semantic class (r, g, b).
CLASS_ALBEDO = {
    SemanticClass.UNLABELED: (0.50, 0.50, 0.50),
    SemanticClass.GROUND: (0.22, 0.30, 0.14),
    SemanticClass.ROAD: (0.16, 0.16, 0.17),
    SemanticClass.BUILDING: (0.55, 0.50, 0.45),
    SemanticClass.VEGETATION: (0.10, 0.25, 0.08),
    SemanticClass.WATER: (0.05, 0.10, 0.15),
    SemanticClass.VEHICLE: (0.50, 0.10, 0.10),
    SemanticClass.UAV: (0.60, 0.55, 0.10),
    SemanticClass.PEDESTRIAN: (0.45, 0.30, 0.35),
}
SHADING_MODEL = ("Lambert: per-class albedo (per-instance tint) x (ambient + sun with ray-cast shadows "
                 "+ camera lamp cone, inverse square + street lamps over the roads, inverse square, "
                 "ray-cast shadows) + the lights of aircraft actors (emitted), distance haze, fixed exposure, sRGB 8-bit, "
                 "rain streaks and Gaussian pixel noise after tone mapping")


def intrinsics(cam: Camera) -> np.ndarray:
    """3x3 camera matrix K (px) of a pinhole camera, OpenCV pixel-centre convention."""
    f = (cam.width_px / 2) / np.tan(np.deg2rad(cam.horizontal_fov_deg) / 2)
    return np.array([[f, 0.0, (cam.width_px - 1) / 2],
                     [0.0, f, (cam.height_px - 1) / 2],
                     [0.0, 0.0, 1.0]])


def pixel_rays(cam: Camera) -> np.ndarray:
    """[H * W, 3] unit ray directions in the optical frame, row-major (v, u)."""
    k = intrinsics(cam)
    v, u = np.meshgrid(np.arange(cam.height_px, dtype=np.float64),
                       np.arange(cam.width_px, dtype=np.float64), indexing="ij")
    d = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], axis=-1)
    d = d.reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser: a stable integer hash (numpy uint64, wraps)."""
    x = np.asarray(x).astype(np.uint64)
    with np.errstate(over="ignore"):
        x = (x + np.uint64(0x9E3779B97F4A7C15))
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        x = x ^ (x >> np.uint64(31))
    return x


def face_albedo(meshes: SceneMeshes) -> np.ndarray:
    """[num_faces, 3] linear albedo: the class albedo times a stable per-instance tint."""
    return albedo_of(meshes.face_class, meshes.face_instance)


def albedo_of(face_class: np.ndarray, face_instance: np.ndarray) -> np.ndarray:
    """[n, 3] linear albedo of faces: class albedo x a stable per-instance brightness, and a
    per-instance colour tint for buildings and actors (two cars are told apart by colour)."""
    table = np.tile(np.asarray(CLASS_ALBEDO[SemanticClass.UNLABELED]), (256, 1))
    for c, rho in CLASS_ALBEDO.items():
        table[int(c)] = rho
    base = table[np.asarray(face_class).astype(np.int64)]
    h = _mix64(face_instance)
    lum = 0.9 + 0.2 * ((h & np.uint64(0xFFFF)).astype(np.float64) / 0xFFFF)
    tint = np.stack([0.9 + 0.2 * (((h >> np.uint64(s)) & np.uint64(0xFFFF)).astype(np.float64) / 0xFFFF)
                     for s in (16, 32, 48)], axis=-1)
    tinted = np.isin(face_class, [SemanticClass.BUILDING, SemanticClass.VEHICLE, SemanticClass.UAV,
                                  SemanticClass.PEDESTRIAN])[:, None]
    return base * lum[:, None] * np.where(tinted, tint, 1.0)


@dataclass(frozen=True)
class StreetLamps:
    """Street lamps on a square lattice: ``position_m [ny * nx, 3]``, ``present [ny * nx]``; cell
    ``(i, j)`` spans ``x0 + i * spacing .. x0 + (i + 1) * spacing`` (likewise ``y``)."""

    x0_m: float
    y0_m: float
    spacing_m: float
    nx: int
    ny: int
    position_m: np.ndarray
    present: np.ndarray


def street_lamps(meshes: SceneMeshes, spacing_m: float, height_m: float, seed: int = 0) -> StreetLamps | None:
    """One lamp per lattice cell that holds road: ``height_m`` above the road point nearest the
    cell's centre (road points: area-uniform samples of the visual mesh's road faces, one per
    m^2 up to 10^6, seeded). None when the scene has no road."""
    road = meshes.face_class == SemanticClass.ROAD
    if not road.any():
        return None
    roads = trimesh.Trimesh(meshes.visual.vertices, meshes.visual.faces[road], process=False)
    count = int(np.clip(roads.area, 1, 1_000_000))
    pts, _ = trimesh.sample.sample_surface(roads, count, seed=seed)
    x0, y0 = (np.floor(pts[:, k].min() / spacing_m) * spacing_m for k in (0, 1))
    ci = np.floor((pts[:, 0] - x0) / spacing_m).astype(np.int64)
    cj = np.floor((pts[:, 1] - y0) / spacing_m).astype(np.int64)
    nx, ny = int(ci.max()) + 1, int(cj.max()) + 1
    cell = cj * nx + ci
    d2 = (pts[:, 0] - x0 - (ci + 0.5) * spacing_m) ** 2 + (pts[:, 1] - y0 - (cj + 0.5) * spacing_m) ** 2
    order = np.lexsort((d2, cell))
    cells, first = np.unique(cell[order], return_index=True)
    position = np.zeros((nx * ny, 3))
    position[cells] = pts[order[first]] + np.array([0.0, 0.0, height_m])
    present = np.zeros(nx * ny, bool)
    present[cells] = True
    return StreetLamps(float(x0), float(y0), float(spacing_m), nx, ny, position, present)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    c = np.clip(linear, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


class _FrameRenderer:
    """Renders one camera frame at a time in drjit (ray casting, shading and tone mapping fused).

    Per-frame values (pose) go in as opaque arrays, so every frame reuses the same compiled kernel.
    """

    def __init__(self, caster: RayCaster, cam: Camera, wx: WeatherModel):
        import drjit as dr
        import mitsuba as mi

        self.dr, self.mi, self.caster, self.cam, self.wx = dr, mi, caster, cam, wx
        self.bundle = RayBundle(caster, pixel_rays(cam))
        self.normals = mi.Float(np.ascontiguousarray(caster.face_normals, np.float32).ravel())
        self.albedo = mi.Float(np.ascontiguousarray(face_albedo(caster.meshes), np.float32).ravel())
        dr.make_opaque(self.normals, self.albedo)
        if caster.actors is not None:
            layer = caster.actors
            self.actor_albedo = mi.Float(np.ascontiguousarray(
                albedo_of(layer.face_class, layer.face_instance), np.float32).ravel())
            lights = (np.asarray(layer.face_class) == SemanticClass.UAV)[:, None] \
                * np.asarray(wx.aircraft_light_radiance_rgb, np.float32)[None, :]
            self.actor_emission = mi.Float(np.ascontiguousarray(lights, np.float32).ravel())
            dr.make_opaque(self.actor_albedo, self.actor_emission)
        self.lamps = street_lamps(caster.meshes, wx.street_lamp_spacing_m, wx.street_lamp_height_m) \
            if wx.has_street_lamps else None
        if self.lamps is not None:
            self.lamp_position = mi.Float(np.ascontiguousarray(self.lamps.position_m, np.float32).ravel())
            self.lamp_present = mi.Float(self.lamps.present.astype(np.float32))
            dr.make_opaque(self.lamp_position, self.lamp_present)

    def render(self, position_m: np.ndarray, rot: np.ndarray):
        """-> display-space rgb [P, 3] float32 in 0..1, z-depth [P] (inf: none), face [P] (-1: none)."""
        dr, mi, wx = self.dr, self.mi, self.wx
        vec = lambda v: mi.Vector3f(*[float(x) for x in v])  # noqa: E731 (weather constants)
        o, d = self.bundle.world_rays(position_m, rot)
        do = self.bundle.local  # the rays in the optical frame
        t, hit_face = self.caster.closest(mi.Ray3f(o, d))
        z = t * do.z  # do.z = cosine between the ray and the optical axis
        valid = (hit_face >= 0) & (z <= self.cam.max_depth_m)
        n_static = self.caster.num_static_faces
        on_actor = valid & (hit_face >= n_static)
        on_static = valid & ~on_actor
        face = mi.UInt32(dr.select(on_static, hit_face, 0))
        n = dr.gather(mi.Vector3f, self.normals, face, on_static)
        albedo = dr.gather(mi.Vector3f, self.albedo, face, on_static)
        if self.caster.actors is not None:
            layer = self.caster.actors
            self.actor_normals = mi.Float(np.ascontiguousarray(layer.face_normals, np.float32).ravel())
            dr.make_opaque(self.actor_normals)
            actor_face = mi.UInt32(dr.select(on_actor, hit_face - n_static, 0))
            n = dr.select(on_actor, dr.gather(mi.Vector3f, self.actor_normals, actor_face, on_actor), n)
            albedo = dr.select(on_actor, dr.gather(mi.Vector3f, self.actor_albedo, actor_face, on_actor), albedo)
        n = dr.select(dr.dot(n, d) > 0, -n, n)  # the side the ray sees
        irr = vec(wx.ambient_rgb)
        p = o + dr.select(valid, t, 0.0) * d
        eps = 1e-3 + 1e-5 * dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))
        if wx.has_sun:
            s = mi.Vector3f(*[float(x) for x in wx.sun_direction_enu()])
            ndots = dr.dot(n, s)
            lit = valid & (ndots > 0)
            shadow = self.caster.blocked(mi.Ray3f(p + n * eps, s), lit)
            irr += vec(wx.sun_irradiance_rgb) * dr.select(lit & ~shadow, ndots, 0.0)
        if self.lamps is not None:  # the lamps of the 2 x 2 lattice cells around the point
            lp = self.lamps
            i0 = mi.Int32(dr.floor((p.x - lp.x0_m) / lp.spacing_m - 0.5))
            j0 = mi.Int32(dr.floor((p.y - lp.y0_m) / lp.spacing_m - 0.5))
            for di, dj in ((0, 0), (1, 0), (0, 1), (1, 1)):
                ci, cj = i0 + di, j0 + dj
                inside = valid & (ci >= 0) & (ci < lp.nx) & (cj >= 0) & (cj < lp.ny)
                k = mi.UInt32(dr.select(inside, cj * lp.nx + ci, 0))
                lamp = dr.gather(mi.Point3f, self.lamp_position, k, inside)
                present = inside & (dr.gather(mi.Float, self.lamp_present, k, inside) > 0.5)
                v = lamp - p
                r2 = dr.squared_norm(v)
                r = dr.sqrt(r2)
                l_dir = v / dr.maximum(r, 1e-6)
                cos_l = dr.dot(n, l_dir)
                lit = present & (cos_l > 0)
                ray = mi.Ray3f(p + n * eps, l_dir)
                ray.maxt = dr.maximum(r - 2 * eps, 0.0)
                shadow = self.caster.blocked(ray, lit)
                irr += vec(wx.street_lamp_intensity_rgb) * dr.select(lit & ~shadow, cos_l / dr.maximum(r2, 1.0), 0.0)
        if wx.has_lamp:
            c_in = float(np.cos(np.deg2rad(wx.lamp_cone_half_angle_deg)))
            c_out = float(np.cos(np.deg2rad(wx.lamp_cone_half_angle_deg + wx.lamp_cone_falloff_deg)))
            cone = dr.clip((do.z - c_out) / max(c_in - c_out, 1e-9), 0.0, 1.0)
            cos_inc = dr.clip(-dr.dot(n, d), 0.0, 1.0)
            irr += vec(wx.lamp_intensity_rgb) * (cone * cos_inc / dr.square(dr.maximum(t, 0.1)))
        rad = albedo * irr
        if self.caster.actors is not None and max(wx.aircraft_light_radiance_rgb) > 0:
            rad += dr.gather(mi.Vector3f, self.actor_emission, actor_face, on_actor)
        fog = dr.exp(-dr.select(valid, t, 0.0) / wx.visibility_m)
        rad = rad * fog + vec(wx.haze_rgb) * (1.0 - fog)
        w = dr.clip(d.z, 0.0, 1.0)
        sky = vec(wx.sky_horizon_rgb) * (1.0 - w) + vec(wx.sky_zenith_rgb) * w
        c = dr.clip(dr.select(valid, rad, sky) * wx.exposure, 0.0, 1.0)
        c = dr.select(c <= 0.0031308, 12.92 * c, 1.055 * dr.power(c, 1 / 2.4) - 0.055)  # sRGB
        z = dr.select(valid, z, dr.inf)
        fid = dr.select(valid, hit_face, -1)
        dr.eval(c, z, fid)
        return (np.array(c, dtype=np.float32).T, np.array(z, dtype=np.float32),
                np.array(fid, dtype=np.int64))


def _rain_streaks(img: np.ndarray, wx: WeatherModel, rng: np.random.Generator) -> None:
    """Draw the weather's rain streaks into one float image [H, W, 3] in 0..1 (display space)."""
    h, w = img.shape[:2]
    count = rng.poisson(wx.rain_streaks_per_mpx * h * w / 1e6)
    if count == 0 or wx.rain_streak_alpha <= 0:
        return
    length = np.maximum(2.0, wx.rain_streak_length_frac * h * rng.uniform(0.6, 1.4, count))
    slant = np.deg2rad(wx.rain_streak_slant_deg + rng.normal(0.0, 2.0, count))
    x0 = rng.uniform(0, w, count)
    y0 = rng.uniform(-0.2 * h, h, count)
    k = np.arange(int(np.ceil(length.max())))
    on = k[None, :] < length[:, None]
    xs = np.rint(x0[:, None] - k[None, :] * np.sin(slant)[:, None]).astype(np.int64)
    ys = np.rint(y0[:, None] + k[None, :] * np.cos(slant)[:, None]).astype(np.int64)
    on &= (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    xs, ys = xs[on], ys[on]
    streak = srgb_encode(np.asarray(wx.rain_streak_rgb))
    img[ys, xs] = (1 - wx.rain_streak_alpha) * img[ys, xs] + wx.rain_streak_alpha * streak


def actor_ground_truth(view: ActorView, i: int, inst: np.ndarray, k: np.ndarray, position_m: np.ndarray,
                       rot: np.ndarray) -> dict[str, np.ndarray]:
    """Ground truth of every actor in one frame: visible pixel count and box (from the rendered
    instance image ``inst`` [H, W]), the box of its projected vertices, its distance (m)."""
    a = len(view.actors)
    count = np.zeros(a, np.int32)
    vis_box = np.full((a, 4), np.nan, np.float32)
    proj_box = np.full((a, 4), np.nan, np.float32)
    dist = np.zeros(a)
    for j, act in enumerate(view.actors):
        vv, uu = np.nonzero(inst == act.instance_id)
        count[j] = len(uu)
        if len(uu):
            vis_box[j] = (uu.min(), vv.min(), uu.max(), vv.max())
        world = view.poses.to_world(j, i, act.body.mesh.vertices)
        centre = view.poses.to_world(j, i, act.body.mesh.bounds.mean(axis=0))
        dist[j] = np.linalg.norm(centre - position_m)
        cam = (world - position_m) @ rot  # optical frame (rot: optical into world)
        if np.all(cam[:, 2] > 1e-6):
            u = k[0, 0] * cam[:, 0] / cam[:, 2] + k[0, 2]
            v = k[1, 1] * cam[:, 1] / cam[:, 2] + k[1, 2]
            proj_box[j] = (u.min(), v.min(), u.max(), v.max())
    return {"pixel_count": count, "visible_box_px": vis_box, "projected_box_px": proj_box, "distance_m": dist}


def render_camera(caster: RayCaster, cam: Camera, times_ns: np.ndarray, position_m: np.ndarray,
                  rotation: Rotation, wx: WeatherModel, rng: np.random.Generator,
                  actors: ActorView | None = None) -> xr.Dataset:
    """Render every frame of one camera.

    :param position_m: [n, 3] optical-frame origin in world at each frame instant.
    :param rotation: n rotations of the optical frame into world.
    :param actors: the actors at the frame instants (``caster.actors`` holds their layer).
    """
    n_t = len(times_ns)
    h, w = cam.height_px, cam.width_px
    frame = _FrameRenderer(caster, cam, wx)
    k = intrinsics(cam)
    truth = []
    mats = rotation.as_matrix().reshape(n_t, 3, 3)
    position_m = np.asarray(position_m, np.float64).reshape(n_t, 3)
    rgb = np.zeros((n_t, h, w, 3), np.uint8)
    depth = np.full((n_t, h, w), np.nan, np.float32)
    sem = np.zeros((n_t, h, w), np.uint8)
    inst = np.zeros((n_t, h, w), np.int64)
    for i in range(n_t):  # in time order: the noise draws are the same however frames are split
        if actors is not None:
            actors.place(caster.actors, i, position_m[i], cam.max_depth_m)
        disp, z, face = frame.render(position_m[i], mats[i])
        hit = face >= 0
        depth[i] = np.where(hit, z, np.nan).reshape(h, w)
        cls, ids = caster.face_labels(face)
        sem[i], inst[i] = cls.reshape(h, w), ids.reshape(h, w)
        if actors is not None:
            truth.append(actor_ground_truth(actors, i, inst[i], k, position_m[i], mats[i]))
        img = disp.reshape(h, w, 3)
        _rain_streaks(img, wx, rng)
        dn = img * np.float32(255.0)
        if wx.pixel_noise_std_dn > 0:
            dn += rng.standard_normal(dn.shape, dtype=np.float32) * np.float32(wx.pixel_noise_std_dn)
        rgb[i] = np.clip(np.rint(dn), 0, 255).astype(np.uint8)

    actor_truth = None
    if actors is not None:
        actor_truth = {key: np.stack([f[key] for f in truth]) for key in truth[0]} if truth else {}
        actor_truth.update(names=[a.name for a in actors.actors],
                           instance_id=[a.instance_id for a in actors.actors],
                           semantic_class=[a.semantic_class for a in actors.actors])
    return contract.camera_stream(
        times_ns, rgb, position_m, rotation.as_quat().reshape(n_t, 4), camera_matrix=k, actor_truth=actor_truth,
        depth_m=depth, semantic_class=sem, instance_id=inst, max_depth_m=cam.max_depth_m,
        shading_model=SHADING_MODEL, source_encoding="none: rendered",
        model=dict(horizontal_fov_deg=cam.horizontal_fov_deg, projection="pinhole, no lens distortion",
                   pose_model="pose at the frame instant (global shutter, no motion blur)"))
