"""Corrections to Sionna RT that the project applies when it selects the Mitsuba variant
(:func:`simart_pipeline.engine.init`, the one way to reach Sionna), each with the measurement that
found it and a test that fails without it.

- **PathSolver's diffraction distances** (Sionna RT 2.2.0,
  ``FieldCalculator._diffraction_compute_s_s_prime``). The walk over a path's interactions adds
  the segment to the vertex slot of the first *empty* interaction before it stops, so every path
  with diffraction that is shorter than ``max_depth`` gets an extra segment to a stale vertex in
  ``s`` (the unfolded length after the diffraction point, which sets the UTD spreading factor and
  transition function). A (diffraction, reflection) path is then 7-8 dB too weak at ``max_depth`` 3
  and right at 2, where the walk ends before an empty slot (``benchmarks/pathsolver_depth_check.py``;
  docs/ckm-one-pass.md). :func:`diffraction_distances` stops at the empty slot; the rest is Sionna's.
- **PathSolver's diffraction candidates** (Sionna RT 2.2.0, ``SBCandidateGenerator``). A sampled
  diffraction point lies exactly on its edge, and the generator tests the target's visibility
  from it (and spawns the next segment) with an offset along the *hit face's* normal towards the
  target's side, which can put the origin on the other face's plane: whether the test passes then
  depends on the vertices' last bits. On the urban scene a lit building corner whose footprint
  vertices lie millimetres off whole metres never got a candidate (its field, -111.6 dB at a street
  cell, appeared once the vertices were rounded; ``benchmarks/pathsolver_corner_check.py``).
  :func:`diffraction_sample_off_the_edge` moves the sampled point 1 mm off the edge along the
  wedge's exterior bisector, as Sionna's image method does for its own visibility tests; the
  image method then computes each path's exact diffraction point from the wedge.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


@dr.syntax
def diffraction_distances(self, paths, src_positions, tgt_positions):
    """``(s, s')`` per path: the lengths after and before its diffraction point (Sionna's
    ``_diffraction_compute_s_s_prime`` with the walk stopped at the first empty interaction)."""
    from sionna.rt.constants import InteractionType

    num_paths = paths.buffer_size
    s = dr.zeros(mi.Float, num_paths)
    s_prime = dr.zeros(mi.Float, num_paths)
    active = dr.full(mi.Bool, True, num_paths)
    depth = dr.full(mi.UInt, 1, num_paths)
    max_depth = paths.max_depth
    prev_vertex = dr.copy(src_positions)
    post_diffraction = dr.full(mi.Bool, False, num_paths)
    while dr.hint(active, mode=self.loop_mode):
        interaction_type = paths.get_interaction_type(depth, active)
        active &= interaction_type != InteractionType.NONE  # the correction: no segment to an empty slot
        diffraction = active & (interaction_type == InteractionType.DIFFRACTION)
        vertex = paths.get_vertex(depth, active)
        length = dr.norm(vertex - prev_vertex)
        s[post_diffraction & active] += length
        s_prime[~post_diffraction & active] += length
        post_diffraction |= diffraction
        prev_vertex = dr.select(active, vertex, prev_vertex)
        depth += 1
        active &= depth <= max_depth
    last_segment_length = dr.norm(tgt_positions - prev_vertex)
    s[post_diffraction] += last_segment_length
    s_prime[~post_diffraction] += last_segment_length
    return s, s_prime


DIFFRACTION_SAMPLE_OFFSET_M = 1e-3  # Sionna's image method offsets its diffraction points by this much


def diffraction_sample_off_the_edge(self, si, ray_origin, ki_world, sample1, sample2, sample2_diffraction,
                                    loc_en_inter, diffraction_enabled, edge_diffraction_enabled, active):
    """Sionna's ``SBCandidateGenerator._sample_radio_material``, with a sampled diffraction point
    moved off its edge along the wedge's exterior bisector (free edges have none: left as they are)."""
    from sionna.rt.constants import InteractionType

    s, n, wedges = SIONNAS["sample_radio_material"](self, si, ray_origin, ki_world, sample1, sample2,
                                                    sample2_diffraction, loc_en_inter, diffraction_enabled,
                                                    edge_diffraction_enabled, active)
    if diffraction_enabled:
        # the method leaves the interactions it enabled in si.dp_du.z: exactly DIFFRACTION where it
        # sampled one
        sampled = dr.reinterpret_array(mi.UInt, si.dp_du.z) == mi.UInt(InteractionType.DIFFRACTION)
        bisector = dr.normalize(wedges.n0 + wedges.nn)
        si.p = dr.select(sampled & (wedges.prim0 != wedges.primn), si.p + DIFFRACTION_SAMPLE_OFFSET_M * bisector, si.p)
    return s, n, wedges


SIONNAS = {}  # what apply() replaced, by name (tests compare against it)


def apply() -> None:
    """Install the corrections (idempotent)."""
    from sionna.rt.path_solvers.field_calculator import FieldCalculator
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    # the first call keeps Sionna's own methods; a later one finds these corrections in place
    SIONNAS.setdefault("diffraction_distances", FieldCalculator._diffraction_compute_s_s_prime)
    SIONNAS.setdefault("sample_radio_material", SBCandidateGenerator._sample_radio_material)
    FieldCalculator._diffraction_compute_s_s_prime = diffraction_distances
    SBCandidateGenerator._sample_radio_material = diffraction_sample_off_the_edge
