"""The architecture's rules (ARCHITECTURE.md, "Layout"), checked on the source with ``ast``.

1. Imports point downward: every layer imports only the layers listed for it in :data:`ALLOWED`.
2. ``models/`` imports neither gtsam nor ``io/`` (nor ``sim/``, ``baselines/``: both sit above it).
3. A module named after one system never imports another system's module (shared pieces live in ``core/``
   or in a layer's shared modules); the imu-pair may use the IMU's modules.
4. Only ``pipelines/`` and ``cli/`` use ``selfcal.registry``; no other module lists the systems or branches
   on a system's name.
5. ``selfcal --help`` imports no gtsam (and no numpy or scipy: building the parser is all it does).

Every checker is also run on a small module that breaks its rule, so that a checker that sees nothing fails.
"""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

from selfcal import registry

PACKAGE = Path(__file__).resolve().parents[1] / "selfcal"
LAYERS = ("core", "models", "io", "sim", "factors", "baselines", "graphs", "audit", "pipelines", "cli")
# layer -> the selfcal layers (and top-level modules) it may import; every layer may import itself
ALLOWED = {
    "core": set(),
    "models": {"core"},
    "io": {"core", "models"},
    "sim": {"core", "models", "io"},
    "factors": {"core", "models"},
    "baselines": {"core", "models"},
    "graphs": {"core", "models", "factors", "io"},
    "audit": {"core", "models", "factors", "graphs", "io"},
    "pipelines": {"core", "models", "io", "sim", "factors", "baselines", "graphs", "audit", "registry"},
    "cli": {"core", "models", "io", "sim", "factors", "baselines", "graphs", "audit", "pipelines", "registry"},
}
NO_GTSAM = ("models", "io", "sim", "baselines")
SYSTEM_MODULES = {s.module for s in registry.SYSTEMS}
MAY_USE = {"imu_pair": {"imu"}}  # system -> other systems whose modules it may import


def imported_modules(tree: ast.AST) -> set[str]:
    """Every module an ``import`` or ``from ... import`` names, including ``from selfcal.x import module``."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def layer_of(module: str) -> str | None:
    """``selfcal.graphs.tracker.gate`` -> ``graphs``; ``selfcal.registry`` -> ``registry``."""
    parts = module.split(".")
    return parts[1] if parts[0] == "selfcal" and len(parts) > 1 else None


def system_of(module: str) -> str | None:
    """The system a module belongs to (``selfcal.audit.imu.static`` -> ``imu``), or None for a shared one."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[1] in LAYERS and parts[2] in SYSTEM_MODULES else None


def upward_imports(layer: str, tree: ast.AST) -> list[str]:
    bad = []
    for name in imported_modules(tree):
        target = layer_of(name)
        if target and target != layer and target in set(LAYERS) | {"registry"} and target not in ALLOWED[layer]:
            bad.append(name)
        if layer in NO_GTSAM and name.split(".")[0] == "gtsam":
            bad.append(name)
    return bad


def cross_system_imports(module: str, tree: ast.AST) -> list[str]:
    own = system_of(module)
    if own is None:
        return []
    return [name for name in imported_modules(tree)
            if (other := system_of(name)) and other != own and other not in MAY_USE.get(own, set())]


def system_name_lists(tree: ast.AST) -> list[str]:
    """Collections of two or more system names, and comparisons of a ``system`` variable with a literal."""
    names = {s.name for s in registry.SYSTEMS} | SYSTEM_MODULES
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            literal = {e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}
            if len(literal & names) >= 2:
                found.append(f"line {node.lineno}: {sorted(literal & names)}")
        elif isinstance(node, ast.Dict):
            literal = {k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)}
            if len(literal & names) >= 2:
                found.append(f"line {node.lineno}: {sorted(literal & names)}")
        elif isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            variable = any("system" in (getattr(s, "id", None) or getattr(s, "attr", None) or "") for s in sides)
            constant = any(isinstance(s, ast.Constant) and s.value in names for s in sides)
            if variable and constant:
                found.append(f"line {node.lineno}: compares a system variable with a name")
    return found


