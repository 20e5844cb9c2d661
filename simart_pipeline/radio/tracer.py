"""Sionna RT PathSolver, called one way: load a radio scene, place devices, trace, sort paths.

Everything the project traces goes through :meth:`RadioScene.trace`. It batches receivers into as
few solver calls as memory allows (the deterministic solver holds about 48 B per sample, bounce and
receiver: :func:`receivers_per_call`), runs ``PathSolver(deterministic=True)`` with the configured
seed, and returns the paths sorted per (receiver, transmitter): valid first, then by delay, then by
interaction sequence, so that two runs compare entry by entry.

Entries that hold no path (``valid`` false) are filled, never left as Sionna leaves them: ``a = 0``,
``tau_s = -1`` (an impossible delay), zero angles, Doppler and interaction points.

Four guards keep every path once and only once, every kept one finite and physical:

- Duplicates: PathSolver sometimes returns one path twice (same objects and primitives, vertices
  millimetres apart), which adds 3 dB to a link's gain. :func:`drop_duplicate_paths` keeps the first.
- Non-finite amplitudes: PathSolver 2.2 with refraction at 1e6 samples returned a second
  line-of-sight entry with a NaN amplitude for 5 of 360 receivers in Sionna's street canyon, which
  made every sum over the receiver's paths NaN. :func:`drop_non_finite_paths` marks such entries
  invalid (``RadioScene.non_finite_paths`` counts them).
- Diffraction into a solid: Sionna's wedges are each mesh's own edges. Where a building's roof is
  a mesh of its own (Sionna's Munich), every roof edge is a plate's free edge whose lower quarter
  lies inside the building; where two building parts meet, a corner of one diffracts into the
  other. With refraction such a path leaves the building through a wall, one transmission short:
  at Munich's cell (-114.5, 162) m one (a roof edge, a reflection inside, a transmission out) was
  56 % of PathSolver's gain.
  :func:`drop_paths_diffracted_into_solids` drops every path whose diffraction moves it into or out
  of a solid of the static scene (``RadioScene.paths_diffracted_into_solids`` counts them); the
  one-pass CKM's diffracted rays obey the same rule (:mod:`simart_pipeline.ckm.diffraction`).
- Candidate cap: Sionna stores at most ``max_num_paths_per_src`` candidates per source over all
  receivers of a call and drops the rest without a word (diffraction keeps every candidate). The
  tracer counts the candidates of each call; a call that reaches the cap is split in two (or, for
  one receiver, rerun with a doubled cap) until none does.

The cap also sizes Sionna's candidate buffers, which are zero-filled on every call: at the default
1e6 per source that fill was a third of a moving-actor CIR trace (about 100 calls of a few
receivers, each finding a few hundred candidates). So after its first call a radio scene sizes the
cap from what it has seen (:meth:`RadioScene._learned_cap`); a call that reaches such a learned
cap is rerun at the configured one. A run's paths are therefore those of the configured cap,
whichever cap a call started with.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from simart_pipeline import engine
from simart_pipeline.config import Array, Materials, RayTracing, SceneConfig
from simart_pipeline.radio import materials
from simart_pipeline.scene.actors import HIDDEN_POINT_M
from simart_pipeline.vocabulary import InteractionKind

RX_NEAR_TX_M = 0.01  # Sionna RT silently drops the LoS path of a receiver this close to a transmitter
INVALID_DELAY_S = -1.0
SOLVER_BYTES_PER_SAMPLE_BOUNCE_RX = 48  # measured: 100 rx x 1e5 samples: 0.46 / 1.2 / 2.3 GB at depth 1 / 3 / 6
# The default (non-deterministic) candidate generator silently loses paths when samples x receivers
# of one call grows too large: Munich with diffraction at 1e8 samples, 40 receivers in one call lost
# a cell's double reflections (RMS delay spread 39 ns against 76-83 ns with 1, 2, 10 or 22 receivers
# per call, the gain 0.25 dB low) and the candidate count did not show it. Calls stay below this.
MAX_SAMPLES_X_RECEIVERS_PER_CALL = 2**31
# Two paths of one link with equal interaction, object and primitive sequences are one path when
# every vertex is this close: Sionna's duplicates differ by millimetres; two distinct paths with
# the same primitives (one specular point per primitive chain) cannot be 1 cm apart.
DUPLICATE_VERTEX_TOLERANCE_M = 0.01
# A leg of a path next to a diffraction is tested for lying inside a solid at its midpoint (a leg
# between two vertices crosses no face: it lies inside a solid all along or nowhere); legs shorter
# than this are not judged (a midpoint that close to a face may fall on either side).
MIN_JUDGED_LEG_M = 0.1
INVALID_ID = np.uint32(0xFFFFFFFF)
# Actor parts are thin shells (sheet metal, glass panes, a rotor): their slab thickness (m).
ACTOR_PART_THICKNESS_M = 0.01
NO_ACTOR = -1
# Learned candidate cap (see the module docstring): this many times the most candidates a
# receiver has needed so far, rounded up to a power of two (few distinct kernels), and no less
# than the floor.
LEARNED_CAP_MARGIN = 4
LEARNED_CAP_FLOOR = 2**14


@dataclass
class TracedPaths:
    """Sorted paths of ``num_rx`` receivers and ``num_tx`` transmitters (numpy)."""

    a: np.ndarray            # [num_rx, rx_ant, num_tx, tx_ant, path] complex64
    tau_s: np.ndarray        # [num_rx, num_tx, path] float64; -1 where invalid
    theta_t: np.ndarray      # [num_rx, num_tx, path] float32 rad, world frame; 0 where invalid
    phi_t: np.ndarray
    theta_r: np.ndarray
    phi_r: np.ndarray
    doppler_hz: np.ndarray   # [num_rx, num_tx, path] float32
    interaction: np.ndarray  # [num_rx, num_tx, depth, path] uint8
    valid: np.ndarray        # [num_rx, num_tx, path] bool
    vertices_m: np.ndarray | None = None  # [num_rx, num_tx, depth, path, 3] float32, if asked for
    actor: np.ndarray | None = None  # [num_rx, num_tx, depth, path] int16: the actor index each
    #                                  bounce interacts with, NO_ACTOR for the static scene / none

    @property
    def los(self) -> np.ndarray:
        return self.valid & np.all(self.interaction == InteractionKind.NONE, axis=-2)


def sionna_array(array: Array):
    import sionna.rt as rt

    return rt.PlanarArray(num_rows=array.rows, num_cols=array.cols,
                          vertical_spacing=array.spacing_wavelengths,
                          horizontal_spacing=array.spacing_wavelengths,
                          pattern=array.pattern, polarization=array.polarization)


def receivers_per_call(solver: RayTracing, deterministic: bool = True) -> int:
    """Receivers per PathSolver call: the configured cap, lowered to fit the memory budget of the
    deterministic solver (the default solver's working set hardly grows with receivers, but it
    loses paths above :data:`MAX_SAMPLES_X_RECEIVERS_PER_CALL` samples x receivers)."""
    if not deterministic:
        return max(1, min(solver.max_receivers_per_call, MAX_SAMPLES_X_RECEIVERS_PER_CALL // solver.samples_per_src))
    per_rx = SOLVER_BYTES_PER_SAMPLE_BOUNCE_RX * max(solver.max_depth, 1) * solver.samples_per_src
    fit = int(solver.max_solver_memory_gib * 2**30 // per_rx)
    return max(1, min(solver.max_receivers_per_call, fit))


class RadioScene:
    """A Sionna RT scene loaded once, with its frequency, arrays, solver settings and weather materials.

    Built from explicit arguments (a notebook needs no scene config) or from a scene config with
    :meth:`from_config`.

    :param scene_xml: the radio mesh (Mitsuba XML); None for an empty scene (free space).
    :param frequency_hz: carrier frequency (Hz); ``bandwidth_hz``: the scene's bandwidth (Hz).
    :param tx_array, rx_array: the arrays of every transmitter and every receiver (Sionna RT holds
        one of each per scene).
    :param solver: PathSolver settings (depth, samples, mechanisms, seed, memory budget).
    :param weather: the weather's name (rain swaps dry materials for wet ones).
    :param weather_materials: {material: the one that replaces it in this weather}; default: the
        weather's row of :data:`simart_pipeline.radio.materials.WEATHER_MATERIALS`.
    :param material_thickness_m: thickness of the materials swapped in for the weather (m).
    """

    def __init__(self, scene_xml: str | Path | None, *, frequency_hz: float, bandwidth_hz: float,
                 tx_array: Array, rx_array: Array, solver: RayTracing | None = None,
                 weather: str = "sunny", weather_materials: dict[str, str] | None = None,
                 material_thickness_m: float = Materials().thickness_m):
        engine.init()
        import sionna.rt as rt

        self.frequency_hz = float(frequency_hz)
        self.bandwidth_hz = float(bandwidth_hz)
        self.tx_array_config, self.rx_array_config = tx_array, rx_array
        self.solver_config = solver if solver is not None else RayTracing()
        self.material_thickness_m = material_thickness_m
        self.weather = weather
        self.scene_xml = Path(scene_xml) if scene_xml else None
        self.scene = rt.load_scene(str(scene_xml), merge_shapes=False) if scene_xml else rt.load_scene()
        self.scene.frequency = frequency_hz
        self.scene.bandwidth = bandwidth_hz
        self.scene.tx_array = sionna_array(tx_array)
        self.scene.rx_array = sionna_array(rx_array)
        if weather_materials is None:
            if weather not in materials.WEATHER_MATERIALS:
                raise ValueError(f"unknown weather {weather!r}; known: {', '.join(materials.WEATHER_MATERIALS)}")
            weather_materials = materials.WEATHER_MATERIALS[weather]
        self.weather_materials = dict(weather_materials)
        self.material_overrides = self._apply_weather(weather, weather_materials)
        self.solvers = {True: rt.PathSolver(deterministic=True), False: rt.PathSolver(deterministic=False)}
        self.cap_retries = 0  # solver calls rerun because their candidates reached the configured cap
        self.non_finite_paths = 0  # valid entries with a non-finite amplitude, dropped (module docstring)
        self.paths_diffracted_into_solids = 0  # ... whose diffraction enters or leaves a solid, dropped
        self._static_solids = None  # the static scene's solids (scene.solids), made on first need
        self.learned_cap_retries = 0  # ... reached a cap learned from earlier calls (rerun at the configured)
        # most candidates per source and receiver of any call so far, per candidate generator
        # (deterministic or Sionna's default: the default stores more per receiver)
        self._candidates_per_rx: dict[bool, float] = {}
        self.actors: list = []
        self._actor_parts: list[tuple[int, object, np.ndarray]] = []  # (actor, SceneObject, body vertices)
        self._object_actor = np.zeros(0, np.int16)  # Sionna object id -> actor index or NO_ACTOR

    def add_actors(self, actors) -> None:
        """Put every actor's body in the scene, one SceneObject per body part with the part's radio
        material (one scene edit); they stay out of every trace until :meth:`place_actors`."""
        if self.actors:
            raise RuntimeError("the actors are already in this radio scene")
        import mitsuba as mi
        import sionna.rt as rt

        mats: dict[str, object] = {}
        objs, owners = [], []
        for a, act in enumerate(actors):
            for k, mat in enumerate(act.body.part_materials):
                sel = np.flatnonzero(act.body.face_part == k)
                if not len(sel):
                    continue
                part = act.body.mesh.submesh([sel], append=True)
                name = f"actor-{act.name}-{k}"
                mesh = mi.Mesh(name, len(part.vertices), len(part.faces), has_vertex_normals=False,
                               has_vertex_texcoords=False)
                params = mi.traverse(mesh)
                params["vertex_positions"] = mi.Float(np.ascontiguousarray(part.vertices, np.float32).ravel())
                params["faces"] = mi.UInt32(np.ascontiguousarray(part.faces, np.uint32).ravel())
                params.update()
                mat = self.weather_materials.get(mat, mat)  # rain wets actors like everything else
                s = float(act.scattering_coefficient)
                if (mat, s) not in mats:
                    mats[mat, s] = materials.sionna_material(
                        mat, self.frequency_hz, ACTOR_PART_THICKNESS_M, suffix=f"_actor_s{round(100 * s)}")
                    mats[mat, s].scattering_coefficient = s
                objs.append(rt.SceneObject(mi_mesh=mesh, name=name, radio_material=mats[mat, s]))
                owners.append(a)
        if not objs:
            return
        self.scene.edit(add=objs)
        params = self.scene.mi_scene_params
        self.actors = list(actors)
        self._actor_parts = []
        for a, obj in zip(owners, objs):
            # Sionna merges duplicate vertices on construction: read back what the scene holds.
            v = np.array(params[obj.mi_mesh.id() + ".vertex_positions"], np.float64).reshape(-1, 3)
            self._actor_parts.append((a, obj, v))
        ids = {obj.object_id: a for a, obj, _ in self._actor_parts}
        table = np.full(max(o.object_id for o in self.scene.objects.values()) + 1, NO_ACTOR, np.int16)
        for oid, a in ids.items():
            table[oid] = a
        self._object_actor = table
        self.place_actors(None, 0, hidden=range(len(self.actors)))

    def place_actors(self, poses, i: int, hidden=()) -> None:
        """Move every actor to its pose and velocity of instant ``i`` of ``poses``
        (``scene.actors.ActorPoses``); actors whose indices are in ``hidden`` leave the scene
        (their triangles collapse to one point, which no ray hits)."""
        import mitsuba as mi

        params = self.scene.mi_scene_params
        hidden = set(hidden)
        for a, obj, v in self._actor_parts:
            if a in hidden:
                world, vel = np.broadcast_to(HIDDEN_POINT_M, v.shape), np.zeros(3)
            else:
                world = poses.to_world(a, i, v)
                vel = poses.velocity_mps[a, i]
            params[obj.mi_mesh.id() + ".vertex_positions"] = mi.Float(
                np.ascontiguousarray(world, np.float32).ravel())
            obj.velocity = mi.Vector3f(*[float(x) for x in vel])
        params.update()
        self.scene.scene_geometry_updated()

    @classmethod
    def from_config(cls, scene_xml: str | Path | None, cfg: SceneConfig, weather: str = "sunny") -> "RadioScene":
        """The radio scene of a scene config: its carrier, bandwidth, arrays, solver and materials."""
        return cls(scene_xml, frequency_hz=cfg.ofdm.carrier_frequency_hz, bandwidth_hz=cfg.ofdm.bandwidth_hz,
                   tx_array=cfg.base_stations[0].array, rx_array=cfg.platforms[0].array,
                   solver=cfg.ray_tracing, weather=weather,
                   weather_materials=cfg.materials.weather_table()[weather],
                   material_thickness_m=cfg.materials.thickness_m)

    def _apply_weather(self, weather: str, swaps: dict[str, str]) -> dict[str, str]:
        swapped: dict[str, object] = {}
        applied = {}
        for name, obj in sorted(self.scene.objects.items()):
            base = materials.material_name(obj.radio_material)
            target = swaps.get(base, base)
            if target == base:
                continue
            if target not in swapped:
                swapped[target] = materials.sionna_material(
                    target, self.frequency_hz, self.material_thickness_m, suffix=f"_{weather}")
            obj.radio_material = swapped[target]
            applied[name] = f"{base} -> {target}"
        return applied

    @property
    def wavelength_m(self) -> float:
        return float(np.array(self.scene.wavelength).ravel()[0])

    def array_positions_m(self, which: str) -> np.ndarray:
        """Antenna positions [num_ant, 3] in the device's own frame (boresight +x)."""
        arr = self.scene.tx_array if which == "tx" else self.scene.rx_array
        return np.array(arr.positions(self.wavelength_m)).T.astype(np.float64)

    def radio_materials(self) -> dict[str, str]:
        """Radio material name of every scene object, after the weather's swaps."""
        return {name: materials.material_name(obj.radio_material)
                for name, obj in sorted(self.scene.objects.items())}

    def material_properties(self) -> dict[str, tuple[float, float, float]]:
        """(relative permittivity, conductivity S/m, thickness m) of every object at the frequency."""
        out = {}
        for name, obj in sorted(self.scene.objects.items()):
            m = obj.radio_material
            out[name] = tuple(float(np.array(v).ravel()[0]) for v in
                              (m.relative_permittivity, m.conductivity, m.thickness))
        return out

    def content_sha256(self) -> str:
        """Hash of everything a trace depends on except the device positions: the radio mesh files,
        every object's material properties at the carrier frequency, frequency, bandwidth, arrays
        and solver settings. Two weathers with equal hashes give equal paths."""
        h = hashlib.sha256()
        if self.scene_xml is not None:
            root = self.scene_xml.parent
            for f in sorted(p for p in root.rglob("*") if p.is_file()):
                h.update(str(f.relative_to(root)).encode())
                h.update(hashlib.sha256(f.read_bytes()).digest())
        import sionna.rt

        h.update(json.dumps({
            "materials": {k: [repr(x) for x in v] for k, v in self.material_properties().items()},
            "frequency_hz": self.frequency_hz, "bandwidth_hz": self.bandwidth_hz,
            "tx_array": self.tx_array_config.model_dump(),
            "rx_array": self.rx_array_config.model_dump(),
            "solver": self.solver_config.model_dump(exclude={"max_receivers_per_call", "max_solver_memory_gib"}),
            "actors": [[a, str(obj.radio_material.name), hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()]
                       for a, obj, v in self._actor_parts],
            "sionna_rt": sionna.rt.__version__,
        }, sort_keys=True).encode())
        return h.hexdigest()

    def trace(self, tx_positions: np.ndarray, tx_orientations_rad: np.ndarray,
              rx_positions: np.ndarray, rx_velocities: np.ndarray | None = None,
              rx_orientations_rad: np.ndarray | None = None,
              tx_velocities: np.ndarray | None = None, with_vertices: bool = False,
              deterministic: bool = True) -> TracedPaths:
        """Trace all transmitters to all receivers.

        :param tx_positions: [num_tx, 3] m, world; ``tx_orientations_rad`` [num_tx, 3] (yaw, pitch, roll)
        :param rx_positions: [num_rx, 3] m; ``rx_velocities`` [num_rx, 3] m/s;
            ``rx_orientations_rad`` [num_rx, 3]
        :param with_vertices: also return every path's interaction points
        :param deterministic: ``PathSolver(deterministic=True)`` (the default, for CIRs); False runs
            Sionna's default candidate generator, which is cheaper per receiver (see docs/ckm.md)
        """
        import sionna.rt as rt

        rt_cfg = self.solver_config
        num_rx, num_tx = len(rx_positions), len(tx_positions)
        if num_rx == 0 or num_tx == 0:
            raise ValueError("nothing to trace: no receiver or no transmitter")

        def vec(v):
            return [float(c) for c in v]

        for i in range(num_tx):
            self.scene.add(rt.Transmitter(
                f"tx{i}", position=vec(tx_positions[i]), orientation=vec(tx_orientations_rad[i]),
                velocity=None if tx_velocities is None else vec(tx_velocities[i])))
        chunks = []
        # PathSolver's buffers are sized per call: Dr.Jit's cache of freed blocks handed back before
        # (what a one-pass or a render left cached does not add to the solver's peak) and after
        # (0.39 against 0.40 s for one receiver's call, canyon, every mechanism)
        engine.release_memory_cache()
        try:
            step = receivers_per_call(rt_cfg, deterministic)
            limit = int(rt_cfg.max_num_paths_per_src)
            for start in range(0, num_rx, step):
                idx = list(range(start, min(start + step, num_rx)))
                cap = self._learned_cap(len(idx), limit, deterministic)
                # each call's paths cleaned and cut to its most valid paths as it comes: only
                # those stay in memory (with diffuse reflection a call's arrays are padded to
                # tens of thousands of candidates; every call's at once ran a 24 GB machine out)
                chunks += [self._cleaned(c, with_vertices, tx_positions) for c in self._solve(
                    idx, cap, num_tx, rx_positions, rx_velocities, rx_orientations_rad, deterministic, limit)]
        finally:
            for i in range(num_tx):
                self.scene.remove(f"tx{i}")
            for name in list(self.scene.receivers):
                self.scene.remove(name)
            engine.release_memory_cache()
        d = _concat(chunks) if len(chunks) > 1 else chunks[0]
        names = {f.name for f in fields(TracedPaths)}
        return TracedPaths(**{k: v for k, v in d.items() if k in names})

    def _cleaned(self, d: dict[str, np.ndarray], with_vertices: bool, tx_positions: np.ndarray) -> dict[str, np.ndarray]:
        """One call's paths: actors named, non-finite, duplicate and diffracted-into-solid paths dropped, sorted
        (:func:`_ordered`), and cut to the most valid paths of any of its (receiver, transmitter)
        pairs. Every step is per pair, so calls cleaned apart and then joined give what the
        joined calls cleaned at once would (up to the invalid padding at the end)."""
        rx_positions = d.pop("rx_positions_m")
        obj = d["objects"].astype(np.int64)
        table = np.append(self._object_actor, NO_ACTOR).astype(np.int16)  # last: any other id
        d["actor"] = table[np.where((obj >= 0) & (obj < len(self._object_actor)), obj, len(table) - 1)]
        d, dropped = drop_non_finite_paths(d)
        self.non_finite_paths += dropped
        # Sorted first so that the path kept of two duplicates is the earlier one, whatever order
        # the solver returned them in; sorted again after (valid first)
        d, dropped = drop_paths_diffracted_into_solids(drop_duplicate_paths(_ordered(d)), tx_positions, rx_positions,
                                                       self.points_inside)
        self.paths_diffracted_into_solids += dropped
        d = _ordered(d)
        if not with_vertices:
            d.pop("vertices_m")
        n = int(d["valid"].sum(axis=-1).max(initial=0))  # the valid paths lead every pair's row
        # copies, not views: a view would keep the padded arrays alive
        return {k: np.ascontiguousarray(v[..., :n, :] if k == "vertices_m" else v[..., :n]) for k, v in d.items()}

    def points_inside(self, points_m: np.ndarray) -> np.ndarray:
        """``[N]`` bool: which of ``points_m [N, 3]`` lie inside a solid of the static scene (the
        buildings; actors are thin shells and move: :func:`simart_pipeline.ckm.outdoor.points_inside`
        on the scene's meshes less the actors' parts, their solids made once)."""
        from simart_pipeline.ckm.outdoor import points_inside, radio_triangles
        from simart_pipeline.scene.solids import mesh_solids

        if self._static_solids is None:
            actor_shapes = {obj.mi_mesh.id() for _, obj, _ in self._actor_parts}
            self._static_solids = mesh_solids(radio_triangles(self, skip_shapes=actor_shapes))
        return points_inside(self, np.asarray(points_m, np.float64).reshape(-1, 3), self._static_solids)

    def _learned_cap(self, num_rx: int, limit: int, deterministic: bool = True) -> int:
        """The candidate cap of a call of ``num_rx`` receivers: the configured ``limit`` until a
        call of the same candidate generator has been counted, then :data:`LEARNED_CAP_MARGIN`
        times the most candidates per receiver seen, as a power of two of at least
        :data:`LEARNED_CAP_FLOOR`, at most ``limit``."""
        per_rx = self._candidates_per_rx.get(deterministic)
        if per_rx is None:
            return limit
        need = max(LEARNED_CAP_FLOOR, LEARNED_CAP_MARGIN * per_rx * num_rx)
        return min(limit, 1 << int(np.ceil(np.log2(need))))

    def _solve(self, idx: list[int], cap: int, num_tx: int, rx_positions, rx_velocities,
               rx_orientations_rad, deterministic: bool, limit: int) -> list[dict[str, np.ndarray]]:
        """One PathSolver call for receivers ``idx`` with ``max_num_paths_per_src = cap``. A call
        whose candidates reach a cap below ``limit`` (a learned one) is rerun at ``limit``; one
        that reaches ``limit`` is split in halves (one receiver: the cap doubles)."""
        import sionna.rt as rt

        rt_cfg = self.solver_config

        def vec(v):
            return [float(c) for c in v]

        for i in idx:
            kw = {}
            if rx_velocities is not None:
                kw["velocity"] = vec(rx_velocities[i])
            if rx_orientations_rad is not None:
                kw["orientation"] = vec(rx_orientations_rad[i])
            self.scene.add(rt.Receiver(f"rx{i}", position=vec(rx_positions[i]), **kw))
        try:
            solver = self.solvers[deterministic]
            counts = _count_candidates(solver)
            paths = solver(
                self.scene, max_depth=rt_cfg.max_depth, max_num_paths_per_src=cap,
                samples_per_src=rt_cfg.samples_per_src, synthetic_array=True, los=rt_cfg.los,
                specular_reflection=rt_cfg.specular_reflection,
                diffuse_reflection=rt_cfg.diffuse_reflection, refraction=rt_cfg.refraction,
                diffraction=rt_cfg.diffraction, edge_diffraction=rt_cfg.edge_diffraction,
                seed=rt_cfg.seed)
            saturated = max(counts, default=0) >= cap
            if not saturated:
                out = _to_numpy(paths, num_tx, len(idx), rt_cfg.max_depth,
                                self.scene.rx_array.num_ant, self.scene.tx_array.num_ant)
                out["rx_positions_m"] = np.asarray(rx_positions, np.float64)[idx]
        finally:
            for i in idx:
                self.scene.remove(f"rx{i}")
        if not saturated:
            seen = max(counts, default=0) / len(idx)
            self._candidates_per_rx[deterministic] = max(self._candidates_per_rx.get(deterministic, 0.0), seen)
            return [out]
        if cap < limit:
            self.learned_cap_retries += 1
            return self._solve(idx, limit, num_tx, rx_positions, rx_velocities, rx_orientations_rad,
                               deterministic, limit)
        self.cap_retries += 1
        if len(idx) == 1:
            return self._solve(idx, 2 * cap, num_tx, rx_positions, rx_velocities,
                               rx_orientations_rad, deterministic, 2 * cap)
        half = len(idx) // 2
        return (self._solve(idx[:half], cap, num_tx, rx_positions, rx_velocities, rx_orientations_rad,
                            deterministic, limit)
                + self._solve(idx[half:], cap, num_tx, rx_positions, rx_velocities, rx_orientations_rad,
                              deterministic, limit))

    def grid_scan(self, tx_positions: np.ndarray, tx_orientations_rad: np.ndarray,
                  grid_points_m: np.ndarray, deterministic: bool = True) -> TracedPaths:
        """Fixed transmitters and a grid of virtual receivers (static, default orientation): the
        CKM generator's reference mode. ``grid_points_m`` [num_points, 3]."""
        return self.trace(tx_positions, tx_orientations_rad, np.asarray(grid_points_m, np.float64),
                          deterministic=deterministic)


