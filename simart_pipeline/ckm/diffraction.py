"""First-order wedge and edge diffraction for the one-pass CKM solver, the way Sionna RT's
RadioMapSolver computes it, deposited into the same per-cell moments as the shoot-and-bounce rays.

Per transmitter, after Sionna RT 2.2 (``RadioMapSolver._shoot_and_bounce`` and
``_evaluate_first_order_diffraction``):

1. **Lit wedges.** The lattice rays' first hits (collected by the specular tracer as it traces
   them, :meth:`Tracer.collect_lit`) name the triangles the transmitter sees; their convex edges
   (Sionna's ``wedge_geometry``: two faces, interior angle below pi) and, with
   ``edge_diffraction``, their free edges are the candidates, each once (the same pair of end
   points, rounded to :data:`WEDGE_KEY_M`, on the same shape). Flat edges do not diffract.
2. **Where samples count** (:meth:`DiffractionSampler.pilot`). :data:`PILOT_POINTS` points per
   pair find the stretch of the edge the source sees and where some of the cone points down to a
   grid plane; a point above every grid plane draws its direction from the cone's downward arc
   only (:func:`keller_cone`: a ray that leaves upwards comes down only off a downward-facing
   face, which extruded buildings do not have; on a roof edge that arc is a third of the cone).
   On Sionna's street canyon 35 % of the direct wedges' length and half of the reflected pairs'
   is seen by no point, and 42 % / 25 % of uniform samples could deposit at all.
3. **Samples on the wedges.** ``num_samples`` points are spread over the pairs in proportion to
   ``length x seen stretch x mean downward arc`` (largest remainders first, at least one for a
   pair the pilot found), each over its seen stretch, its direction on the (downward) arc; the
   ``k``-th of a pair's ``n`` samples sits at ``u = (k + 1/2) / n`` along the stretch and
   ``v = frac(k / golden ratio)`` round the arc, a rank-1 lattice, so the result is
   deterministic. A sample counts where the transmitter sees the point, also from 5 cm off the
   edge (Sionna's guard against leaks through the faces).
4. **Flux of a sample.** Its field is Sionna's UTD evaluation of the wedge's radio material
   (``RadioMapSolver._evaluate_radio_material_diffraction``, spreading factor included) at
   ``s_ref``, where the diffracted ray first meets the scene or a grid plane; its weight is
   the change of variables from (position on the edge, angle on the cone) to the area of a
   plane normal to the ray at ``s_ref`` (:func:`diffracted_bundle_area`, as Sionna's
   ``RadioMap._diffraction_integration_weight``), times the stretch's length and the arc's
   angle over the pair's sample count. ``|E|^2`` falls as
   ``1 / (s s' (s + s'))`` and that area grows as ``s (s + s') / s'``: their product, the flux,
   is the same all along the ray (the transition function's dependence on ``s`` aside: hence
   ``s_ref`` at the first crossing).
5. **On through the specular tracer.** The ray is handed to :meth:`Tracer.propagate` with its
   field scaled so that the tracer's ``4 pi / num_rays`` becomes that flux: it deposits
   ``|E|^2 weight / |cos theta_z|`` on every plane it crosses (RadioMapSolver's estimator for
   diffracted rays on the first crossing) and reflects specularly up to ``max_depth - 1`` more
   times. It carries its tube, ``tube_c = area(s) / (s (s + s'))`` and ``tube_l0 = s'``, so that
   the tracer knows its cross-section ``tube_c (L - s') L`` at any path length ``L`` and spreads
   a crossing over the footprint where that is larger than a cell
   (:mod:`simart_pipeline.ckm.one_pass`).

Delays and directions of a deposit are those of the path through the sampled point to the cell
centre ``c``: ``tau = (|q - tx| + |c - q|) / c0``, arrival from ``q``, departure towards ``q``.
Moving ``q`` along the edge to the centre's own diffraction point changes the length only at
second order (Fermat: the diffracted path is stationary along the edge), so this is the centre's
delay to first order, as the image-source correction is for reflections.

Traced: (diffraction) and, with depth >= 2, (reflection, diffraction) paths, either followed by
specular reflections. Not traced: two reflections before a diffraction and second-order
diffraction (RadioMapSolver traces neither); docs/ckm-one-pass.md gives the measured effect.
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.ckm.shoot_bounce import (Grid, _unique_keys, fibonacci_directions,
                                               on_departure_grid, reflection_terms)

__all__ = ["DiffractionSampler", "WEDGE_KEY_M", "diffracted_bundle_area"]

WEDGE_KEY_M = 1e-3      # end points closer than this are the same edge
LEAK_OFFSET_M = 5e-2    # Sionna's offset of the visibility-test point off the wedge
SPAWN_OFFSET_M = 1e-3   # diffracted rays start this far off the edge
MAX_REFERENCE_DISTANCE_M = 1e4  # a diffracted ray meeting nothing: its field is taken this far out
# A diffracted ray is tested for leaving into another solid this far along it from its spawn point
# (the probe of Sionna's leak guard, LEAK_OFFSET_M); a wedge is tested for a solid against it at
# BLOCKED_ARC_PROBES angles round its exterior at each of BLOCKED_ARC_STATIONS points along it, and
# the ends of a blocked arc are found by BLOCKED_ARC_BISECTIONS halvings (DiffractionSampler._blocked_arcs)
INSIDE_PROBE_M = LEAK_OFFSET_M
BLOCKED_ARC_PROBES = 32
BLOCKED_ARC_STATIONS = (0.125, 0.5, 0.875)
BLOCKED_ARC_BISECTIONS = 7
# a blocked arc is widened by this on either side: a ray at its very end grazes the face that bounds
# it (a plate edge's ray along the wall below it), where the probe may fall on either side
BLOCKED_ARC_MARGIN_RAD = 1e-3
# Samples per lattice ray on the direct wedges, and the (image, wedge) pairs' share of those. Before
# the pilot, 4 per ray on Munich gave a value in 96.6 % of the sampled outdoor cells PathSolver
# reaches (benchmarks.ckm_solver, 1e7 rays, 2 m cells); with the pilot and the downward arc, 2 per
# ray gave 99.2 % (street canyon 100 %, urban 100 %). With deposits spread over their footprints
# (one_pass, max_footprint_cells) 1 per ray is closer to a 32x-sample map than 2 were without
# (Munich: gain p95 3.9 against 8.0 dB) in the same time, and 30 % faster on the street canyon
# (docs/ckm-one-pass.md, "Session 12").
DIRECT_SAMPLES_PER_RAY = 1
REFLECTED_SAMPLE_SHARE = 0.125
PILOT_POINTS = 32  # lattice points per (source, wedge) pair that find where it can diffract (pilot)
PILOT_BATCH = 1 << 22  # pilot points evaluated at once
SAMPLES_PER_BATCH_RAY = 4  # diffraction samples traced at once per lattice ray of a batch: a
#                            sample's state is smaller than a ray's, and fewer launches cost less
STRETCHES_PER_PAIR = 64  # the second pass resamples a pair's edge in runs of 1/64 of its samples
DIFFRACTED_RAY_KEY = 0x9E3779B9  # diffracted rays' random-number keys: sample index plus this
_LATTICE_STEP = 0x9E3779B9  # round(2**32 / golden ratio): the lattice's cone coordinate, fixed point


class DiffractionSampler:
    """First-order diffraction of one transmitter over a :class:`Grid`: finds the lit wedges, then
    hands the deposits of ``num_samples`` samples to ``sink(deposits, line_of_sight=False)`` in the
    dict form of :class:`simart_pipeline.ckm.shoot_bounce.Tracer`."""

    def __init__(self, radio, tracer, tx_position_m, tx_rotation: np.ndarray, grid: Grid, reflections_after: int,
                 edge_diffraction: bool, reflections_before: int = 0, solids=None):
        import drjit as dr
        import mitsuba as mi

        if reflections_before not in (0, 1):
            raise ValueError(f"reflections_before must be 0 or 1, got {reflections_before}")
        self.dr, self.mi = dr, mi
        self.radio, self.scene = radio, radio.scene.mi_scene
        self.tx = np.asarray(tx_position_m, np.float64)
        self.rot = np.asarray(tx_rotation, np.float64)
        self.grid = grid
        self.tracer = tracer
        self.reflections_after = int(reflections_after)
        self.reflections_before = int(reflections_before)
        self.edge_diffraction = bool(edge_diffraction)
        self._wedge_np: dict[str, np.ndarray] = {}
        self._dr_all = None  # _wedge_np as Dr.Jit arrays, built on first use
        self._u_lo = self._u_span = self._weight = None  # from pilot()
        self._dr_span = None
        self._counts = self._starts = None  # samples per pair of the last trace() and where they start
        # the radio scene's solids (ckm.outdoor.radio_solids; made on first use where None) and, per
        # pair, the arc of its exterior inside another solid (_blocked_arcs)
        self.solids = solids
        self._blocked = None

    @property
    def num_wedges(self) -> int:
        """(source, wedge) pairs found by :meth:`find_wedges`."""
        return len(self._wedge_np.get("length", ()))

    # -- step 1 ---------------------------------------------------------------------------------
    def find_wedges(self, num_rays: int, batch_rays: int) -> int:
        """Wedges of the triangles that ``num_rays`` lattice rays from the transmitter hit first
        (source: the transmitter) and, with ``reflections_before``, after one specular reflection
        (source: the transmitter's image in the reflecting face's plane); returns how many
        (source, wedge) pairs. The hits the tracer collected while tracing these rays
        (``Tracer.lit_faces`` / ``lit_pairs``) are used where it did; else the rays are cast here."""
        dr, mi = self.dr, self.mi
        tr = self.tracer
        direct = list(tr.lit_faces or [])
        reflected = list(tr.lit_pairs or []) if self.reflections_before else []
        cast_direct = tr.lit_faces is None
        cast_reflected = self.reflections_before and tr.lit_pairs is None
        tx = mi.Point3f(*(float(v) for v in self.tx))
        for start in range(0, int(num_rays) if (cast_direct or cast_reflected) else 0, int(batch_rays)):
            stop = min(start + int(batch_rays), int(num_rays))
            d = fibonacci_directions(start, stop, int(num_rays))
            o = dr.zeros(mi.Point3f, stop - start) + tx
            pi = self.scene.ray_intersect_preliminary(mi.Ray3f(o, d), False)
            hit = pi.is_valid()
            face, n = tr.face_at(dr.reinterpret_array(mi.UInt32, pi.shape), pi.prim_index, hit)
            if cast_direct:
                direct.append(_unique_keys(dr, face, hit))
            if cast_reflected:
                reflected.append(tr.mirror_pair_keys(o, d, pi.t, face, n, hit))
        if not direct:
            direct = [np.zeros(0, np.uint64)]
        faces = tr.faces
        cols = self._candidates(faces.shape_and_primitive(np.unique(np.concatenate(direct))), None)
        pairs = np.unique(np.concatenate(reflected)) if self.reflections_before and reflected else ()
        if len(pairs):  # none: no lattice ray met a second face after a specular reflection
            mirror = self._canonical_faces((pairs >> np.uint64(32)).astype(np.int64))  # one source per plane
            pairs = np.unique(np.column_stack([faces.shape_and_primitive(pairs & np.uint64(0xFFFFFFFF)), mirror]),
                              axis=0)
            cols = {k: np.concatenate([cols[k], v]) for k, v in self._candidates(pairs[:, :2], pairs[:, 2]).items()}
        self._wedge_np = cols
        self._dr_all = self._blocked = None
        self._u_lo = self._u_span = self._weight = None
        self._dr_span = None
        return self.num_wedges

    def _candidates(self, triangles: np.ndarray, reflector_face: np.ndarray | None) -> dict[str, np.ndarray]:
        """Wedges of ``triangles`` ``[n, 2]`` (shape id, primitive) lit from the transmitter or,
        per row, from its image in the plane of global face ``reflector_face``: convex or (with
        ``edge_diffraction``) free edges, the source outside the wedge, each (source, edge) once."""
        dr, mi = self.dr, self.mi
        from sionna.rt.constants import EPSILON_FLOAT
        from sionna.rt.utils.wedges import wedge_geometry

        if len(triangles) == 0:
            return {k: np.zeros((0,) + ((3,) if k in _VEC else ()), _DTYPES.get(k, np.float64)) for k in _KEYS}
        if reflector_face is None:
            src = np.broadcast_to(self.tx, (len(triangles), 3)).astype(np.float64)
            plane_n, plane_off = np.zeros((len(triangles), 3)), np.zeros(len(triangles))
            order = np.zeros(len(triangles), np.int64)
        else:
            plane_n, plane_off = self._planes(reflector_face)
            src = self.tx - 2.0 * (plane_n @ self.tx - plane_off)[:, None] * plane_n
            order = np.ones(len(triangles), np.int64)
        rep = lambda a: np.repeat(a, 3, axis=0)  # noqa: E731 three edges per triangle
        shape_id, prim = rep(triangles[:, 0]).astype(np.uint32), rep(triangles[:, 1]).astype(np.uint32)
        local_edge = np.tile(np.arange(3, dtype=np.uint32), len(triangles))
        src3 = rep(src)
        mesh = mi.MeshPtr(dr.reinterpret_array(mi.ShapePtr, mi.UInt32(shape_id)))
        w = wedge_geometry(mesh, mi.UInt32(prim), mi.UInt32(local_edge))
        s = mi.Point3f(*(mi.Float(src3[:, k].astype(np.float32)) for k in range(3)))
        mid = w.o + 0.5 * w.length * w.e_hat
        w.swap_faces(dr.dot(mid - s, w.n0) > 0)  # the source sees the 0-face, as in Sionna
        k = s - mid
        valid = (w.length > 0) & ((dr.dot(k, w.n0) > EPSILON_FLOAT) | (dr.dot(k, w.nn) > EPSILON_FLOAT))
        valid = _without_flat_edges(dr, mesh, w, valid)  # two coplanar faces do not diffract
        if not self.edge_diffraction:
            valid &= w.primn != w.prim0
        dr.eval(valid, w)
        keep = np.asarray(valid.numpy(), bool)
        out = {"shape": shape_id, "prim0": w.prim0.numpy(), "primn": w.primn.numpy(), "local_edge": w.local_edge.numpy(),
               "o": np.stack([getattr(w.o, c).numpy() for c in "xyz"], -1),
               "e_hat": np.stack([getattr(w.e_hat, c).numpy() for c in "xyz"], -1),
               "n0": np.stack([getattr(w.n0, c).numpy() for c in "xyz"], -1),
               "nn": np.stack([getattr(w.nn, c).numpy() for c in "xyz"], -1),
               "length": w.length.numpy(), "src": src3, "plane_n": rep(plane_n), "plane_off": rep(plane_off),
               "order": rep(order)}
        out = {k: np.asarray(v)[keep] for k, v in out.items()}
        o_np = out["o"].astype(np.float64)
        e_np = o_np + out["e_hat"] * out["length"][:, None].astype(np.float64)
        first_o = _lex_less(o_np, e_np)[:, None]  # the key does not depend on the edge's direction
        lo, hi = np.where(first_o, o_np, e_np), np.where(first_o, e_np, o_np)
        # the shape's place in the scene (mi_scene.shapes() order), not its Mitsuba id: Mitsuba
        # loads shapes on several threads and numbers them as they finish, so ids differ from one
        # process to the next (and with them the sample keys, so the diffuse draws, of each wedge)
        faces = self.tracer.faces
        rank = np.zeros(int(faces.shape_ids.max(initial=0)) + 1, np.int64)
        rank[faces.shape_ids] = np.arange(len(faces.shape_ids))
        key = np.column_stack([rank[out["shape"].astype(np.int64)], np.round(np.column_stack([lo, hi]) / WEDGE_KEY_M),
                               np.round(out["src"] / WEDGE_KEY_M)]).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)  # sorted keys: a fixed order
        return {k: v[first] for k, v in out.items()}

    def _planes(self, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Planes of global faces: unit normal ``[n, 3]`` turned towards the transmitter and offset
        ``[n]`` m (``n . x = offset`` on the plane)."""
        table = self.tracer.faces
        f = np.asarray(faces, np.int64)
        n, point = table.normals[f], table.first_vertex[f]
        off = np.einsum("ij,ij->i", n, point)
        sign = np.where(n @ self.tx - off < 0, -1.0, 1.0)
        return n * sign[:, None], off * sign

    def _canonical_faces(self, faces: np.ndarray) -> np.ndarray:
        """Each face replaced by the lowest-numbered face of its plane (normal within 1e-5, offset
        within 1e-5 m): coplanar triangles of one wall give one image source, bit for bit, so a
        (source, wedge) pair is never sampled twice."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        uniq, inverse = np.unique(faces, return_inverse=True)
        n, off = self._planes(uniq)
        pairs = cKDTree(np.column_stack([n, off])).query_pairs(1e-5, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(uniq), len(uniq)))
        _, label = connected_components(graph, directed=False)
        lowest = np.full(label.max() + 1, np.iinfo(np.int64).max)
        np.minimum.at(lowest, label, uniq)
        return lowest[label][inverse]

    def _wedge_table(self):
        """:class:`WedgeGeometry`, source, reflecting plane of every (source, wedge) pair, as
        Dr.Jit arrays built once."""
        dr, mi = self.dr, self.mi
        from sionna.rt.utils.wedges import WedgeGeometry

        if self._dr_all is None:
            c = self._wedge_np
            vec = lambda a, t=mi.Vector3f: t(*(mi.Float(a[:, j].astype(np.float32)) for j in range(3)))  # noqa: E731
            shape = mi.MeshPtr(dr.reinterpret_array(mi.ShapePtr, mi.UInt32(c["shape"])))
            wedges = WedgeGeometry(shape, mi.UInt32(c["prim0"]), mi.UInt32(c["primn"]), mi.UInt32(c["local_edge"]),
                                   vec(c["o"], mi.Point3f), vec(c["e_hat"]), mi.Float(c["length"].astype(np.float32)),
                                   vec(c["n0"], mi.Normal3f), vec(c["nn"], mi.Normal3f))
            self._dr_all = (wedges, vec(c["src"], mi.Point3f), vec(c["plane_n"]),
                            mi.Float(c["plane_off"].astype(np.float32)))
        return self._dr_all

    def _blocked_arcs(self):
        """Where another solid lies against a (source, wedge) pair's edge, the arc of its exterior
        angle inside that solid, as Dr.Jit arrays (lo, hi) of the cone angle ``phi`` (rad, Sionna's
        frame of :func:`keller_cone`: a diffracted direction there is blocked where ``lo <= phi
        <= hi``; none: ``lo > hi``), and ``host``: the pairs whose arc is tested per sample on the
        host instead (:meth:`_outside_solids`); None where no pair has one. Built once per
        :meth:`find_wedges`, per wedge whatever its sources.

        A point :data:`INSIDE_PROBE_M` out from the edge at each of :data:`BLOCKED_ARC_PROBES`
        angles across the exterior (square to the edge), at each of :data:`BLOCKED_ARC_STATIONS`
        along it, is tested for lying inside a solid (:func:`simart_pipeline.ckm.outdoor.points_inside`).
        Near the edge a solid bounded by faces through it blocks one arc, the same all along: where
        the stations agree and the blocked angles are one run, its ends are found by bisection at
        the middle station (:data:`BLOCKED_ARC_BISECTIONS` halvings of the probes' spacing). A
        solid against part of the edge only, or two blocked runs: tested per sample.

        On Munich a building's roof and walls are separate meshes, so each roof edge is a free edge
        (a plate's, 360 degrees of exterior) whose lower quarter lies inside the building, and where
        two building parts meet, one part's corner diffracts into the other; with every mechanism
        42 % of the diffraction samples left into a solid (docs/ckm-one-pass.md "Session 45")."""
        from simart_pipeline.ckm.outdoor import points_inside, radio_solids

        mi = self.mi
        if self._blocked is None:
            if self.solids is None:
                self.solids = radio_solids(self.radio)
            c = self._wedge_np
            keys = np.column_stack([c["shape"], c["prim0"], c["local_edge"]]).astype(np.int64)
            _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
            inverse = inverse.ravel()
            o, e, n0, nn, length = (np.asarray(c[k][first], np.float64) for k in ("o", "e_hat", "n0", "nn", "length"))
            t0 = np.cross(n0, e)
            t0 /= np.maximum(np.linalg.norm(t0, axis=1, keepdims=True), 1e-12)
            exterior = 2.0 * np.pi - np.arccos(np.clip(-np.einsum("ij,ij->i", n0, nn), -1.0, 1.0))
            free = c["prim0"][first] == c["primn"][first]
            ne = np.where(free[:, None], 0.0, n0 + nn)
            ne /= np.maximum(np.linalg.norm(ne, axis=1, keepdims=True), 1e-12)

            def probes(rows, phi, u):  # wedges rows, phi [rows, m] rad, u: the station along the edge
                out = np.cos(phi)[..., None] * t0[rows, None] + np.sin(phi)[..., None] * n0[rows, None]
                at = o[rows] + (u * length[rows])[:, None] * e[rows] + SPAWN_OFFSET_M * ne[rows]
                return at[:, None] + INSIDE_PROBE_M * out  # [rows, m, 3]

            def inside(pts):  # [..., 3] -> [...] bool, in one test
                return points_inside(self.radio, pts.reshape(-1, 3), self.solids).reshape(pts.shape[:-1])

            k = BLOCKED_ARC_PROBES
            phi = (np.arange(k) + 0.5) / k * exterior[:, None]
            every = np.arange(len(first))
            stations = inside(np.stack([probes(every, phi, u) for u in BLOCKED_ARC_STATIONS]))  # [station, w, k]
            mid = stations[len(BLOCKED_ARC_STATIONS) // 2]
            any_blocked = stations.any(axis=(0, 2))
            runs = (mid[:, 1:] & ~mid[:, :-1]).sum(1) + mid[:, 0]  # blocked runs at the middle station
            arc = any_blocked & (stations == mid).all(axis=(0, 2)) & (runs == 1)
            host = any_blocked & ~arc
            lo, hi = np.ones(len(first)), -np.ones(len(first))
            if arc.any():
                a = np.flatnonzero(arc)
                m = mid[a]
                i_b = np.stack([np.argmax(m, 1), k - 1 - np.argmax(m[:, ::-1], 1)], 1)  # [arc, end]
                i_f = i_b + np.array([-1, 1])  # the free neighbour of each end (off the exterior: none)
                step = (exterior[a] / k)[:, None]
                blocked_phi, free_phi = (i_b + 0.5) * step, (i_f + 0.5) * step
                for _ in range(BLOCKED_ARC_BISECTIONS):  # both ends of every arc in one test
                    half = 0.5 * (blocked_phi + free_phi)
                    ins = inside(probes(a, half, 0.5))
                    blocked_phi = np.where(ins, half, blocked_phi)
                    free_phi = np.where(ins, free_phi, half)
                ends = 0.5 * (blocked_phi + free_phi)
                lo[a] = np.where(i_f[:, 0] < 0, 0.0, ends[:, 0]) - BLOCKED_ARC_MARGIN_RAD
                hi[a] = np.where(i_f[:, 1] >= k, exterior[a], ends[:, 1]) + BLOCKED_ARC_MARGIN_RAD
            lo, hi, host = lo[inverse], hi[inverse], host[inverse]
            self._blocked = () if not any_blocked.any() else (  # (): built, none blocked
                mi.Float(lo.astype(np.float32)), mi.Float(hi.astype(np.float32)), mi.Bool(host) if host.any() else None)
        return self._blocked or None

    def _outside_solids(self, idx, pair, spawn, ko):
        """``idx`` (kept sample lanes) less the samples of the pairs whose blocked arc is tested
        per sample (:meth:`_blocked_arcs`) whose diffracted ray leaves into another solid: its point
        :data:`INSIDE_PROBE_M` along ``ko`` from ``spawn`` lies inside one (on the host). Such a
        ray would cross that solid without entering it, and with refraction leave it through a
        far wall, one transmission short (Munich's cell (-18.5, -30) m: a 305 m path, a reflection,
        a diffraction into the town hall's other part, a transmission out, 40 % of the cell's
        power; docs/ckm-one-pass.md "Session 45"). Sionna's solvers launch these rays too;
        :func:`simart_pipeline.radio.tracer.drop_paths_diffracted_into_solids` drops PathSolver's."""
        from simart_pipeline.ckm.outdoor import points_inside

        dr, mi = self.dr, self.mi
        blocked = self._blocked_arcs()
        if blocked is None or blocked[2] is None:
            return idx
        at = dr.compress(dr.gather(mi.Bool, blocked[2], dr.gather(mi.UInt32, pair, idx)))
        if dr.width(at) == 0:
            return idx
        lanes = dr.gather(mi.UInt32, idx, at)
        p = dr.gather(mi.Point3f, spawn, lanes) + INSIDE_PROBE_M * dr.gather(mi.Vector3f, ko, lanes)
        dr.eval(p)
        inside = points_inside(self.radio, np.stack([p.x.numpy(), p.y.numpy(), p.z.numpy()], -1), self.solids)
        if not inside.any():
            return idx
        keep = np.ones(dr.width(idx), bool)
        keep[at.numpy()[inside]] = False
        return mi.UInt32(idx.numpy()[keep])

    def _wedge_geometry(self, index):
        """:meth:`_wedge_table`'s rows ``index`` (a UInt32 array): Dr.Jit gathers (numpy fancy
        indexing of every field per sample cost more than the samples' kernels)."""
        return tuple(self.dr.gather(type(a), a, index) for a in self._wedge_table())

    # -- step 2 ---------------------------------------------------------------------------------
    def allocation(self, num_samples: int) -> np.ndarray:
        """Samples per (source, wedge): ``num_samples`` for the direct wedges and
        :data:`REFLECTED_SAMPLE_SHARE` of that for the (image, wedge) pairs, each spread in
        proportion to the pairs' weights (:meth:`pilot`; edge length before it), largest
        remainders, at least one for a pair of positive weight, none for the others."""
        weight = self._weight if self._weight is not None else self._wedge_np["length"].astype(np.float64)
        n = np.zeros(len(weight), np.int64)
        for order in np.unique(self._wedge_np["order"]):
            sel = np.flatnonzero((self._wedge_np["order"] == order) & (weight > 0))
            if not len(sel):
                continue
            total = int(num_samples if order == 0 else round(num_samples * REFLECTED_SAMPLE_SHARE))
            share = total * weight[sel] / weight[sel].sum()
            k = np.floor(share).astype(np.int64)
            left = int(total - k.sum())
            if left > 0:
                k[np.argsort(-(share - k), kind="stable")[:left]] += 1
            n[sel] = np.maximum(k, 1)
        return n

    def pilot(self, points: int | None = None) -> None:
        """Where each (source, wedge) pair can diffract towards a grid plane, from ``points``
        lattice points per pair (validity depends on the position along the edge only: the source
        sees it, and some of its cone points down, see :func:`keller_cone`): the samples are then
        spread over the hull of the valid points widened by one spacing on either side, and the
        pairs get samples in proportion to ``length x hull x mean downward measure`` (equal
        density of samples per unit of edge and cone angle that can deposit). A pair with no valid
        point gets none: a lit stretch shorter than ``length / points`` can be missed.
        ``points`` 0: no pilot, every pair's whole edge, in proportion to its length."""
        mi = self.mi
        num = self.num_wedges
        order = self._wedge_np["order"]
        points = PILOT_POINTS if points is None else int(points)
        lo, span, weight = np.zeros(num), np.ones(num), np.zeros(num)
        if points == 0:
            weight = self._wedge_np["length"].astype(np.float64)
        k = np.arange(points)
        for o in (0, 1) if points else ():
            pairs = np.flatnonzero(order == o)
            for chunk in np.array_split(pairs, max(1, len(pairs) * points // PILOT_BATCH + 1)):
                if not len(chunk):
                    continue
                w = mi.UInt32(np.repeat(chunk, points).astype(np.uint32))
                kk = np.tile(k, len(chunk)).astype(np.uint32)
                u = mi.Float(((kk + 0.5) / points).astype(np.float32))
                v = mi.Float((mi.UInt32(kk) * _LATTICE_STEP) >> 8) * (2.0**-24)
                g = self._geometry(w, u, v, o)
                valid = g["ok"].numpy().reshape(-1, points)
                measure = np.where(valid, g["measure"].numpy().reshape(-1, points), 0.0)
                seen = valid.any(1)
                first = np.argmax(valid, 1)
                last = points - 1 - np.argmax(valid[:, ::-1], 1)
                a = np.clip((first - 0.5) / points, 0.0, 1.0)
                b = np.clip((last + 1.5) / points, 0.0, 1.0)
                lo[chunk] = np.where(seen, a, 0.0)
                span[chunk] = np.where(seen, b - a, 1.0)
                mean_measure = measure.sum(1) / np.maximum(valid.sum(1), 1)
                weight[chunk] = np.where(seen, self._wedge_np["length"][chunk] * (b - a) * mean_measure, 0.0)
        self._u_lo, self._u_span, self._weight = lo, span, weight
        self._dr_span = None

    def trace(self, num_samples: int, batch: int, sink, tag_stretches: bool = False) -> None:
        """Samples on the wedges found by :meth:`find_wedges`, deposits handed to ``sink``;
        ``tag_stretches``: each deposit names the stretch of its pair's edge its sample came from
        (``stretch``: pair x :data:`STRETCHES_PER_PAIR` + stretch), for :meth:`resample`."""
        if self.num_wedges == 0 or num_samples <= 0:
            return
        if self._weight is None:
            self.pilot()
        counts = self.allocation(int(num_samples))
        self._counts, self._starts = counts, np.cumsum(counts) - counts
        pairs = np.flatnonzero(counts)
        self._trace_segments(pairs, np.zeros(len(pairs), np.int64), counts[pairs], 1, batch, sink, tag_stretches)

    def resample(self, stretches: np.ndarray, factor: int, batch: int, replay_sink, finer_sink) -> int:
        """A second pass on the stretches ``stretches`` (tags of :meth:`trace`'s deposits) of the
        last :meth:`trace`: their samples of that pass again, exactly (to ``replay_sink``: what
        they added, to be taken out), and ``factor`` times as many new ones over the same part of
        the edge (to ``finer_sink``: each standing for ``1 / factor`` of a first-pass sample's
        share, on a lattice of their own, random numbers keyed past the first pass's). A stretch
        is the ``b``-th of :data:`STRETCHES_PER_PAIR` runs of consecutive samples of a pair (the
        ``k``-th of ``n`` lies in ``floor(k S / n)``): a cell far from an edge is reached from
        near one point of it (Keller's law), so a few stretches carry the rays it got. Returns
        the new samples' count."""
        if self._counts is None:
            raise RuntimeError("resample() needs a trace() first")
        tags = np.unique(np.asarray(stretches, np.int64))
        pair, b = tags // STRETCHES_PER_PAIR, tags % STRETCHES_PER_PAIR
        n = self._counts[pair]
        k_lo = (b * n + STRETCHES_PER_PAIR - 1) // STRETCHES_PER_PAIR
        k_hi = ((b + 1) * n + STRETCHES_PER_PAIR - 1) // STRETCHES_PER_PAIR
        keep = k_hi > k_lo
        pair, k_lo, m = pair[keep], k_lo[keep], (k_hi - k_lo)[keep]
        if not len(pair) or int(factor) < 1:
            return 0
        self._trace_segments(pair, k_lo, m, 1, batch, replay_sink)
        self._trace_segments(pair, k_lo, m, int(factor), batch, finer_sink)
        return int(m.sum()) * int(factor)

    def _trace_segments(self, pair: np.ndarray, k0: np.ndarray, m: np.ndarray, factor: int, batch: int, sink,
                        tag_stretches: bool = False) -> None:
        """Segment ``i``: the first-pass samples ``k0[i] .. k0[i] + m[i] - 1`` of pair ``pair[i]``
        (``factor`` 1: those very samples, keyed as in the first pass) or ``factor m[i]`` new ones
        over the same stretch of edge (:meth:`_lattice`), traced in batches."""
        dr, mi = self.dr, self.mi
        order = self._wedge_np["order"]
        if np.any(np.diff(order) < 0):
            raise AssertionError("find_wedges stores the direct wedges before the reflected pairs")
        srt = np.argsort(pair, kind="stable")  # direct pairs first: batches never mix source orders
        pair, k0, m = pair[srt], k0[srt], m[srt]
        cnt = m * int(factor)
        ends = np.cumsum(cnt)
        seg_start = ends - cnt
        if factor == 1:  # the first pass's keys
            base = self._starts[pair] + k0
        else:  # past every first-pass key
            base = int(self._counts.sum()) + seg_start
        seg = {"pair": pair, "k0": k0, "start": seg_start, "base": base}
        seg = {k: mi.UInt32(np.asarray(v, np.int64).astype(np.uint32)) for k, v in seg.items()}
        seg["n"] = mi.UInt32(np.maximum(self._counts, 1).astype(np.uint32))
        direct = order[pair] == 0
        split = int(ends[direct][-1]) if direct.any() else 0
        for o, lo, hi in ((0, 0, split), (1, split, int(ends[-1]) if len(ends) else 0)):
            for start in range(lo, hi, int(batch)):
                stop = min(start + int(batch), hi)
                # the segment each sample belongs to, on the device: the first one the batch
                # touches plus the starts of the next ones at or before the sample (a prefix sum
                # of marks; a host np.repeat and its copy took 8 ms a batch on a GPU)
                s0, s1 = np.searchsorted(ends, [start, stop - 1], side="right")
                mark = dr.zeros(mi.UInt32, stop - start)
                if s1 > s0:
                    dr.scatter_reduce(dr.ReduceOp.Add, mark, mi.UInt32(1),
                                      mi.UInt32((seg_start[s0 + 1:s1 + 1] - start).astype(np.uint32)))
                s = dr.prefix_sum(mark) + mark + dr.opaque(mi.UInt32, int(s0))  # opaque: one kernel
                lattice = self._lattice(start, stop, s, seg, int(factor), tag_stretches)
                self._trace_batch(lattice, o, sink)

    def _lattice(self, start: int, stop: int, s, seg: dict, factor: int, tag_stretches: bool = False) -> dict:
        """The rank-1 lattice points of samples ``start..stop-1`` of the segments ``s``
        (:meth:`_trace_segments`): the ``k``-th of a pair's ``n`` first-pass samples at
        ``u = lo + span (k + 1/2) / n`` along the edge (``lo``, ``span``: the pair's stretch from
        :meth:`pilot`), ``v = frac(k / golden ratio)`` round the cone (32-bit fixed point, exact
        for any ``k``), standing for ``span / n`` of the edge; with ``factor`` f > 1, the ``j``-th
        new sample of a segment at ``k = k0 + (j + 1/2) / f`` and ``v = frac(j / golden ratio)``,
        for ``span / (n f)`` (its ray tube, and so its footprint, 1 / f of a first-pass
        sample's). Also each sample's pair, key (``base`` of its segment plus ``j``) and, with
        ``tag_stretches``, its stretch tag."""
        dr, mi = self.dr, self.mi
        if self._dr_span is None:
            self._dr_span = (mi.Float(self._u_lo.astype(np.float32)), mi.Float(self._u_span.astype(np.float32)))
        j = dr.arange(mi.UInt32, start, stop) - dr.gather(mi.UInt32, seg["start"], s)
        w = dr.gather(mi.UInt32, seg["pair"], s)
        k0 = dr.gather(mi.UInt32, seg["k0"], s)
        n_w = mi.Float(dr.gather(mi.UInt32, seg["n"], w))
        lo, span = (dr.gather(mi.Float, a, w) for a in self._dr_span)
        if factor == 1:
            k = k0 + j
            u = lo + span * (mi.Float(k) + 0.5) / n_w
            v = mi.Float((k * _LATTICE_STEP) >> 8) * (2.0**-24)
            share = span / n_w
        else:
            k = k0 + j // factor
            u = lo + span * (mi.Float(k0) + (mi.Float(j) + 0.5) / factor) / n_w
            v = mi.Float((j * _LATTICE_STEP) >> 8) * (2.0**-24)
            share = span / (n_w * factor)
        out = dict(u=u, v=v, edge_share=share, index=dr.gather(mi.UInt32, seg["base"], s) + j, pair=w)
        if tag_stretches:
            stretch = dr.minimum(mi.UInt32(mi.Float(k) * (STRETCHES_PER_PAIR / n_w)), STRETCHES_PER_PAIR - 1)
            out["stretch"] = w * STRETCHES_PER_PAIR + stretch
        return out

    def _incident(self, q, q_off, src, plane_n, plane_off, order: int):
        """Where the source's field reaches ``q``: (valid, Jones vector of the field arriving at
        ``q`` in Sionna's implicit basis of its direction, that direction ``ki``, the unfolded
        distance ``s'``, the departure direction at the transmitter)."""
        dr, mi = self.dr, self.mi
        from sionna.rt.antenna_pattern import antenna_pattern_to_world_implicit
        from sionna.rt.utils.ray_tracing import spawn_ray_to

        tr = self.tracer
        pattern = self.radio.scene.tx_array.antenna_pattern.patterns[0]
        to_world = mi.Matrix3f(*(float(self.rot[r, c]) for r in range(3) for c in range(3)))
        n_q = dr.width(q)
        tx = dr.zeros(mi.Point3f, n_q) + mi.Point3f(*(float(x) for x in self.tx))
        ki = dr.normalize(q - src)
        s_prime = dr.norm(q - src)
        if order == 0:
            ok = ~self.scene.ray_test(spawn_ray_to(tx, q))
            ok &= ~self.scene.ray_test(spawn_ray_to(tx, q_off), ok)
            return ok, antenna_pattern_to_world_implicit(pattern, to_world, ki, direction="out"), ki, s_prime, ki
        # one reflection: the path tx -> r -> q with r where q's line to the image source crosses
        # the plane; it exists when r lies on a face of that plane and both legs are clear
        dist_q = dr.dot(plane_n, q) - plane_off
        cos_q = dr.dot(plane_n, ki)
        ok = (dist_q > 0) & (cos_q > 1e-6)
        t_r = dist_q / dr.select(ok, cos_q, 1.0)
        r = q - t_r * ki
        probe = 1e-2
        pi = self.scene.ray_intersect_preliminary(mi.Ray3f(r + probe * plane_n, -plane_n), False, ok)
        ok &= pi.is_valid() & (dr.abs(pi.t - probe) < 1e-3)
        ids = dr.reinterpret_array(mi.UInt32, pi.shape)
        _, n_hit = tr.face_at(ids, pi.prim_index, ok)
        ok &= dr.abs(dr.dot(n_hit, plane_n)) > 1.0 - 1e-4
        r_off = r + 1e-3 * plane_n
        ok &= ~self.scene.ray_test(spawn_ray_to(tx, r_off), ok)
        ok &= ~self.scene.ray_test(spawn_ray_to(r_off, q), ok)
        ok &= ~self.scene.ray_test(spawn_ray_to(r_off, q_off), ok)
        dep = dr.normalize(r - tx)
        er, ei = jones_to_world(antenna_pattern_to_world_implicit(pattern, to_world, dep, direction="out"), dep)
        # specular reflection at r: the tracer's slab TE/TM coefficients and sqrt(1 - S^2)
        eta_re, eta_im, thick, spec = (dr.gather(mi.Float, table, ids, ok) for table in tr.mat)
        r = reflection_terms(dr, mi, dep, plane_n, er, ei, eta_re, eta_im, thick, tr.wavelength)
        out_re = spec * (r["a_r"] * r["e_s"] + r["b_r"] * r["e_pr"])  # e_pr: along ki, the mirror of dep
        out_im = spec * (r["a_i"] * r["e_s"] + r["b_i"] * r["e_pr"])
        return ok, world_to_jones(out_re, out_im, ki), ki, s_prime, dep

    def _geometry(self, w_index, u, v, order: int) -> dict:
        """Sample points ``u`` along the edges of pairs ``w_index``, cone coordinates ``v``:
        the wedges, the point ``q``, the incident field (:meth:`_incident`), the diffracted
        direction ``ko`` and its arc's measure, and ``ok`` where the sample can deposit."""
        dr, mi = self.dr, self.mi
        from sionna.rt.constants import MIN_SEGMENT_LENGTH

        wedges, src, plane_n, plane_off = self._wedge_geometry(w_index)
        q = wedges.o + u * wedges.length * wedges.e_hat
        free_edge = wedges.primn == wedges.prim0
        ne = dr.select(free_edge, mi.Vector3f(0), dr.normalize(wedges.n0 + wedges.nn))
        q_off = q + LEAK_OFFSET_M * ne
        ok, e_in, ki, s_prime, dep = self._incident(q, q_off, src, plane_n, plane_off, order)
        ok &= s_prime > MIN_SEGMENT_LENGTH
        # above every grid plane only the cone's downward arc can reach one (see keller_cone)
        downward = q.z > float(max(self.grid.heights)) + SPAWN_OFFSET_M
        ko, measure = keller_cone(dr, mi, wedges.e_hat, wedges.n0, wedges.nn, v, ki, downward)
        ok &= measure > 0
        return dict(wedges=wedges, q=q, ne=ne, ok=ok, e_in=e_in, ki=ki, s_prime=s_prime, dep=dep, ko=ko,
                    measure=measure)

    def _trace_batch(self, lattice: dict, order: int, sink) -> None:
        dr, mi = self.dr, self.mi
        from sionna.rt.constants import MIN_SEGMENT_LENGTH
        from sionna.rt.radio_map_solvers.radio_map_solver import RadioMapSolver

        g = self._geometry(lattice["pair"], lattice["u"], lattice["v"], order)
        wedges, q, ne, ok, e_in, ki, s_prime, dep, ko, measure = (
            g[k] for k in ("wedges", "q", "ne", "ok", "e_in", "ki", "s_prime", "dep", "ko", "measure"))
        blocked = self._blocked_arcs()
        if blocked is not None:  # a direction into a solid against the edge: the sample is void
            t0 = dr.normalize(dr.cross(wedges.n0, wedges.e_hat))
            phi = dr.atan2(dr.dot(ko, wedges.n0), dr.dot(ko, t0))
            phi = dr.select(phi < 0, phi + dr.two_pi, phi)
            ok &= ~((phi >= dr.gather(mi.Float, blocked[0], lattice["pair"]))
                    & (phi <= dr.gather(mi.Float, blocked[1], lattice["pair"])))
        # leave the edge by a millimetre into the exterior (ne + ko points there for any ko on the
        # cone), else the first intersection is the wedge's own face at t ~ 0
        ray = mi.Ray3f(q + SPAWN_OFFSET_M * (ne + ko), ko)
        # the field is evaluated where the diffracted ray first meets the scene or a grid plane
        # (the UTD transition function depends on that distance; the flux does not, see module doc)
        first = self.scene.ray_intersect_preliminary(ray, False, ok)
        t_first = dr.select(first.is_valid(), first.t, dr.inf)
        s_ref = t_first
        for height in self.grid.heights:
            t_h = (float(height) - ray.o.z) / ray.d.z
            s_ref = dr.select((t_h > 0) & (t_h < s_ref), t_h, s_ref)
        s_ref = dr.clip(s_ref, 2.0 * MIN_SEGMENT_LENGTH, MAX_REFERENCE_DISTANCE_M)
        shape_id = dr.reinterpret_array(mi.UInt32, first.shape)
        # one kernel for everything the kept samples read: a gather from a lazy array evaluates
        # it in a kernel of its own, and these share the wedge geometry and the incident field
        kept_lattice = [lattice[k] for k in ("pair", "edge_share", "stretch") if k in lattice]
        if self.tracer.sampled:
            kept_lattice.append(lattice["index"])
        dr.eval(ok, s_ref, t_first, shape_id, first.prim_index, q, ki, ko, s_prime, ray.o, dep, e_in, measure,
                *kept_lattice)
        idx = self._outside_solids(dr.compress(ok), lattice["pair"], ray.o, ko)
        if dr.width(idx) == 0:
            return
        take = lambda x: dr.gather(type(x), x, idx)  # noqa: E731
        # the kept samples' wedges from the table, not from ``wedges``: a gather evaluates a lazy
        # source first, one kernel per field over the whole batch (17 of them, 4 % of the canyon's kernel time)
        wq = dr.gather(type(wedges), self._wedge_table()[0], take(lattice["pair"]))
        qq, kki, kko, sp, sr, o, dd = take(q), take(ki), take(ko), take(s_prime), take(s_ref), take(ray.o), take(dep)
        # departure directions on a 2**-7 grid of direction cosines (< 0.45 deg): the deposits of
        # neighbouring samples then share their beam factors (one evaluation per cell and direction,
        # one-pass _Accumulator._add_beams), which otherwise cost 25x the tracing with 64 beams
        dd = on_departure_grid(dd)
        n = dr.width(idx)
        e_out = RadioMapSolver._evaluate_radio_material_diffraction(
            None, mi.ShapePtr(wq.shape), wq, qq, kki, kko, [take(e_in)], sr, sp, dr.full(mi.Bool, True, n))[0]
        # the flux of the ray: its field at s_ref times the area it stands for there
        area = diffracted_bundle_area(sr, sp, kki, wq.e_hat)
        area *= wq.length * take(measure) * take(lattice["edge_share"])
        # The tracer deposits |E|^2 (4 pi / num_rays) / |cos| per crossing: scale the field so that
        # its solid-angle factor becomes this ray's area per sample
        scale = dr.sqrt(dr.maximum(area, 0.0) * (self.tracer.num_rays / (4.0 * np.pi)))
        e_re, e_im = jones_to_world(e_out, kko)
        state = dict(o=o, d=kko, e_re=scale * e_re, e_im=scale * e_im, length=sp,
                     # the ray tube: area c (L - s') L at path length L (diffracted_bundle_area)
                     tube_c=area / (sr * (sr + sp)), tube_l0=sp,
                     # departure is fixed whatever the arrival: rank-one "mirror" columns
                     # (dep_k ko), so that the deposit's normalised M d_c is that direction
                     **{f"m{k}": dd[k] * kko for k in range(3)})
        if "stretch" in lattice:  # the deposits name it (one_pass's second pass)
            state["stretch"] = take(lattice["stretch"])
        if self.tracer.sampled:
            # diffuse reflection or refraction on: the tracer's random numbers are keyed by a ray
            # index (not a lattice ray's: offset), and the delay restarts at q (``anchor``: the
            # path length there), so a deposit's is |q - tx| + |c - q| exactly
            state.update(idx=take(lattice["index"]) + DIFFRACTED_RAY_KEY, anchor=sp)
        # the tracer's first segment is this very ray: its intersection is not cast again
        self.tracer.propagate(state, sink, self.reflections_after - order, from_transmitter=False,
                              first_hit=(take(t_first), take(shape_id), take(first.prim_index)))


def _without_flat_edges(dr, mesh, w, valid, tolerance: float = 1e-4):
    """``valid`` less the edges of ``w`` (a :class:`WedgeGeometry`) between two coplanar faces: no
    wedge at all (a wall's diagonal). Equal normals (within ``tolerance``) say so, but not alone:
    Sionna's ``wedge_geometry`` turns each normal away from the other face by the side of it that
    face's centroid lies on, within ``EPSILON_FLOAT``, and for coplanar faces float32 rounding
    decides. A flipped normal made the flat edge a knife edge (zero interior angle) that diffracts strongly
    (Munich: 920 of 7,209 lit pairs, up to 28 dB of spurious field behind a wall's diagonal).
    PathSolver never meets such an edge (it samples silhouette edges only). So the faces are read
    too: the unit directions from the edge into each face, across it, are opposite for faces on
    either side of it (flat), and equal for a thin plate's knife edge, which stays."""

    def into_face(prim):
        idx = mesh.face_indices(prim)
        r = (mesh.vertex_position(idx.x) + mesh.vertex_position(idx.y) + mesh.vertex_position(idx.z)) / 3.0 - w.o
        return dr.normalize(r - dr.dot(r, w.e_hat) * w.e_hat)

    valid = valid & (dr.dot(w.n0, w.nn) < 1.0 - tolerance)
    return valid & ~((w.prim0 != w.primn) & (dr.dot(into_face(w.prim0), into_face(w.primn)) < -(1.0 - tolerance)))


def keller_cone(dr, mi, e_hat, n0, nn, sample, ki, downward):
    """A direction on the Keller cone of the wedge (``e_hat``, faces' normals ``n0``, ``nn``) for
    an incident ``ki``, and the angular measure of the arc it was drawn from: Sionna's
    ``sample_keller_cone_with_measure`` (the whole exterior angle, lit region included), except on
    the lanes ``downward``, where ``sample`` spreads over the part of the exterior arc whose
    directions point down (``k_z < 0``) and the measure is that part's length (0: none points
    down, the sample is void).

    Why: a diffracted ray that leaves a point above every grid plane upwards can reach a plane only
    by reflecting off a downward-facing face (a wall keeps ``k_z`` positive), which the scenes'
    extruded buildings do not have. On a roof edge that is two thirds of the cone (270 degrees of
    exterior, 90 of them downward): the samples go where they count. The estimate of the downward
    part is unbiased (uniform on the arc, measure its length); paths up and back down are not
    traced.

    In Sionna's frame (``t0 = n0 x e_hat``, ``e_fwd`` = the edge along ``ki``), the direction at
    cone angle ``phi`` is ``sin b (cos phi t0 + sin phi n0) + cos b e_fwd``; its z component is
    ``sin b R cos(phi - phi0) + cos b e_fwd.z`` with ``R cos phi0 = t0.z``, ``R sin phi0 = n0.z``:
    negative on the arc of half-width ``acos(cos b e_fwd.z / (sin b R))`` about ``phi0 + pi``."""
    from sionna.rt.utils.wedges import wedge_interior_angle

    t0 = dr.normalize(dr.cross(n0, e_hat))
    e_fwd = dr.select(dr.dot(e_hat, ki) > 0, e_hat, -e_hat)
    cos_b = dr.clip(dr.dot(ki, e_fwd), -1.0, 1.0)
    sin_b = dr.safe_sqrt(1.0 - cos_b * cos_b)
    exterior = dr.two_pi - wedge_interior_angle(n0, nn)
    r = dr.sqrt(t0.z * t0.z + n0.z * n0.z)
    c = cos_b * e_fwd.z
    amp = sin_b * r
    # the downward arc [a, a + 2 half) modulo 2 pi, cut to the exterior [0, exterior)
    all_down = c < -amp  # every direction of the cone points down (also amp = 0, c < 0)
    half = dr.select(all_down, dr.pi, dr.select(c >= amp, 0.0, dr.acos(dr.clip(c / dr.maximum(amp, 1e-30), -1.0, 1.0))))
    centre = dr.atan2(n0.z, t0.z) + dr.pi
    a = dr.select(all_down, 0.0, centre - half)
    a = a - dr.two_pi * dr.floor(a / dr.two_pi)
    end = a + 2.0 * half
    len1 = dr.maximum(dr.minimum(dr.minimum(end, dr.two_pi), exterior) - a, 0.0)
    len2 = dr.maximum(dr.minimum(end - dr.two_pi, exterior), 0.0)
    s = sample * (len1 + len2)
    phi = dr.select(downward, dr.select(s < len1, a + s, s - len1), sample * exterior)
    measure = dr.select(downward, len1 + len2, exterior)
    sin_phi, cos_phi = dr.sincos(phi)
    return sin_phi * sin_b * n0 + cos_phi * sin_b * t0 + cos_b * e_fwd, measure


def _implicit_basis(k):
    """Sionna's implicit Jones basis of a wave along unit ``k``: ``e_s = theta-hat(k)``
    (``implicit_basis_vector``, with its fallback near the poles) and ``e_p = k x e_s``."""
    import drjit as dr
    from sionna.rt.utils.jones import implicit_basis_vector

    e_s = implicit_basis_vector(k)
    return e_s, dr.cross(k, e_s)


def jones_to_world(jones, k):
    """Sionna's real 4-vector Jones field ``(Re S, Re P, Im S, Im P)`` of a wave along unit ``k``
    as world-frame (real, imaginary) 3-vectors."""
    e_s, e_p = _implicit_basis(k)
    return jones.x * e_s + jones.y * e_p, jones.z * e_s + jones.w * e_p


def world_to_jones(e_re, e_im, k):
    """The inverse of :func:`jones_to_world` for a field transverse to ``k``."""
    import drjit as dr
    import mitsuba as mi

    e_s, e_p = _implicit_basis(k)
    return mi.Vector4f(dr.dot(e_re, e_s), dr.dot(e_re, e_p), dr.dot(e_im, e_s), dr.dot(e_im, e_p))


def diffracted_bundle_area(s_m, s_prime_m, ki, e_hat):
    """Area (m^2 per m of edge and rad of cone angle) that the rays diffracted around
    ``(l, phi)`` cover on a plane normal to them at ``s_m`` from the edge; the source lies
    ``s_prime_m`` before it, ``ki`` its unit incident direction, ``e_hat`` the unit edge.

    ``d/dphi`` moves the point by ``s sin(beta)``, ``d/dl`` by ``sin(beta) (s + s') / s'`` across
    it (the source at ``s'`` turns the Keller cone as ``l`` moves), so
    ``dA = s (s + s') sin^2(beta) / s' dl dphi``. Sionna's
    ``RadioMap._diffraction_integration_weight`` (forward-mode AD on any plane) gives the same for
    that plane (tests/test_one_pass.py) at several times the cost."""
    import drjit as dr

    sin2_beta = dr.maximum(1.0 - dr.square(dr.dot(ki, e_hat)), 0.0)
    return s_m * (s_m + s_prime_m) * sin2_beta / s_prime_m


_KEYS = ("shape", "prim0", "primn", "local_edge", "o", "e_hat", "n0", "nn", "length", "src", "plane_n",
         "plane_off", "order")
_VEC = {"o", "e_hat", "n0", "nn", "src", "plane_n"}
_DTYPES = {"shape": np.uint32, "prim0": np.uint32, "primn": np.uint32, "local_edge": np.uint32, "order": np.int64}


def _lex_less(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise lexicographic ``a < b`` of ``[n, 3]`` arrays."""
    lt, eq = a < b, a == b
    return lt[:, 0] | (eq[:, 0] & (lt[:, 1] | (eq[:, 1] & lt[:, 2])))
