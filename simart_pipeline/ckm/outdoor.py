"""How much of each CKM cell lies outdoors: the fast mode's indoor mask.

A sample point is indoors when it lies inside a solid of the radio mesh
(:mod:`simart_pipeline.scene.solids`: a closed part, or one open only at its bottom, such as walls
and a roof without a floor); under a slab, a ceiling box, an overhang or a bridge it is outdoors,
and so it is in a room whose walls, floor and ceiling are separate boxes (``scenes/indoor``) and in
a courtyard. A ray cast straight up with Mitsuba first finds the points with anything above them
(a point inside a solid always has one of its faces above it); only those are counted against the
solids' faces on the vertical line (:func:`simart_pipeline.scene.solids.inside_solids`).

Before, "anything above" was the whole test: it masked every cell of ``scenes/indoor`` (the
ceiling is above them all) and, on Sionna's Munich, points under building parts that hang above
the street (``tests/test_outdoor_mask.py`` checks every sample point of every bundled scene and of
Munich against an independent point-in-solid test).
"""

from __future__ import annotations

import numpy as np

from simart_pipeline.ckm.shoot_bounce import grid_from_centres
from simart_pipeline.scene.meshes import SceneMeshes
from simart_pipeline.scene.solids import Solids, inside_solids, mesh_solids

OUTDOOR_SAMPLES_PER_AXIS = 4
# cells with less of their area outdoors are masked in fast mode (the one-pass divides a cell's sums by
# its outdoor share: power per outdoor area), and say so in the map (layer cell_masked)
DEFAULT_MIN_OUTDOOR_FRACTION = 0.5


def radio_triangles(radio, skip_shapes=()) -> np.ndarray:
    """Every triangle of the radio scene's Mitsuba meshes, ``[F, 3, 3]`` (m, world frame), less
    those of the shapes whose Mitsuba ids ``skip_shapes`` names."""
    tris = [np.zeros((0, 3, 3))]
    for shape in radio.scene.mi_scene.shapes():
        if shape.id() in skip_shapes:
            continue
        if not shape.is_mesh():
            raise ValueError(f"shape {shape.id()!r} of the radio scene is not a triangle mesh")
        v = shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype(np.float64)
        f = shape.faces_buffer().numpy().reshape(-1, 3).astype(np.int64)
        tris.append(v[f])
    return np.concatenate(tris)


def radio_solids(radio) -> Solids:
    """The solids of the radio scene's meshes (:func:`simart_pipeline.scene.solids.mesh_solids`)."""
    return mesh_solids(radio_triangles(radio))


def mesh_solids_of(paired: SceneMeshes) -> Solids:
    """The solids of a scene's radio mesh read from its paired meshes (the PLY files the radio
    scene loads), without loading Sionna: what ``ckm_layers`` masks cell centres with."""
    tris = [m.triangles for m in paired.radio.values() if len(m.faces)]
    return mesh_solids(np.concatenate(tris) if tris else np.zeros((0, 3, 3)))


def anything_above(radio, points: np.ndarray) -> np.ndarray:
    """``[N]`` bool: whether a ray cast straight up from each of ``points [N, 3]`` (m) hits the
    radio mesh."""
    import drjit as dr
    import mitsuba as mi

    pts = [np.ascontiguousarray(points[:, k], np.float32) for k in range(3)]
    up = dr.zeros(mi.Vector3f, len(points)) + mi.Vector3f(0.0, 0.0, 1.0)
    hit = radio.scene.mi_scene.ray_intersect_preliminary(mi.Ray3f(mi.Point3f(*pts), up), False).is_valid()
    return np.asarray(hit.numpy(), bool)


def cell_sample_points(grid, cells: np.ndarray | None = None,
                       samples_per_axis: int = OUTDOOR_SAMPLES_PER_AXIS) -> np.ndarray:
    """``[len(cells) * samples_per_axis**2, 3]`` points (m): the centres of a
    ``samples_per_axis``-times finer grid in each of the flat ``cells`` of ``grid`` (None: every
    cell), cell by cell, x fastest within a cell."""
    off = (np.arange(samples_per_axis) + 0.5) / samples_per_axis - 0.5
    c = grid.centres() if cells is None else grid.centres()[cells]
    px = c[:, 0, None, None] + off[None, None, :] * grid.dx + 0 * off[None, :, None]
    py = c[:, 1, None, None] + off[None, :, None] * grid.dy + 0 * off[None, None, :]
    pz = np.broadcast_to(c[:, 2, None, None], px.shape)
    return np.column_stack([px.ravel(), py.ravel(), pz.ravel()])


def points_inside(radio, points: np.ndarray, solids: Solids | None = None) -> np.ndarray:
    """``[N]`` bool: which of ``points [N, 3]`` (m) lie inside a solid of the radio mesh (a ray cast
    up first, then the solids' faces on the vertical line for the points with anything above)."""
    inside = anything_above(radio, points)
    if inside.any():
        inside[inside] = inside_solids(radio_solids(radio) if solids is None else solids, points[inside])
    return inside


def outdoor_fraction(radio, x_m, y_m, heights_m, samples_per_axis: int = OUTDOOR_SAMPLES_PER_AXIS,
                     cell_size_m: float | None = None, solids: Solids | None = None) -> np.ndarray:
    """Share of each cell's area outdoors, ``[num_heights, ny, nx]``, from ``samples_per_axis**2``
    points per cell (:func:`cell_sample_points`; 1: the cell centre).

    :param radio: :class:`simart_pipeline.radio.tracer.RadioScene`
    :param x_m, y_m, heights_m, cell_size_m: the grid, as in
        :func:`simart_pipeline.ckm.shoot_bounce.grid_from_centres`
    :param solids: :func:`radio_solids` of ``radio``, if the caller has them already
    """
    g = grid_from_centres(x_m, y_m, heights_m, cell_size_m)
    inside = points_inside(radio, cell_sample_points(g, None, samples_per_axis), solids)
    return (1.0 - inside.reshape(int(np.prod(g.shape)), -1).mean(axis=1)).reshape(g.shape)
