"""The session bag's picture: one camera frame beside the power-delay profiles and best beams of
the links at the same instant."""

from __future__ import annotations

import numpy as np
import xarray as xr

from simart_pipeline import previews


def bag_picture(session: xr.DataTree, title: str = "") -> str:
    """Markdown image: the camera frame that sees the most actors (else the first camera's middle
    frame), and for every link of that camera's device at the same instant (the radio instant at or
    before it) the power-delay profile (path gain per path, dB, against delay, ns) and the best beam."""
    import matplotlib.pyplot as plt

    cams = [n for n in session["sensors"].subtree if n.has_data and "rgb" in n.data_vars] \
        if "sensors" in session.children else []
    cirs, kpis = session["cirs"].to_dataset(), session["kpis"].to_dataset()
    fig, (ax_img, ax_pdp) = plt.subplots(1, 2, figsize=(9, 3.2), gridspec_kw={"width_ratios": [1.1, 1]})
    if cams:
        node, i = max(((n, k) for n in cams for k in range(n.sizes["time"])),
                      key=lambda c: (int((c[0]["actor_pixel_count"].values[c[1]] > 0).sum()) if "actor_pixel_count"
                                     in c[0].data_vars else 0, -abs(c[1] - c[0].sizes["time"] // 2)))
        t = int(node["time"].values[i])
        device = node.path.split("/sensors/", 1)[1].split("/")[0]
        ax_img.imshow(node["rgb"].values[i])
        ax_img.set_title(f"{node.path.split('/sensors/', 1)[1]}  t = {t / 1e9:g} s", fontsize=8)
    else:
        t, device = int(cirs["time"].values[cirs.sizes["time"] // 2]), None
        ax_img.text(0.5, 0.5, "no camera", ha="center")
    ax_img.set_axis_off()
    k = int(np.searchsorted(cirs["time"].values, t, side="right") - 1)
    links = [j for j in range(cirs.sizes["link"])
             if device is None or device in (str(cirs["tx"].values[j]), str(cirs["rx"].values[j]))]
    profiles = []
    for j in links:
        f = cirs.isel(time=k, link=j)
        valid = f["valid"].values
        gain = (np.abs(f["a"].values) ** 2).mean(axis=(0, 1))[valid]
        label = f"{cirs['tx'].values[j]}->{cirs['rx'].values[j]}, best beam {int(kpis['best_beam'].values[k, j])}"
        if gain.size:
            profiles.append((j, f["tau_s"].values[valid] * 1e9, 10 * np.log10(gain), label))
    floor = min((g.min() for _, _, g, _ in profiles), default=-100.0) - 10
    for j, tau_ns, gain_db, label in profiles:
        ax_pdp.vlines(tau_ns, floor, gain_db, color=f"C{j % 10}")
        ax_pdp.plot(tau_ns, gain_db, "o", color=f"C{j % 10}", label=label)
    ax_pdp.set_xlabel("delay (ns)")
    ax_pdp.set_ylabel("path gain (dB)")
    ax_pdp.set_title(f"power-delay profile at t = {int(cirs['time'].values[k]) / 1e9:g} s", fontsize=8)
    if ax_pdp.get_legend_handles_labels()[0]:
        ax_pdp.legend(fontsize=6)
    fig.suptitle(title, fontsize=9)
    return previews.figure_markdown(fig)
