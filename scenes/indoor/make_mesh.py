"""Generate ``office.glb``: one office floor, the user-defined mesh of the ``indoor`` scene.

A 30 m x 12 m floor (ENU: x east, y north, z up; m): a corridor along x (y in [-1.2, 1.2]) with
five rooms on each side, 3 m clear height. Every wall segment, slab, window pane and piece of
furniture is its own glTF node, named so that the scene's rules can find it:

- ``outer_wall_*`` (concrete), ``inner_wall_*`` (plasterboard), ``window_glass_*`` (glass),
  ``ceiling`` (ceiling board), ``floor`` (the floor slab);
- ``window_frame_*``: thin frames, removed from the radio mesh by a name rule;
- ``office/furniture/<room>_furniture/<item>``: desks, chairs, cabinets and lamps, small enough (< 2 m) that the
  size threshold removes them; they carry the glTF extras tag ``furniture`` (plants also ``plant``).

The file follows the glTF convention (+y up), so the importer's ``up_axis: auto`` turns it back into
ENU. Run ``python scenes/indoor/make_mesh.py`` to rewrite it; the output is deterministic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
X0, X1, Y_OUT, Y_COR, H, T = -15.0, 15.0, 6.0, 1.2, 3.0, 0.2  # extents, corridor half-width, height, wall
ROOM_X = np.linspace(X0, X1, 6)  # room boundaries along x
ENU_TO_GLTF = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # (x, y, z) -> (x, z, -y)


def box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(hi - lo, trimesh.transformations.translation_matrix((lo + hi) / 2))


def leg(x, y, height, radius=0.025) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius, height, sections=16)
    m.apply_translation((x, y, height / 2))
    return m


class Builder:
    """Every node under one root node ``office`` whose matrix turns ENU into glTF's +y up."""

    def __init__(self):
        self.scene = trimesh.Scene()
        self.scene.graph.update(frame_to="office", frame_from=self.scene.graph.base_frame, matrix=ENU_TO_GLTF)

    def add(self, name: str, mesh: trimesh.Trimesh, parent: str = "office", tags=None):
        self.scene.add_geometry(mesh, node_name=name, geom_name=name, parent_node_name=parent,
                                metadata={"tags": list(tags)} if tags else None)

    def group(self, name: str, parent: str = "office"):
        self.scene.graph.update(frame_to=name, frame_from=parent)


def outer_wall_with_windows(b: Builder, side: int) -> None:
    """South (side -1) or north (+1) facade: piers, sills and lintels around one window per room."""
    y_lo, y_hi = (-Y_OUT - T, -Y_OUT) if side < 0 else (Y_OUT, Y_OUT + T)
    tag = "s" if side < 0 else "n"
    b.add(f"outer_wall_{tag}_pier_0", box((X0 - T, y_lo, 0), (ROOM_X[0] + 1.8, y_hi, H)))
    for i, (xa, xb) in enumerate(zip(ROOM_X[:-1], ROOM_X[1:])):
        xc = (xa + xb) / 2
        w0, w1, z0, z1 = xc - 1.2, xc + 1.2, 0.9, 2.3
        b.add(f"outer_wall_{tag}_sill_{i}", box((w0, y_lo, 0), (w1, y_hi, z0)))
        b.add(f"outer_wall_{tag}_lintel_{i}", box((w0, y_lo, z1), (w1, y_hi, H)))
        right = xb + 1.8 if i < 4 else X1 + T
        b.add(f"outer_wall_{tag}_pier_{i + 1}", box((w1, y_lo, 0), (right, y_hi, H)))
        ym = (y_lo + y_hi) / 2
        b.add(f"window_glass_{tag}_{i}", box((w0, ym - 0.01, z0), (w1, ym + 0.01, z1)))
        f, yf = 0.05, (y_lo - 0.04, y_lo) if side < 0 else (y_hi, y_hi + 0.04)
        frame = [box((w0, yf[0], z0), (w1, yf[1], z0 + f)), box((w0, yf[0], z1 - f), (w1, yf[1], z1)),
                 box((w0, yf[0], z0 + f), (w0 + f, yf[1], z1 - f)), box((w1 - f, yf[0], z0 + f), (w1, yf[1], z1 - f))]
        for k, bar in enumerate(frame):
            b.add(f"window_frame_{tag}_{i}_{k}", bar)


