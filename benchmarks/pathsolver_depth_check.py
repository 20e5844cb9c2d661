"""PathSolver 2.2 gave one (diffraction, reflection) path different powers at different max_depth.

    python benchmarks/pathsolver_depth_check.py

Sionna's street canyon reduced to one building (``building_4``) on a metal floor, iso V antennas
at 3.5 GHz, transmitter (-30, 5, 20) m, receiver (29, -25, 1.5) m, diffraction on, the project's
deterministic PathSolver call (:meth:`simart_pipeline.radio.tracer.RadioScene.trace`). Prints every
path at ``max_depth`` 2 and 3 with its interaction sequence, power and vertices, with Sionna RT
2.2.0's own ``FieldCalculator._diffraction_compute_s_s_prime`` and with the project's correction
(:mod:`simart_pipeline.sionna_fixes`, which :func:`simart_pipeline.engine.init` installs). With
Sionna's own, the (diffraction, reflection) paths keep their vertices and lose 7-8 dB at depth 3
(its walk adds a segment to the stale vertex of the first empty interaction, which a depth-2 walk
never reaches); with the correction every path has one power at both depths, the one image theory
gives (tests/test_radio.py). docs/ckm-one-pass.md (Diffraction) says what this meant for comparisons.
"""

from __future__ import annotations

import numpy as np

TX_M = (-30.0, 5.0, 20.0)
RX_M = (29.0, -25.0, 1.5)


def paths_at(depth: int) -> list[tuple[tuple[int, ...], float, list]]:
    import sionna.rt as rt

    from simart_pipeline.config.radio import RayTracing
    from simart_pipeline.config.devices import Array
    from simart_pipeline.radio.tracer import RadioScene

    iso = Array(rows=1, cols=1, pattern="iso", polarization="V")
    radio = RadioScene(rt.scene.simple_street_canyon, frequency_hz=3.5e9, bandwidth_hz=20e6, tx_array=iso,
                       rx_array=iso, solver=RayTracing(diffraction=True, edge_diffraction=False, refraction=False,
                                                         max_depth=depth, samples_per_src=10**6))
    radio.scene.edit(remove=[o for o in list(radio.scene.objects) if o not in ("building_4", "floor")])
    radio.scene.objects["floor"].radio_material = rt.ITURadioMaterial("floor_metal", "metal", thickness=0.1)
    p = radio.trace(np.array([TX_M]), np.zeros((1, 3)), np.array([RX_M]), with_vertices=True)
    out = []
    for k in np.flatnonzero(p.valid[0, 0]):
        seq = tuple(int(c) for c in p.interaction[0, 0, :, k] if c)
        power_db = float(10 * np.log10(np.abs(p.a[0, 0, 0, 0, k]) ** 2))
        out.append((seq, power_db, np.round(p.vertices_m[0, 0, :len(seq), k], 2).tolist()))
    return out


def main() -> None:
    from simart_pipeline import engine, sionna_fixes

    engine.init()
    from sionna.rt.path_solvers.field_calculator import FieldCalculator

    for label, walk in (("Sionna RT's own distances", sionna_fixes.SIONNAS["diffraction_distances"]),
                        ("corrected (simart_pipeline.sionna_fixes)", sionna_fixes.diffraction_distances)):
        FieldCalculator._diffraction_compute_s_s_prime = walk
        for depth in (2, 3):
            print(f"{label}, max_depth {depth}  (interactions: 1 specular, 8 diffraction)")
            for seq, power_db, vertices in paths_at(depth):
                print(f"  {str(seq):10s} {power_db:8.1f} dB  {vertices}")
    sionna_fixes.apply()


if __name__ == "__main__":
    main()