def merge_traced(parts: list[tuple[np.ndarray, TracedPaths]], num_rx: int) -> TracedPaths:
    """One :class:`TracedPaths` of ``num_rx`` receivers from calls that traced receivers
    ``idx`` each; path slots padded to the largest count with the invalid fill."""
    order = np.concatenate([idx for idx, _ in parts])
    if not np.array_equal(np.sort(order), np.arange(num_rx)):
        raise ValueError("merge_traced: the calls must cover every receiver exactly once")
    if np.array_equal(order, np.arange(num_rx)) and len(parts) == 1:
        return parts[0][1]
    d = _concat([{f.name: getattr(p, f.name) for f in fields(TracedPaths) if getattr(p, f.name) is not None}
                 for _, p in parts])
    back = np.argsort(order, kind="stable")  # concatenated rows back into receiver order
    return TracedPaths(**{k: v[back] for k, v in d.items()})


def _count_candidates(solver) -> list[int]:
    """Hook Sionna's candidate generator (a private attribute of PathSolver in Sionna RT 1.x) so
    that the returned list receives the candidates stored per source by the next call."""
    counts: list[int] = []
    gen = solver._candidate_generator
    original = getattr(gen, "_simart_original", gen)

    def counting(*args, **kwargs):
        buf = original(*args, **kwargs)
        n = int(np.array(buf.paths_counter).ravel()[0])
        src = np.array(buf.source_indices)[:n].astype(np.int64)
        counts.extend(np.bincount(src).tolist() if n else [0])
        return buf

    counting._simart_original = original
    solver._candidate_generator = counting
    return counts


