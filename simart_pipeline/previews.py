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


def top_view(geom, cfg, traj=None, title: str = ""):
    """Building footprints, base stations and platform tracks, seen from above."""
    fig, ax = plt.subplots(figsize=(5, 4))
    for f in geom.of_class("building"):
        xs, ys = f.geometry.exterior.xy
        ax.fill(xs, ys, color="0.6", lw=0)
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


def heatmap(values: np.ndarray, x: np.ndarray, y: np.ndarray, geom, label: str, title: str = ""):
    fig, ax = plt.subplots(figsize=(5, 4))
    if values.size:
        half = (x[1] - x[0]) / 2 if len(x) > 1 else 0.5
        im = ax.imshow(values, origin="lower", extent=[x[0] - half, x[-1] + half, y[0] - half, y[-1] + half],
                       cmap="viridis")
        fig.colorbar(im, ax=ax, label=label)
    for f in geom.of_class("building"):
        xs, ys = f.geometry.exterior.xy
        ax.plot(xs, ys, "w-", lw=1)
    ax.set_title(title)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    return figure_markdown(fig)


def image(rgb: np.ndarray, title: str = ""):
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.imshow(rgb)
    ax.set_axis_off()
    ax.set_title(title)
    return figure_markdown(fig)
