"""Generate ``harbour.glb``: a harbour basin, the user-defined mesh of the ``maritime`` scene.

ENU (x east, y north, z up; m), the water surface at z = 0:

- ``sea``: open water north of the quay (y in [0, 400]), tessellated in 10 m tiles, which the
  lossless decimation merges into a few large triangles;
- ``quay``: a concrete block (top 2.5 m above the water) along y < 0, with a ``warehouse`` and its
  ``warehouse_roof`` on it; ``quay_bollard_*``, ``quay_fender_*`` (small: removed by the size
  threshold) and ``quay_lamp_post_*`` (thin and tall: removed by a name rule);
- ``ship_*``: a container ship in the basin (hull with a pointed bow, deckhouse, funnel, container
  stacks), with railings and antenna masts that the size threshold removes.

The file follows the glTF convention (+y up); the importer's ``up_axis: auto`` turns it into ENU.
Run ``python scenes/maritime/make_mesh.py`` to rewrite it; the output is deterministic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import shapely
import trimesh

HERE = Path(__file__).resolve().parent
ENU_TO_GLTF = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # (x, y, z) -> (x, z, -y)
X0, X1, Y_SEA, QUAY_TOP = -250.0, 250.0, 400.0, 2.5
SHIP_X, SHIP_Y, SHIP_BEAM, DECK = (-40.0, 40.0), 100.0, 14.0, 6.0  # stern/bow x, port side y, beam, deck z


def box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(hi - lo, trimesh.transformations.translation_matrix((lo + hi) / 2))


def cylinder(x, y, z0, height, radius, sections=16) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius, height, sections=sections)
    m.apply_translation((x, y, z0 + height / 2))
    return m


def sea(tile_m: float = 10.0) -> trimesh.Trimesh:
    xs = np.arange(X0, X1 + tile_m / 2, tile_m)
    ys = np.arange(0.0, Y_SEA + tile_m / 2, tile_m)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return trimesh.Trimesh(v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])]))


class Builder:
    """Every node under one root node ``harbour`` whose matrix turns ENU into glTF's +y up."""

    def __init__(self):
        self.scene = trimesh.Scene()
        self.scene.graph.update(frame_to="harbour", frame_from=self.scene.graph.base_frame, matrix=ENU_TO_GLTF)

    def add(self, name: str, mesh: trimesh.Trimesh, tags=None):
        self.scene.add_geometry(mesh, node_name=name, geom_name=name, parent_node_name="harbour",
                                metadata={"tags": list(tags)} if tags else None)


def quay(b: Builder) -> None:
    b.add("quay", box((X0, -80.0, -3.0), (X1, 0.0, QUAY_TOP)))
    b.add("warehouse", box((-120.0, -70.0, QUAY_TOP), (-60.0, -30.0, 14.0)))
    b.add("warehouse_roof", box((-121.0, -71.0, 14.0), (-59.0, -29.0, 14.3)))
    for i, x in enumerate(np.arange(X0 + 10.0, X1, 15.0)):
        b.add(f"quay_bollard_{i}", cylinder(x, -1.0, QUAY_TOP, 0.6, 0.25, sections=20), ("quay_furniture",))
        b.add(f"quay_fender_{i}", box((x + 5.0, 0.0, -0.5), (x + 6.0, 0.4, 1.5)), ("quay_furniture",))
    for i, x in enumerate(np.arange(X0 + 20.0, X1, 40.0)):
        b.add(f"quay_lamp_post_{i}", cylinder(x, -6.0, QUAY_TOP, 8.0, 0.1), ("quay_furniture",))
        b.add(f"quay_lamp_post_{i}_head", box((x - 0.3, -6.8, QUAY_TOP + 7.8), (x + 0.3, -6.0, QUAY_TOP + 8.1)),
              ("quay_furniture",))


def ship(b: Builder) -> None:
    (xs, xb), y0, w = SHIP_X, SHIP_Y, SHIP_BEAM
    outline = shapely.Polygon([(xs, y0), (xb - 12.0, y0), (xb, y0 + w / 2), (xb - 12.0, y0 + w), (xs, y0 + w)])
    hull = trimesh.creation.extrude_polygon(outline, DECK + 4.0)
    hull.apply_translation((0.0, 0.0, -4.0))  # 4 m draft below the water surface
    b.add("ship_hull", hull)
    b.add("ship_deckhouse", box((xs + 2.0, y0 + 1.0, DECK), (xs + 14.0, y0 + w - 1.0, DECK + 10.0)))
    b.add("ship_funnel", cylinder(xs + 5.0, y0 + w / 2, DECK + 10.0, 5.0, 1.5, sections=24))
    k = 0
    for bay in range(4):  # container stacks: 20 ft boxes, 4 across, 2 high
        x = xs + 18.0 + bay * 7.0
        for row in range(4):
            y = y0 + 2.2 + row * 2.45
            for tier in range(2):
                z = DECK + tier * 2.6
                b.add(f"ship_container_{k}", box((x, y, z), (x + 6.06, y + 2.44, z + 2.59)))
                k += 1
    for side, y in (("port", y0 + 0.1), ("starboard", y0 + w - 0.1)):
        for i, x in enumerate(np.arange(xs + 15.0, xb - 14.0, 2.0)):
            b.add(f"ship_railing_{side}_post_{i}", cylinder(x, y, DECK, 1.1, 0.03, sections=8))
            b.add(f"ship_railing_{side}_rail_{i}", box((x, y - 0.02, DECK + 1.05), (x + 1.9, y + 0.02, DECK + 1.1)))
    for i, dy in enumerate((3.0, 7.0, 11.0)):
        b.add(f"ship_antenna_mast_{i}", cylinder(xs + 8.0, y0 + dy, DECK + 10.0, 1.8, 0.05, sections=8))


def build() -> trimesh.Scene:
    b = Builder()
    b.add("sea", sea())
    quay(b)
    ship(b)
    return b.scene


if __name__ == "__main__":
    out = HERE / "harbour.glb"
    build().export(out)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")