def drop_non_finite_paths(d: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
    """``d`` with its valid entries whose amplitude ``a`` [rx, rx_ant, tx, tx_ant, path] is not
    finite for every antenna pair marked invalid, and how many there were."""
    bad = d["valid"] & ~np.isfinite(d["a"]).all(axis=(1, 3))
    if not bad.any():
        return d, 0
    return {**d, "valid": d["valid"] & ~bad}, int(bad.sum())


def drop_duplicate_paths(d: dict[str, np.ndarray],
                         tolerance_m: float = DUPLICATE_VERTEX_TOLERANCE_M) -> dict[str, np.ndarray]:
    """Mark invalid every path that repeats an earlier one of the same (receiver, transmitter):
    equal interaction, object and primitive sequences and every vertex within ``tolerance_m``
    (largest coordinate difference) of a path kept before it. The first in path order is kept
    (deterministic: :func:`_ordered`'s order, whatever order the solver returned); a path with a
    non-finite vertex repeats none.

    ``d`` holds ``valid`` [rx, tx, path], ``interaction``, ``objects``, ``primitives``
    [rx, tx, depth, path] and ``vertices_m`` [rx, tx, depth, path, 3]; returns a copy with
    ``valid`` updated, ``a`` zeroed where dropped, and without ``objects`` and ``primitives``.

    Paths are grouped by their id sequences (a sort), and only within a group are vertices
    compared, through a k-d tree's pairs within the tolerance: with diffuse reflection one
    primitive (a ground triangle) holds thousands of a receiver's paths, which a comparison of
    every pair made quadratic (4,000 paths on one primitive: 66 s, now 0.06 s).
    """
    from scipy.spatial import cKDTree

    valid = d["valid"].copy()
    inter, obj, prim, vert = d["interaction"], d["objects"], d["primitives"], d["vertices_m"]
    num_rx, num_tx, num_paths = valid.shape
    for r in range(num_rx):
        for t in range(num_tx):
            ks = np.flatnonzero(valid[r, t])
            if ks.size < 2:
                continue
            ids = np.concatenate([a[r, t][:, ks].astype(np.int64) for a in (inter, obj, prim)]).T
            _, group, counts = np.unique(ids, axis=0, return_inverse=True, return_counts=True)
            group = group.ravel()
            xyz = vert[r, t][:, ks].astype(np.float64).transpose(1, 0, 2).reshape(ks.size, -1)
            shared = np.flatnonzero((counts[group] > 1) & np.isfinite(xyz).all(axis=1))
            if shared.size < 2:
                continue
            # the group as one more coordinate: two groups are at least 1 apart, beyond any tolerance
            points = np.column_stack([group[shared] * max(1.0, 2.0 * tolerance_m), xyz[shared]])
            pairs = cKDTree(points).query_pairs(tolerance_m, p=np.inf, output_type="ndarray")
            if not len(pairs):
                continue
            pairs = np.sort(shared[pairs], axis=1)  # (earlier, later) in path order
            dropped = np.zeros(ks.size, bool)
            for i, j in pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]:  # by the later path
                if not dropped[i]:  # a repeat of a path kept before it
                    dropped[j] = True
            valid[r, t, ks[dropped]] = False
    out = {k: v for k, v in d.items() if k not in ("objects", "primitives")}
    out["valid"] = valid
    out["a"] = np.where(valid[:, None, :, None, :], d["a"], 0)
    return out