def corridor_wall(b: Builder, side: int) -> None:
    """The wall between the corridor and one row of rooms, a door (1 m x 2.1 m) into each room."""
    y_lo, y_hi = (-Y_COR - T, -Y_COR) if side < 0 else (Y_COR, Y_COR + T)
    tag = "s" if side < 0 else "n"
    x = X0
    for i, (xa, xb) in enumerate(zip(ROOM_X[:-1], ROOM_X[1:])):
        d0, d1 = xa + 4.0, xa + 5.0
        b.add(f"inner_wall_corridor_{tag}_{i}", box((x, y_lo, 0), (d0, y_hi, H)))
        b.add(f"inner_wall_corridor_{tag}_{i}_over_door", box((d0, y_lo, 2.1), (d1, y_hi, H)))
        x = d1
    b.add(f"inner_wall_corridor_{tag}_end", box((x, y_lo, 0), (X1, y_hi, H)))


def furniture(b: Builder, room: str, xc: float, yc: float, side: int) -> None:
    grp = f"{room}_furniture"
    b.group(grp, "furniture")
    tags = ("furniture",)
    dy = -side  # desks face the window
    b.add(f"{room}_desk_top", box((xc - 0.8, yc - 0.4, 0.72), (xc + 0.8, yc + 0.4, 0.76)), grp, tags)
    for k, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
        b.add(f"{room}_desk_leg_{k}", leg(xc + sx * 0.75, yc + sy * 0.35, 0.72), grp, tags)
    for c, cx in enumerate((xc - 0.4, xc + 0.4)):
        cy = yc + dy * 0.7
        b.add(f"{room}_chair_{c}_seat", box((cx - 0.22, cy - 0.22, 0.43), (cx + 0.22, cy + 0.22, 0.47)), grp, tags)
        by = cy + dy * 0.2
        b.add(f"{room}_chair_{c}_back", box((cx - 0.22, by - 0.02, 0.47), (cx + 0.22, by + 0.02, 0.9)), grp, tags)
        for k, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
            b.add(f"{room}_chair_{c}_leg_{k}", leg(cx + sx * 0.19, cy + sy * 0.19, 0.43, 0.015), grp, tags)
    b.add(f"{room}_cabinet", box((xc + 1.6, yc - 0.2 * side - 0.2, 0), (xc + 2.4, yc - 0.2 * side + 0.2, 1.8)),
          grp, tags)
    b.add(f"{room}_monitor", box((xc - 0.3, yc - 0.25 * dy - 0.02, 0.8), (xc + 0.3, yc - 0.25 * dy + 0.02, 1.15)),
          grp, tags)
    b.add(f"{room}_keyboard", box((xc - 0.22, yc + 0.1 * dy - 0.07, 0.76), (xc + 0.22, yc + 0.1 * dy + 0.07, 0.78)),
          grp, tags)
    lamp = trimesh.creation.cylinder(0.25, 0.05, sections=32)
    lamp.apply_translation((xc, yc, H - 0.1))
    b.add(f"{room}_lamp", lamp, grp, tags)
    px, py = xc - 1.9, yc - 0.8 * side
    pot = trimesh.creation.cylinder(0.15, 0.3, sections=24)
    pot.apply_translation((px, py, 0.15))
    b.add(f"{room}_plant_pot", pot, grp, tags)
    foliage = trimesh.creation.icosphere(subdivisions=2, radius=0.35)
    foliage.apply_translation((px, py, 0.65))
    b.add(f"{room}_plant", foliage, grp, tags + ("plant",))


def build() -> trimesh.Scene:
    b = Builder()
    b.add("floor", box((X0 - T, -Y_OUT - T, -0.2), (X1 + T, Y_OUT + T, 0.0)))
    b.add("ceiling", box((X0 - T, -Y_OUT - T, H), (X1 + T, Y_OUT + T, H + 0.2)))
    b.add("outer_wall_w", box((X0 - T, -Y_OUT, 0), (X0, Y_OUT, H)))
    b.add("outer_wall_e", box((X1, -Y_OUT, 0), (X1 + T, Y_OUT, H)))
    for side in (-1, 1):
        outer_wall_with_windows(b, side)
        corridor_wall(b, side)
        y_lo, y_hi = (-Y_OUT, -Y_COR - T) if side < 0 else (Y_COR + T, Y_OUT)
        for k, xb in enumerate(ROOM_X[1:-1]):
            b.add(f"inner_wall_partition_{'s' if side < 0 else 'n'}_{k}", box((xb - T / 2, y_lo, 0), (xb + T / 2, y_hi, H)))
    b.group("furniture")
    for side in (-1, 1):
        for i, (xa, xb) in enumerate(zip(ROOM_X[:-1], ROOM_X[1:])):
            yc = side * (Y_COR + T + Y_OUT) / 2
            furniture(b, f"room_{'s' if side < 0 else 'n'}{i}", (xa + xb) / 2 - 0.6, yc, side)
    return b.scene


if __name__ == "__main__":
    out = HERE / "office.glb"
    build().export(out)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")
