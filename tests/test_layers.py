"""Imports point downward only (ARCHITECTURE.md): checked on the source with ast, so a new import that breaks
the layering fails here before it becomes a cycle."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "selfcal"

# layer -> modules it must never import (selfcal sub-packages, or external packages)
FORBIDDEN = {
    "models": {"gtsam", "selfcal.io", "selfcal.sim", "selfcal.factors", "selfcal.graphs", "selfcal.audit",
               "selfcal.pipelines", "selfcal.cli", "selfcal.baselines"},
    "io": {"gtsam", "selfcal.factors", "selfcal.graphs", "selfcal.audit", "selfcal.pipelines", "selfcal.cli"},
    "sim": {"gtsam", "selfcal.factors", "selfcal.graphs", "selfcal.audit", "selfcal.pipelines", "selfcal.cli"},
    "baselines": {"gtsam", "selfcal.factors", "selfcal.graphs", "selfcal.audit", "selfcal.pipelines", "selfcal.cli"},
    "factors": {"selfcal.graphs", "selfcal.audit", "selfcal.pipelines", "selfcal.cli", "selfcal.io"},
    "graphs": {"selfcal.audit", "selfcal.pipelines", "selfcal.cli"},
    "audit": {"selfcal.pipelines", "selfcal.cli"},
    "pipelines": {"selfcal.cli"},
}


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_imports_point_downward(layer):
    offenders = []
    for path in sorted((PACKAGE / layer).glob("*.py")):
        for name in imported_modules(path):
            if any(name == bad or name.startswith(bad + ".") for bad in FORBIDDEN[layer]):
                offenders.append(f"{path.relative_to(PACKAGE.parent)} imports {name}")
    assert not offenders, offenders


def test_the_check_sees_imports():
    """The checker itself must find a forbidden import (guards against a test that passes vacuously)."""
    assert "gtsam" in imported_modules(PACKAGE / "factors" / "imu.py")