def drop_paths_diffracted_into_solids(d: dict[str, np.ndarray], tx_positions_m: np.ndarray,
                                      rx_positions_m: np.ndarray, points_inside) -> tuple[dict[str, np.ndarray], int]:
    """Mark invalid every path with a diffraction whose leg in and leg out do not both lie
    outside, or both inside, a solid (``points_inside``: ``[N, 3]`` points to ``[N]`` bool, tested at
    each leg's midpoint; legs shorter than :data:`MIN_JUDGED_LEG_M` are not judged): a diffracted
    ray leaves its wedge into the same region it came from, and a path that crosses a building's
    interior without entering it lacks a transmission. Returns ``d`` with ``valid`` updated and how
    many paths were dropped.

    ``d`` holds ``valid`` [rx, tx, path], ``interaction`` [rx, tx, depth, path] and ``vertices_m``
    [rx, tx, depth, path, 3]; ``tx_positions_m`` [tx, 3] and ``rx_positions_m`` [rx, 3] end the
    first and last legs."""
    inter, valid = d["interaction"], d["valid"]
    depth = inter.shape[2]
    r, t, k, p = np.nonzero((inter == InteractionKind.DIFFRACTION) & valid[:, :, None, :])
    if not len(r):
        return d, 0
    vert = d["vertices_m"].astype(np.float64)
    tx, rx = np.asarray(tx_positions_m, np.float64), np.asarray(rx_positions_m, np.float64)
    q = vert[r, t, k, p]
    prev = np.where((k > 0)[:, None], vert[r, t, np.maximum(k - 1, 0), p], tx[t])
    k_next = np.minimum(k + 1, depth - 1)
    has_next = (k + 1 < depth) & (inter[r, t, k_next, p] != InteractionKind.NONE)
    nxt = np.where(has_next[:, None], vert[r, t, k_next, p], rx[r])
    judged = (np.isfinite(prev).all(1) & np.isfinite(q).all(1) & np.isfinite(nxt).all(1)
              & (np.linalg.norm(q - prev, axis=1) >= MIN_JUDGED_LEG_M)
              & (np.linalg.norm(nxt - q, axis=1) >= MIN_JUDGED_LEG_M))
    if not judged.any():
        return d, 0
    r, t, p, prev, q, nxt = r[judged], t[judged], p[judged], prev[judged], q[judged], nxt[judged]
    inside = np.asarray(points_inside(np.concatenate([(prev + q) / 2, (q + nxt) / 2])), bool).reshape(2, -1)
    bad = inside[0] != inside[1]
    if not bad.any():
        return d, 0
    valid = valid.copy()
    valid[r[bad], t[bad], p[bad]] = False
    dropped = int(np.count_nonzero(d["valid"] & ~valid))
    return {**d, "valid": valid}, dropped


