import shutil
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def tiny_scene(tmp_path) -> Path:
    """A writable copy of tests/scenes/tiny (tests may edit its scene.yaml)."""
    dst = tmp_path / "tiny"
    shutil.copytree(TESTS / "scenes" / "tiny", dst)
    return dst
