"""An open lead (session 16): PathSolver 2.2 does not diffract on one vertical corner of the urban scene.

    python -m benchmarks.pathsolver_corner_check

The project's urban scene (benchmarks.ckm_solver's ``urban``: its OSM extract, bs0) reduced to
one building, ``building_brick`` (x -28..-8 m, y -10..30 m, 18 m tall). PathSolver (depth 1,
diffraction on, 1e6 samples, deterministic) diffracts on its north-west and south-west vertical
corners, but never on its south-east one at (-8, -10): at (0, 20) and (2, 7.3) m, in that
corner's shadow, it returns only the roof edge's diffraction. The one-pass solver diffracts there,
and that corner's field (-111 dB at (79, 21) m, lit-region diffraction where other buildings block
the line of sight) is what sets the urban scene's gain p95 against PathSolver
(docs/ckm-one-pass.md, "Session 16"). The geometry is clear (the transmitter sees the diffraction
point, the point sees the receivers); the cause is not found.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

RECEIVERS_M = ((0.0, 20.0, 1.5), (2.0, 7.3, 1.5), (-20.0, 45.0, 1.5), (79.0, 21.0, 1.5))


def main() -> None:
    from benchmarks import ckm_solver as cs

    spec = cs.SCENES["urban"]
    cfg = cs._config(spec, "diffraction")
    radio = cs._radio_scene(cs._radio_xml(spec, Path(tempfile.mkdtemp())), cfg, "diffraction")
    radio.scene.edit(remove=[o for o in list(radio.scene.objects) if o != "building_brick"])
    radio.solver_config = radio.solver_config.model_copy(update={"samples_per_src": 10**6, "max_depth": 1})
    tx = np.array(spec["tx"])
    ori = np.radians([spec["yaw_pitch_deg"][0], spec["yaw_pitch_deg"][1], 0.0])
    p = radio.trace(tx[None], ori[None], np.array(RECEIVERS_M), with_vertices=True)
    power = (np.abs(p.a[:, 0]) ** 2).mean(axis=(1, 2))
    print(f"transmitter {tx.tolist()} m; paths per receiver (D: diffraction point)")
    for j, rx in enumerate(RECEIVERS_M):
        out = []
        for k in np.argsort(-power[j]):
            if p.valid[j, 0, k]:
                kinds = [int(c) for c in p.interaction[j, 0, :, k] if c]
                where = np.round(p.vertices_m[j, 0, 0, k], 1).tolist() if kinds else ""
                out.append(f"{cs.sequence_name(sum(c << (4 * i) for i, c in enumerate(kinds)))} "
                           f"{10 * np.log10(power[j, k]):.1f} dB {where}")
        print(f"  {rx}: " + ("; ".join(out) or "no path"))


if __name__ == "__main__":
    main()