def _to_numpy(paths, num_tx: int, num_rx: int, max_depth: int, rx_ant: int,
              tx_ant: int) -> dict[str, np.ndarray]:
    # Explicit shapes: a call with no path has zero-size arrays.
    num_paths = np.array(paths.tau).shape[-1]
    shape = (num_rx, num_tx, num_paths)
    re = np.array(paths.a[0])
    a = np.empty(re.shape, np.complex64)  # made in place: no complex128 temporaries
    a.real, a.imag = re, np.array(paths.a[1])
    del re
    out = {
        "a": a.reshape(num_rx, rx_ant, num_tx, tx_ant, num_paths),
        "tau_s": np.array(paths.tau).astype(np.float64).reshape(shape),
        "theta_t": np.array(paths.theta_t).reshape(shape),
        "phi_t": np.array(paths.phi_t).reshape(shape),
        "theta_r": np.array(paths.theta_r).reshape(shape),
        "phi_r": np.array(paths.phi_r).reshape(shape),
        "doppler_hz": np.array(paths.doppler).reshape(shape),
        "valid": np.array(paths.valid).astype(bool).reshape(shape),
    }
    for key, attr, dtype in (("interaction", "interactions", np.uint8), ("objects", "objects", np.uint32),
                             ("primitives", "primitives", np.uint32)):
        v = np.array(getattr(paths, attr)).astype(dtype)
        v = v.reshape(max_depth, num_rx, num_tx, num_paths) if max_depth else \
            np.zeros((0, num_rx, num_tx, num_paths), dtype)
        out[key] = np.moveaxis(v, 0, 2)  # [rx, tx, depth, path]
    # Vertices always: the duplicate test compares them.
    v = np.array(paths.vertices).astype(np.float32)
    v = v.reshape(max_depth, num_rx, num_tx, num_paths, 3) if max_depth else \
        np.zeros((0, num_rx, num_tx, num_paths, 3), np.float32)
    out["vertices_m"] = np.moveaxis(v, 0, 2)  # [rx, tx, depth, path, 3]
    return out


