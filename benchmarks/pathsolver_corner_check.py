"""PathSolver 2.2's candidate generator lost a lit corner's diffraction on an OSM building (corrected).

    python -m benchmarks.pathsolver_corner_check

The project's urban scene (benchmarks.ckm_solver's ``urban``: its OSM extract, bs0) reduced to
one building, ``building_brick`` (x -28..-8 m, y -10..30 m, 18 m tall, a courtyard), whose
footprint vertices lie millimetres off whole metres. PathSolver (depth 1, diffraction on, 1e6
samples, deterministic) with Sionna RT 2.2.0's own candidate generator diffracts on the
building's north-west and south-west vertical corners and its roof edges, but never on its
south-east corner at (-8, -10): the generator tests the target's visibility from the sampled
diffraction point, which lies on the edge, with an offset along the hit face's normal that puts
it on the other face's plane, and the outcome depends on the vertices' last bits. With the
vertices rounded to whole metres, or with the project's correction
(:mod:`simart_pipeline.sionna_fixes`: the sample moved 1 mm off the edge along the wedge's
exterior bisector), the corner diffracts: -111.6 dB at (79, 21) m, the one-pass solver's -111.4 dB.
That corner's field had set the urban scene's gain p95 against PathSolver (docs/ckm-one-pass.md,
"Session 16"). This script prints the three: Sionna's own generator, the correction, and the
vertices rounded.
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
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    from simart_pipeline import sionna_fixes

    print(f"transmitter {tx.tolist()} m; paths per receiver (D: diffraction point)")
    corrected = SBCandidateGenerator._sample_radio_material
    SBCandidateGenerator._sample_radio_material = sionna_fixes.SIONNAS["sample_radio_material"]
    try:
        print("building_brick as built, Sionna RT's own candidate generator:")
        _show(cs, radio, tx, ori)
    finally:
        SBCandidateGenerator._sample_radio_material = corrected
    print("building_brick as built, corrected (simart_pipeline.sionna_fixes):")
    _show(cs, radio, tx, ori)
    mesh = radio.scene.objects["building_brick"].mi_mesh
    vertices = np.asarray(mesh.vertex_positions_buffer().numpy(), np.float64).reshape(-1, 3)
    faces = np.asarray(mesh.faces_buffer().numpy()).reshape(-1, 3)
    print("its vertices rounded to whole metres (corrected):")
    _show(cs, _scene_of(np.round(vertices), faces, cfg), tx, ori)


def _scene_of(vertices, faces, cfg):
    """A radio scene of one brick mesh, written as the project writes its radio scenes
    (:func:`simart_pipeline.scene.meshes.radio_scene_xml`), 1e6 samples, depth 1."""
    import trimesh

    from simart_pipeline.radio.tracer import RadioScene
    from simart_pipeline.scene.meshes import radio_scene_xml

    folder = Path(tempfile.mkdtemp())
    (folder / "meshes").mkdir()
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.export(folder / "meshes" / "building_brick.ply", encoding="binary")
    (folder / "scene.xml").write_text(radio_scene_xml({("building", "brick"): mesh}, 0.2,
                                                      frequency_hz=cfg.ofdm.carrier_frequency_hz))
    radio = RadioScene.from_config(folder / "scene.xml", cfg)
    radio.solver_config = radio.solver_config.model_copy(update={"samples_per_src": 10**6, "max_depth": 1})
    return radio


def _show(cs, radio, tx, ori) -> None:
    p = radio.trace(tx[None], ori[None], np.array(RECEIVERS_M), with_vertices=True)
    power = (np.abs(p.a[:, 0]) ** 2).mean(axis=(1, 2))
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
