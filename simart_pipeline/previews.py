"""Small PNG previews (matplotlib, Agg) as Markdown that Dagster's UI shows inline."""

from __future__ import annotations

import base64
import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def figure_markdown(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return f"![preview](data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()})"


_LAYER_COLOURS = {"water": "#9cc3e6", "vegetation": "#b5d99c", "parking": "0.8", "road": "0.75"}


def _polygon_patches(geoms, **kw):
    """One matplotlib PathPatch per polygon, holes included."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    from simart_pipeline.scene.geometry import polygons_of

    patches = []
    for g in geoms:
        for poly in polygons_of(g):
            rings = [np.asarray(poly.exterior.coords)[:, :2]] + [np.asarray(r.coords)[:, :2] for r in poly.interiors]
            verts = np.concatenate(rings)
            codes = np.concatenate([[MplPath.MOVETO] + [MplPath.LINETO] * (len(r) - 2) + [MplPath.CLOSEPOLY]
                                    for r in rings])
            patches.append(PathPatch(MplPath(verts, codes), **kw))
    return patches


def _draw_source(ax, geom, building_colour="0.45", outline_only=False):
    from matplotlib.collections import LineCollection, PatchCollection
    from shapely.geometry import LineString

    if not outline_only:
        for cls, colour in _LAYER_COLOURS.items():
            areas = [f.geometry for f in geom.of_class(cls) if not isinstance(f.geometry, LineString)]
            if areas:
                ax.add_collection(PatchCollection(_polygon_patches(areas), facecolor=colour, edgecolor="none"))
        lines = [np.asarray(f.geometry.coords)[:, :2] for f in geom.of_class("road")
                 if isinstance(f.geometry, LineString)]
        if lines:
            ax.add_collection(LineCollection(lines, colors="0.7", linewidths=1.0))
    vols = [f.geometry for f in geom.volumes()]
    if vols:
        kw = ({"facecolor": "none", "edgecolor": building_colour, "linewidth": 0.8} if outline_only
              else {"facecolor": building_colour, "edgecolor": "none"})
        ax.add_collection(PatchCollection(_polygon_patches(vols), **kw))
    ax.autoscale_view()


def top_view(geom, cfg, traj=None, title: str = ""):
    """Land cover, roads, buildings, base stations and platform tracks, seen from above."""
    fig, ax = plt.subplots(figsize=(5, 4))
    _draw_source(ax, geom)
    for b in cfg.base_stations:
        ax.plot(*b.position_m[:2], "r^", ms=8)
        ax.annotate(b.name, b.position_m[:2])
    if traj is not None:
        for p in traj["platform"].values:
            xy = traj["position_m"].sel(platform=p).values
            ax.plot(xy[:, 0], xy[:, 1], "-", lw=2, label=str(p))
        ax.legend(loc="upper right", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title)
    return figure_markdown(fig)


def heatmaps(panels: list[tuple[str, np.ndarray, str]], x: np.ndarray, y: np.ndarray, geom, title: str = "",
             ncols: int = 3):
    """One figure of several maps over the building outlines: ``panels`` = (name, values [y, x], label).

    The panels share their axes (one extent), so only the outer ones carry tick labels, and the
    spacing is fixed rather than fitted: matplotlib's tight layout measures every tick label of
    every panel (a nine-panel map: 1.1 -> 0.9 s)."""
    nrows = max(1, -(-len(panels) // ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.4 * nrows), squeeze=False,
                             sharex=True, sharey=True)
    fig.subplots_adjust(left=0.06, right=0.97, bottom=0.08 / nrows, top=1 - 0.22 / nrows,
                        wspace=0.35, hspace=0.25)
    half = (x[1] - x[0]) / 2 if len(x) > 1 else 0.5
    extent = [x[0] - half, x[-1] + half, y[0] - half, y[-1] + half] if len(x) and len(y) else None
    for ax, (name, values, label) in zip(axes.ravel(), panels):
        if values.size and extent is not None:
            im = ax.imshow(values, origin="lower", extent=extent, cmap="viridis")
            fig.colorbar(im, ax=ax, label=label, shrink=0.85)
        _draw_source(ax, geom, building_colour="w", outline_only=True)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(panels):]:
        ax.set_axis_off()
    for ax in axes.ravel():
        ax.label_outer()
    fig.suptitle(title)
    return figure_markdown(fig)


def image(rgb: np.ndarray, title: str = "", boxes=()):
    """An RGB frame; ``boxes``: (label, (u_min, v_min, u_max, v_max) px) drawn over it."""
    from matplotlib.patches import Rectangle

    fig, ax = plt.subplots(figsize=(4, 3))
    ax.imshow(rgb)
    for label, (u0, v0, u1, v1) in boxes:
        ax.add_patch(Rectangle((u0 - 0.5, v0 - 0.5), u1 - u0 + 1, v1 - v0 + 1, fill=False, ec="yellow", lw=1))
        ax.text(u0, v0 - 2, label, color="yellow", fontsize=6)
    ax.set_axis_off()
    ax.set_title(title)
    return figure_markdown(fig)


def range_doppler(power_db: np.ndarray, range_m: np.ndarray, velocity_mps: np.ndarray, truth=(),
                  title: str = "", max_range_m: float | None = None, dynamic_range_db: float = 60.0):
    """A range-Doppler map [range, velocity] (dB) with the actors' true (range, radial velocity)."""
    keep = range_m <= (max_range_m if max_range_m is not None else range_m.max())
    # The velocity span that holds the actors (at least +-30 m/s), not the whole unambiguous one.
    span = max([30.0] + [2 * abs(v) + 10 for _, _, v in truth])
    cols = np.abs(velocity_mps) <= span
    shown = power_db[keep][:, cols]
    top = float(np.max(shown)) if shown.size else 0.0
    fig, ax = plt.subplots(figsize=(5, 3.2))
    im = ax.pcolormesh(velocity_mps[cols], range_m[keep], shown, vmin=top - dynamic_range_db, vmax=top,
                       shading="nearest", cmap="viridis")
    fig.colorbar(im, ax=ax, label="power (dB)")
    for label, r, v in truth:
        ax.plot(v, r, "r+", ms=8)
        ax.text(v, r, f" {label}", color="red", fontsize=7)
    ax.set_xlabel("radial velocity (m/s, + receding)")
    ax.set_ylabel("range (m)")
    ax.set_title(title)
    return figure_markdown(fig)