_FILL = {"valid": False, "a": 0, "interaction": 0, "tau_s": INVALID_DELAY_S,
         "objects": INVALID_ID, "primitives": INVALID_ID, "actor": NO_ACTOR}


def _concat(chunks: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Pad every chunk to the largest path count, then join along receivers."""
    n = max(c["tau_s"].shape[-1] for c in chunks)
    padded = []
    for c in chunks:
        k = n - c["tau_s"].shape[-1]
        d = {}
        for key, v in c.items():
            path_axis = v.ndim - 2 if key == "vertices_m" else v.ndim - 1
            pad = [(0, 0)] * v.ndim
            pad[path_axis] = (0, k)
            d[key] = np.pad(v, pad, constant_values=_FILL.get(key, 0))
        padded.append(d)
    return {key: np.concatenate([c[key] for c in padded], axis=0) for key in padded[0]}


def _ordered(d: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per (receiver, transmitter): valid first, then by delay, then by interaction sequence, and
    where those tie by object and primitive sequences and vertices (where ``d`` has them), so the
    order does not depend on the order the solver returned the paths in. Sionna's candidate
    generator appends candidates through an atomic counter, whose order varies between runs on
    several threads; two paths of equal delay and interaction types (a symmetric scene's two
    wedges) then swapped places, and every sum over a receiver's paths moved by an ulp (a CKM
    cell's delay spread, docs/ckm.md)."""
    valid = d["valid"]
    tau = np.where(valid, d["tau_s"], np.inf)
    inter = d["interaction"]  # [rx, tx, depth, path]
    depth = inter.shape[2]
    # np.lexsort: the last key is the primary one.
    keys = []
    if "vertices_m" in d:  # [rx, tx, depth, path, 3]; the least significant keys
        vert = np.where(np.isfinite(d["vertices_m"]), d["vertices_m"], np.inf)
        keys += [vert[:, :, k, :, c] for k in range(depth - 1, -1, -1) for c in (2, 1, 0)]
    for name in ("primitives", "objects"):
        if name in d:
            keys += [d[name][:, :, k, :] for k in range(depth - 1, -1, -1)]
    keys += [inter[:, :, k, :] for k in range(depth - 1, -1, -1)] + [tau, ~valid]
    order = np.lexsort(keys, axis=-1)  # [rx, tx, path]

    def take(key, v):
        if key == "a":  # [rx, rx_ant, tx, tx_ant, path]
            return np.take_along_axis(v, order[:, None, :, None, :], axis=-1)
        if key in ("interaction", "objects", "primitives", "actor"):  # [rx, tx, depth, path]
            return np.take_along_axis(v, order[:, :, None, :], axis=-1)
        if key == "vertices_m":  # [rx, tx, depth, path, 3]
            return np.take_along_axis(v, order[:, :, None, :, None], axis=-2)
        return np.take_along_axis(v, order, axis=-1)

    out = {k: take(k, v) for k, v in d.items()}
    vs = out["valid"]
    out["tau_s"] = np.where(vs, out["tau_s"], INVALID_DELAY_S)
    for k in ("theta_t", "phi_t", "theta_r", "phi_r", "doppler_hz"):
        out[k] = np.where(vs, out[k], 0.0).astype(np.float32)
    out["a"] = np.where(vs[:, None, :, None, :], out["a"], 0).astype(np.complex64)
    out["interaction"] = np.where(vs[:, :, None, :], out["interaction"], 0).astype(np.uint8)
    if "actor" in out:
        out["actor"] = np.where(vs[:, :, None, :] & (out["interaction"] != 0), out["actor"],
                                NO_ACTOR).astype(np.int16)
    if "vertices_m" in out:
        out["vertices_m"] = np.where(vs[:, :, None, :, None], out["vertices_m"], 0).astype(np.float32)
    return out
