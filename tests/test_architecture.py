"""The shape of the house, read from the code's own imports: no import circle anywhere, a ground floor
that imports nothing of the project, and science modules that never import Dagster."""

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from simart_pipeline import versions

PACKAGE = Path(__file__).resolve().parents[1] / "simart_pipeline"
GROUND_FLOOR = ("simart_pipeline.vocabulary", "simart_pipeline.clock")
DAGSTER_LAYERS = ("simart_pipeline.assets", "simart_pipeline.resources", "simart_pipeline.partitions",
                  "simart_pipeline.definitions", "simart_pipeline.cli", "simart_pipeline.cluster")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


# The reader that code versions use (versions.import_closure), module level and inside functions.
GRAPH = {m: set(versions._project_imports(m)) for m in MODULES}


def test_the_import_graph_was_read():
    assert len(MODULES) > 60
    assert "simart_pipeline.config.scene" in GRAPH["simart_pipeline.config"]
    assert "simart_pipeline.vocabulary" in GRAPH["simart_pipeline.scene.meshes"]


def test_no_import_circle_anywhere():
    names = sorted(GRAPH)
    index = {m: i for i, m in enumerate(names)}
    edges = [(index[a], index[b]) for a, targets in GRAPH.items() for b in targets if a != b]
    rows, cols = np.array(edges).T
    graph = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(len(names), len(names)))
    n, label = connected_components(graph, directed=True, connection="strong")
    circles = [sorted(names[i] for i in np.flatnonzero(label == k)) for k in range(n)
               if (label == k).sum() > 1]
    assert circles == [], f"import circles: {circles}"


@pytest.mark.parametrize("module", GROUND_FLOOR)
def test_the_ground_floor_imports_nothing_of_the_project(module):
    assert GRAPH[module] == set()


def test_science_modules_never_import_dagster():
    offenders = []
    for m, p in MODULES.items():
        if m.startswith(DAGSTER_LAYERS):
            continue
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(x == "dagster" or x.startswith("dagster.") for x in mods):
                offenders.append(m)
    assert offenders == []


def test_every_module_imports_alone_in_a_fresh_interpreter():
    """Import order never matters: each module imports first thing in a new interpreter."""
    code = ("import importlib, sys\nbad = []\nfor m in sys.argv[1:]:\n"
            "    for k in [k for k in sys.modules if k.startswith('simart_pipeline')]:\n"
            "        del sys.modules[k]\n"
            "    try:\n        importlib.import_module(m)\n"
            "    except Exception as exc:\n        bad.append(f'{m}: {exc!r}')\n"
            "print('\\n'.join(bad)); sys.exit(1 if bad else 0)")
    # One interpreter, each module imported with the project's modules cleared first (third-party
    # libraries stay loaded: a fresh process per module would take minutes for the same check).
    res = subprocess.run([sys.executable, "-c", code, *sorted(MODULES)], capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