def package_modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
        yield path, module, ast.parse(path.read_text())


@pytest.mark.parametrize("layer", LAYERS)
def test_layer_imports_point_downward(layer):
    offenders = [f"{module} imports {name}" for _, module, tree in package_modules() if layer_of(module) == layer
                 for name in upward_imports(layer, tree)]
    assert not offenders, offenders


def test_no_system_module_imports_another_systems_module():
    offenders = [f"{module} imports {name}" for _, module, tree in package_modules()
                 for name in cross_system_imports(module, tree)]
    assert not offenders, offenders


def test_only_pipelines_and_cli_use_the_registry_and_nothing_else_lists_the_systems():
    users = [module for _, module, tree in package_modules() if "selfcal.registry" in imported_modules(tree)
             or any(name.startswith("selfcal.registry") for name in imported_modules(tree))]
    assert users and all(layer_of(m) in ("pipelines", "cli") for m in users), users
    listings = [f"{module} {found}" for _, module, tree in package_modules() if module != "selfcal.registry"
                for found in system_name_lists(tree)]
    assert not listings, listings


def test_every_system_has_its_cli_module_and_its_declared_capabilities():
    for system in registry.SYSTEMS:
        assert system.load("cli").VERBS, system.name
        pipeline = system.load("pipelines")
        assert not system.audit or callable(pipeline.audit_system), system.name
        assert not system.online or callable(pipeline.online_estimator), system.name


def test_help_imports_no_estimator():
    code = ("import sys; from selfcal.cli.main import build_parser; build_parser().format_help(); "
            "print(sorted(m for m in ('gtsam', 'numpy', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


# --- the checkers see what they must see ---------------------------------------------------------------------

def test_the_checkers_find_each_kind_of_violation():
    upward = ast.parse("import gtsam\nfrom selfcal.io.recording import Recording\nfrom selfcal.core import so3\n")
    assert sorted(upward_imports("models", upward)) == ["gtsam", "selfcal.io.recording",
                                                        "selfcal.io.recording.Recording"]
    assert sorted(upward_imports("graphs", ast.parse("from selfcal.audit import engine\n"))) == [
        "selfcal.audit", "selfcal.audit.engine"]
    assert upward_imports("audit", ast.parse("from selfcal import registry\n")) == ["selfcal.registry"]
    assert upward_imports("pipelines", ast.parse("from selfcal import registry\n")) == []
    cross = ast.parse("from selfcal.models import ship\nfrom selfcal.graphs.tracker import gate\n"
                      "from selfcal.core import so3\n")
    assert sorted(cross_system_imports("selfcal.audit.tracker", cross)) == ["selfcal.models.ship"]
    assert cross_system_imports("selfcal.audit.imu_pair", ast.parse("from selfcal.models import imu\n")) == []
    assert cross_system_imports("selfcal.audit.engine", cross) == []  # a shared module may use any system
    lists = ast.parse('SYSTEMS = ("imu", "tracker")\nif system == "ship":\n    pass\nx = {"imu": 1, "scan": 2}\n')
    assert len(system_name_lists(lists)) == 3
    assert system_name_lists(ast.parse('sensor = "imu"\nkind = ("imu0", "imu1")\n')) == []


def test_the_grid_in_docs_architecture_matches_the_package():
    """docs/architecture.md's grid is the newcomer's map: one row per registry system, marks as on disk."""
    text = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| system |"))
    layers = [cell.strip() for cell in header.strip("|").split("|")][1:]
    rows = {line.split("|")[1].strip().split()[0].strip("`"): [c.strip() for c in line.strip("|").split("|")[1:]]
            for line in text.splitlines() if line.startswith("| `")}
    assert set(rows) >= {s.name for s in registry.SYSTEMS}
    for system in registry.SYSTEMS:
        for layer, mark in zip(layers, rows[system.name]):
            on_disk = ("✓" if (PACKAGE / layer / f"{system.module}.py").is_file() else
                       "✓/" if (PACKAGE / layer / system.module).is_dir() else "")
            assert mark == on_disk, (system.name, layer, mark, on_disk)
