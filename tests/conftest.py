import shutil
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
SHARED_DATA = REPO.parent / "shared" / "data"
# LoS and specular reflection alone (diffraction and refraction are on by default): the settings of a
# test whose closed form counts those paths (two-ray ground, a plate's echo); a finite ground or
# plate also diffracts at its edges
LOS_SPECULAR = {"diffraction": False, "edge_diffraction": False, "refraction": False}


@pytest.fixture(scope="session")
def tiny_built(tmp_path_factory):
    """tests/scenes/tiny built once: (config, source geometry, paired meshes, their directory)."""
    from simart_pipeline import stores
    from simart_pipeline.config import load_scene_config
    from simart_pipeline.scene import meshes, source

    cfg = load_scene_config(TESTS / "scenes" / "tiny")
    geom = source.build_source_geometry(cfg, TESTS / "scenes" / "tiny")
    m = meshes.build_meshes(geom)
    out = tmp_path_factory.mktemp("pm") / "tiny"
    stores.write_directory(out, lambda d: meshes.save(m, d, {"name": "tiny"}, cfg.materials.thickness_m))
    return cfg, geom, m, out


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """tests/scenes/tiny materialised once through ``simart run``'s code path (every asset, its asset
    checks, three weathers, two tiles): (data root, stores, instance, progress lines, config). Shared
    by test_end_to_end.py and test_checks.py; tests that change the data work on a copy."""
    import dagster as dg

    from simart_pipeline.cli import materialize_scene
    from simart_pipeline.config import load_scene_config

    data = tmp_path_factory.mktemp("data")
    instance = dg.DagsterInstance.ephemeral()
    lines = []
    out = materialize_scene(TESTS / "scenes" / "tiny", data, ["sunny", "night", "rainy"], ["r0c0", "r0c1"],
                            instance=instance, progress=lines.append)
    return data, out, instance, lines, load_scene_config(TESTS / "scenes" / "tiny")


@pytest.fixture
def tiny_scene(tmp_path) -> Path:
    """A writable copy of tests/scenes/tiny (tests may edit its scene.yaml)."""
    dst = tmp_path / "tiny"
    shutil.copytree(TESTS / "scenes" / "tiny", dst)
    return dst


def write_radio_scene(out: Path, parts: dict, frequency_hz: float, thickness_m: float) -> Path:
    """A Sionna scene XML with one PLY per named part: ``parts = {name: (trimesh, material)}``."""
    from simart_pipeline.radio import materials

    (out / "meshes").mkdir(parents=True)
    lines = ['<scene version="2.1.0">']
    for mat in sorted({m for _, m in parts.values()}):
        lines.append(materials.bsdf_xml(mat, frequency_hz, thickness_m))
    for name, (mesh, mat) in sorted(parts.items()):
        mesh.export(out / "meshes" / f"{name}.ply", encoding="binary")
        lines.append(f'<shape type="ply" id="{name}"><string name="filename" value="meshes/{name}.ply"/>'
                     f'<boolean name="face_normals" value="true"/>'
                     f'<ref id="{materials.bsdf_id(mat)}" name="bsdf"/></shape>')
    lines.append("</scene>")
    (out / "scene.xml").write_text("\n".join(lines))
    return out / "scene.xml"


def ground_square(size_m: float = 2000.0):
    """A flat square at z = 0 facing up, centred on the origin."""
    import trimesh

    h = size_m / 2
    return trimesh.Trimesh([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], [[0, 1, 2], [0, 2, 3]],
                           process=False)


def scene_config(scene_dir, edit=None):
    """The SceneConfig of ``scene_dir/scene.yaml``, after ``edit(raw_dict)`` if given."""
    import yaml

    from simart_pipeline.config import SceneConfig

    raw = yaml.safe_load((Path(scene_dir) / "scene.yaml").read_text())
    if edit:
        edit(raw)
    return SceneConfig.model_validate(raw)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (for a dev server started by a test)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def processes_with_env(home: Path) -> list[int]:
    """Pids of live processes whose environment holds ``DAGSTER_HOME=home``: everything a test's
    ``simart dev`` started (dagster dev, its webserver, daemon, code server and run workers)."""
    needle = f"DAGSTER_HOME={home}".encode()
    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if needle in (p / "environ").read_bytes().split(b"\0"):
                    out.append(int(p.name))
            except OSError:
                pass
    return out
