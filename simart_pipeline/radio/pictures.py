"""Pictures of traced paths: what the ray tracer found at one instant, for the asset's metadata."""

from __future__ import annotations

import numpy as np

from simart_pipeline import previews
from simart_pipeline.config import SceneConfig
from simart_pipeline.radio.cirs import LinkGeometry
from simart_pipeline.radio.tracer import RadioScene
from simart_pipeline.scene.geometry import SourceGeometry
from simart_pipeline.vocabulary import InteractionKind

# Colour of a path by its last interaction (NONE: the line of sight).
_KIND_COLOUR = {InteractionKind.NONE: "tab:green", InteractionKind.SPECULAR: "tab:blue",
                InteractionKind.DIFFUSE: "tab:orange", InteractionKind.REFRACTION: "tab:purple",
                InteractionKind.DIFFRACTION: "tab:red"}


def traced_paths_markdown(radio: RadioScene, cfg: SceneConfig, lg: LinkGeometry,
                          geom: SourceGeometry | None, step: int, title: str = "") -> str:
    """Top view of every path at radio-clock instant ``step`` (colour: last interaction type,
    width: path gain) and each link's power-delay profile, as inline Markdown."""
    import matplotlib.pyplot as plt

    p = radio.trace(lg.tx_position_m, lg.tx_orientation_rad, lg.rx_position_m[step],
                    lg.rx_velocity_mps[step], lg.rx_orientation_rad[step], with_vertices=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4.2), gridspec_kw={"width_ratios": [1.3, 1]})
    if geom is not None:
        for f in geom.of_class("building"):
            for g in getattr(f.geometry, "geoms", [f.geometry]):
                xs, ys = g.exterior.xy
                ax.fill(xs, ys, color="0.75", lw=0)
    gain_db = 10 * np.log10(np.maximum((np.abs(p.a) ** 2).mean(axis=(1, 3)), 1e-30))  # [rx, tx, path]
    finite = gain_db[p.valid]
    g_max = finite.max() if finite.size else 0.0
    for r in range(p.valid.shape[0]):
        for t in range(p.valid.shape[1]):
            for k in np.flatnonzero(p.valid[r, t]):
                depth = int(np.count_nonzero(p.interaction[r, t, :, k]))
                pts = np.vstack([lg.tx_position_m[t], p.vertices_m[r, t, :depth, k], lg.rx_position_m[step, r]])
                kind = int(p.interaction[r, t, depth - 1, k]) if depth else InteractionKind.NONE
                width = 0.4 + 2.0 * max(0.0, 1 + (gain_db[r, t, k] - g_max) / 40)
                ax.plot(pts[:, 0], pts[:, 1], "-", color=_KIND_COLOUR.get(kind, "k"), lw=width, alpha=0.8)
            delays_ns = p.tau_s[r, t][p.valid[r, t]] * 1e9
            if not delays_ns.size:
                continue
            ax2.stem(delays_ns, gain_db[r, t][p.valid[r, t]], bottom=-200,
                     label=f"{cfg.base_stations[t].name} -> {cfg.platforms[r].name}",
                     linefmt=f"C{(r * p.valid.shape[1] + t) % 10}-",
                     markerfmt=f"C{(r * p.valid.shape[1] + t) % 10}o", basefmt=" ")
    for b in cfg.base_stations:
        ax.plot(*b.position_m[:2], "r^", ms=9)
        ax.annotate(b.name, b.position_m[:2])
    for j, pl in enumerate(cfg.platforms):
        ax.plot(*lg.rx_position_m[step, j, :2], "ko", ms=6)
        ax.annotate(pl.name, lg.rx_position_m[step, j, :2])
    for kind, colour in _KIND_COLOUR.items():
        ax.plot([], [], color=colour, label="line of sight" if kind == InteractionKind.NONE else kind.name.lower())
    ax.legend(loc="upper right", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"{title} paths at t = {lg.time_ns[step] / 1e9:.2f} s")
    if finite.size:
        ax2.set_ylim(finite.min() - 5, g_max + 5)
    ax2.set_xlabel("delay (ns)")
    ax2.set_ylabel("path gain (dB)")
    ax2.set_title("power-delay profile")
    if ax2.get_legend_handles_labels()[0]:
        ax2.legend(fontsize=7)
    return previews.figure_markdown(fig)
