"""First-order wedge and edge diffraction for the one-pass CKM solver, the way Sionna RT's
RadioMapSolver computes it, deposited into the same per-cell moments as the shoot-and-bounce rays.

Per transmitter, after Sionna RT 2.2 (``RadioMapSolver._shoot_and_bounce`` and
``_evaluate_first_order_diffraction``):

1. **Lit wedges.** The lattice rays' first hits name the triangles the transmitter sees; their
   convex edges (Sionna's ``wedge_geometry``: two faces, interior angle below pi) and, with
   ``edge_diffraction``, their free edges are the candidates, each once (the same pair of end
   points, rounded to :data:`WEDGE_KEY_M`, on the same shape). Flat edges do not diffract.
2. **Samples on the wedges.** ``num_samples`` points are spread over the wedges in proportion to
   their length (largest remainders first, at least one each), each with a direction on its
   Keller cone (the exterior angle, lit region included); the ``k``-th of a wedge's ``n`` samples
   sits at ``u = (k + 1/2) / n`` along it and ``v = frac(k / golden ratio)`` round the cone, a
   rank-1 lattice, so the result is deterministic. A sample counts where the transmitter sees
   the point, also from 5 cm off the edge (Sionna's guard against leaks through the faces).
3. **Flux of a sample.** Its field is Sionna's UTD evaluation of the wedge's radio material
   (``RadioMapSolver._evaluate_radio_material_diffraction``, spreading factor included) at
   ``s_ref``, where the diffracted ray first meets the scene or a grid plane; its weight is
   Sionna's change of variables from (position on the edge, angle on the cone) to the area of a
   plane normal to the ray at ``s_ref`` (``RadioMap._diffraction_integration_weight``), times edge
   length and cone angle over the wedge's sample count. ``|E|^2`` falls as
   ``1 / (s s' (s + s'))`` and that area grows as ``s (s + s') / s'``: their product, the flux,
   is the same all along the ray (the transition function's dependence on ``s`` aside: hence
   ``s_ref`` at the first crossing).
4. **On through the specular tracer.** The ray is handed to :meth:`Tracer.propagate` with its
   field scaled so that the tracer's ``4 pi / num_rays`` becomes that flux: it deposits
   ``|E|^2 weight / |cos theta_z|`` on every plane it crosses (RadioMapSolver's estimator for
   diffracted rays on the first crossing) and reflects specularly up to ``max_depth - 1`` more
   times.

Delays and directions of a deposit are those of the path through the sampled point to the cell
centre ``c``: ``tau = (|q - tx| + |c - q|) / c0``, arrival from ``q``, departure towards ``q``.
Moving ``q`` along the edge to the centre's own diffraction point changes the length only at
second order (Fermat: the diffracted path is stationary along the edge), so this is the centre's
delay to first order, as the image-source correction is for reflections.

Traced: (diffraction) and (diffraction, reflection...) paths. Not traced: a reflection before the
diffraction and second-order diffraction (RadioMapSolver traces neither; PathSolver has the
first); docs/ckm-one-pass.md gives the measured effect.
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.ckm.shoot_bounce import Grid, fibonacci_directions

__all__ = ["DiffractionSampler", "WEDGE_KEY_M"]

WEDGE_KEY_M = 1e-3      # end points closer than this are the same edge
LEAK_OFFSET_M = 5e-2    # Sionna's offset of the visibility-test point off the wedge
SPAWN_OFFSET_M = 1e-3   # diffracted rays start this far off the edge
MAX_REFERENCE_DISTANCE_M = 1e4
DIFFRACTED_RAY_KEY = 0x9E3779B9  # diffracted rays' random-number keys: sample index plus this  # a diffracted ray meeting nothing: its field is taken this far out
_GOLDEN_RATIO = (1.0 + 5.0**0.5) / 2.0
_PLASTIC = 1.32471795724474602596  # R2 sequence constant: the wedge-picking sample of step 1


class DiffractionSampler:
    """First-order diffraction of one transmitter over a :class:`Grid`: finds the lit wedges, then
    hands the deposits of ``num_samples`` samples to ``sink(deposits, line_of_sight=False)`` in the
    dict form of :class:`simart_pipeline.ckm.shoot_bounce.Tracer`."""

    def __init__(self, radio, tracer, tx_position_m, tx_rotation: np.ndarray, grid: Grid, reflections_after: int,
                 edge_diffraction: bool):
        import drjit as dr
        import mitsuba as mi

        self.dr, self.mi = dr, mi
        self.radio, self.scene = radio, radio.scene.mi_scene
        self.tx = np.asarray(tx_position_m, np.float64)
        self.rot = np.asarray(tx_rotation, np.float64)
        self.grid = grid
        self.tracer = tracer
        self.reflections_after = int(reflections_after)
        self.edge_diffraction = bool(edge_diffraction)
        self.wedges = None
        self.num_wedges = 0

    # -- step 1 ---------------------------------------------------------------------------------
    def find_wedges(self, num_rays: int, batch_rays: int) -> int:
        """Wedges of the triangles that ``num_rays`` lattice rays from the transmitter hit; returns how many."""
        dr, mi = self.dr, self.mi
        from sionna.rt.constants import EPSILON_FLOAT
        from sionna.rt.utils.wedges import wedge_geometry

        tx = mi.Point3f(*(float(v) for v in self.tx))
        hit = []
        for start in range(0, int(num_rays), int(batch_rays)):
            stop = min(start + int(batch_rays), int(num_rays))
            d = fibonacci_directions(start, stop, int(num_rays))
            pi = self.scene.ray_intersect_preliminary(mi.Ray3f(dr.zeros(mi.Point3f, stop - start) + tx, d), False)
            idx = dr.compress(pi.is_valid())
            ids = dr.gather(mi.UInt32, dr.reinterpret_array(mi.UInt32, pi.shape), idx)
            prim = dr.gather(mi.UInt32, pi.prim_index, idx)
            dr.eval(ids, prim)
            hit.append(np.unique((ids.numpy().astype(np.uint64) << np.uint64(32)) | prim.numpy().astype(np.uint64)))
        tri = np.unique(np.concatenate(hit)) if hit else np.zeros(0, np.uint64)
        if len(tri) == 0:
            self.num_wedges = 0
            return 0
        shape_id = np.repeat((tri >> np.uint64(32)).astype(np.uint32), 3)
        prim = np.repeat((tri & np.uint64(0xFFFFFFFF)).astype(np.uint32), 3)
        local_edge = np.tile(np.arange(3, dtype=np.uint32), len(tri))
        mesh = mi.MeshPtr(dr.reinterpret_array(mi.ShapePtr, mi.UInt32(shape_id)))
        w = wedge_geometry(mesh, mi.UInt32(prim), mi.UInt32(local_edge))
        mid = w.o + 0.5 * w.length * w.e_hat
        w.swap_faces(dr.dot(mid - tx, w.n0) > 0)  # the transmitter sees the 0-face, as in Sionna
        k = tx - mid
        valid = (w.length > 0) & ((dr.dot(k, w.n0) > EPSILON_FLOAT) | (dr.dot(k, w.nn) > EPSILON_FLOAT))
        valid &= dr.dot(w.n0, w.nn) < 1.0 - 1e-4  # a flat edge (two coplanar faces) does not diffract
        if not self.edge_diffraction:
            valid &= w.primn != w.prim0
        cols = [mi.UInt32(shape_id), w.prim0, w.primn, w.local_edge]
        cols += [getattr(w, k)[c] for k in ("o", "e_hat", "n0", "nn") for c in range(3)] + [w.length]
        dr.eval(valid, *cols)
        keep = np.asarray(valid.numpy(), bool)
        a = [np.asarray(c.numpy())[keep] for c in cols]
        o_np = np.stack(a[4:7], -1).astype(np.float64)
        e_np = o_np + np.stack(a[7:10], -1) * a[-1][:, None].astype(np.float64)
        first_o = _lex_less(o_np, e_np)[:, None]  # the key does not depend on the edge's direction
        lo, hi = np.where(first_o, o_np, e_np), np.where(first_o, e_np, o_np)
        key = np.column_stack([a[0].astype(np.int64), np.round(np.column_stack([lo, hi]) / WEDGE_KEY_M).astype(np.int64)])
        _, first = np.unique(key, axis=0, return_index=True)  # sorted keys: a fixed order
        self._wedge_np = [c[first] for c in a]
        self.num_wedges = len(first)
        return self.num_wedges

    def _wedge_geometry(self, index: np.ndarray):
        dr, mi = self.dr, self.mi
        from sionna.rt.utils.wedges import WedgeGeometry

        c = [a[index] for a in self._wedge_np]
        f = [mi.Float(np.asarray(v, np.float32)) for v in c[4:]]
        shape = mi.MeshPtr(dr.reinterpret_array(mi.ShapePtr, mi.UInt32(c[0])))
        return WedgeGeometry(shape, mi.UInt32(c[1]), mi.UInt32(c[2]), mi.UInt32(c[3]),
                             mi.Point3f(*f[0:3]), mi.Vector3f(*f[3:6]), f[12],
                             mi.Normal3f(*f[6:9]), mi.Normal3f(*f[9:12]))

    # -- step 2 ---------------------------------------------------------------------------------
    def allocation(self, num_samples: int) -> np.ndarray:
        """Samples per wedge: proportional to length, largest remainders, at least one each."""
        length = self._wedge_np[-1].astype(np.float64)
        share = num_samples * length / length.sum()
        n = np.floor(share).astype(np.int64)
        left = int(num_samples - n.sum())
        if left > 0:
            n[np.argsort(-(share - n), kind="stable")[:left]] += 1
        return np.maximum(n, 1)

    def trace(self, num_samples: int, batch: int, sink) -> None:
        """Samples on the wedges found by :meth:`find_wedges`, deposits handed to ``sink``."""
        if self.num_wedges == 0 or num_samples <= 0:
            return
        counts = self.allocation(int(num_samples))
        wedge = np.repeat(np.arange(self.num_wedges), counts)
        k = np.arange(len(wedge)) - np.repeat(np.cumsum(counts) - counts, counts)  # index within wedge
        for start in range(0, len(wedge), int(batch)):
            sl = slice(start, start + int(batch))
            w, kk = wedge[sl], k[sl].astype(np.float64)
            n_w = counts[w].astype(np.float64)
            u = (kk + 0.5) / n_w
            v = np.mod(kk / _GOLDEN_RATIO, 1.0)
            self._trace_batch(w, u, v, n_w, np.arange(start, start + len(w)), sink)

    def _trace_batch(self, w_index, u, v, n_w, sample_index, sink) -> None:
        dr, mi = self.dr, self.mi
        from sionna.rt.antenna_pattern import antenna_pattern_to_world_implicit
        from sionna.rt.constants import MIN_SEGMENT_LENGTH
        from sionna.rt.radio_map_solvers.radio_map import RadioMap
        from sionna.rt.radio_map_solvers.radio_map_solver import RadioMapSolver
        from sionna.rt.utils.jones import implicit_basis_vector
        from sionna.rt.utils.ray_tracing import sample_keller_cone_with_measure, spawn_ray_to

        wedges = self._wedge_geometry(w_index)
        tx = dr.zeros(mi.Point3f, len(w_index)) + mi.Point3f(*(float(x) for x in self.tx))
        q = wedges.o + mi.Float(u.astype(np.float32)) * wedges.length * wedges.e_hat
        ki = dr.normalize(q - tx)
        free_edge = wedges.primn == wedges.prim0
        ne = dr.select(free_edge, mi.Vector3f(0), dr.normalize(wedges.n0 + wedges.nn))
        q_off = q + LEAK_OFFSET_M * ne
        s_prime = dr.norm(q - tx)
        ok = ~self.scene.ray_test(spawn_ray_to(tx, q)) & ~self.scene.ray_test(spawn_ray_to(tx, q_off))
        ok &= s_prime > MIN_SEGMENT_LENGTH
        ko, measure = sample_keller_cone_with_measure(wedges.e_hat, wedges.n0, wedges.nn,
                                                      mi.Float(v.astype(np.float32)), ki, True)
        # leave the edge by a millimetre into the exterior (ne + ko points there for any ko on the
        # cone), else the first intersection is the wedge's own face at t ~ 0
        ray = mi.Ray3f(q + SPAWN_OFFSET_M * (ne + ko), ko)
        # the field is evaluated where the diffracted ray first meets the scene or a grid plane
        # (the UTD transition function depends on that distance; the flux does not, see module doc)
        first = self.scene.ray_intersect_preliminary(ray, False)
        s_ref = dr.select(first.is_valid(), first.t, dr.inf)
        for height in self.grid.heights:
            t_h = (float(height) - ray.o.z) / ray.d.z
            s_ref = dr.select((t_h > 0) & (t_h < s_ref), t_h, s_ref)
        s_ref = dr.clip(s_ref, 2.0 * MIN_SEGMENT_LENGTH, MAX_REFERENCE_DISTANCE_M)
        dr.eval(ok, s_ref)
        idx = dr.compress(ok)
        if dr.width(idx) == 0:
            return
        take = lambda x: dr.gather(type(x), x, idx)  # noqa: E731
        wq = dr.gather(type(wedges), wedges, idx)
        qq, kki, kko, sp, sr, o = take(q), take(ki), take(ko), take(s_prime), take(s_ref), take(ray.o)
        n = dr.width(idx)
        pattern = self.radio.scene.tx_array.antenna_pattern.patterns[0]
        to_world = mi.Matrix3f(*(float(self.rot[r, c]) for r in range(3) for c in range(3)))
        e_in = antenna_pattern_to_world_implicit(pattern, to_world, kki, direction="out")
        e_out = RadioMapSolver._evaluate_radio_material_diffraction(
            None, mi.ShapePtr(wq.shape), wq, qq, kki, kko, [e_in], sr, sp, dr.full(mi.Bool, True, n))[0]
        # Sionna's change of variables from (position on the edge, angle on the cone) to the area
        # of a plane normal to the ray at s_ref: with the field there, the ray's flux
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.p, si.n = qq + sr * kko, mi.Normal3f(kko)
        area = RadioMap._diffraction_integration_weight(None, wq, take(tx), qq, kko, si)
        area *= wq.length * take(measure) / mi.Float(n_w.astype(np.float32)[idx.numpy()])
        # The tracer deposits |E|^2 (4 pi / num_rays) / |cos| per crossing: scale the field so that
        # its solid-angle factor becomes this ray's area per sample
        scale = dr.sqrt(dr.maximum(area, 0.0) * (self.tracer.num_rays / (4.0 * np.pi)))
        e_s = implicit_basis_vector(kko)  # Sionna's implicit Jones basis: (e_s, k x e_s)
        e_p = dr.cross(kko, e_s)
        state = dict(o=o, d=kko, e_re=scale * (e_out.x * e_s + e_out.y * e_p),
                     e_im=scale * (e_out.z * e_s + e_out.w * e_p), length=sp,
                     # departure is towards q whatever the arrival: rank-one "mirror" columns
                     # (dep_k ko), so that the deposit's normalised M d_c is that direction
                     **{f"m{k}": kki[k] * kko for k in range(3)})
        if self.tracer.sampled:
            # diffuse reflection or refraction on: the tracer's random numbers are keyed by a ray
            # index (not a lattice ray's: offset), and the delay restarts at q (``anchor``: the
            # path length there), so a deposit's is |q - tx| + |c - q| exactly
            state.update(idx=mi.UInt32((sample_index[idx.numpy()] + DIFFRACTED_RAY_KEY) % 2**32),
                         anchor=sp)
        self.tracer.propagate(state, sink, self.reflections_after, from_transmitter=False)


def _lex_less(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise lexicographic ``a < b`` of ``[n, 3]`` arrays."""
    lt, eq = a < b, a == b
    return lt[:, 0] | (eq[:, 0] & (lt[:, 1] | (eq[:, 1] & lt[:, 2])))
