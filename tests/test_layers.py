"""The package is layered errors -> config -> core -> io -> sim / service / viz -> app -> cli:
no module imports (at module level or lazily inside a function) from a layer above its own,
and core does no file I/O beyond what its own layer allows."""

from __future__ import annotations

import ast
from pathlib import Path

import graphslam

PKG = Path(graphslam.__file__).parent
LAYER = {"errors": 0, "config": 1, "core": 2, "io": 3, "sim": 4, "service": 4, "viz": 4, "app": 5, "cli": 6}
# sim/service/viz are side by side: none may import another of the three
PEERS = {"sim", "service", "viz"}


def _part(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "graphslam" or len(parts) < 2:
        return None
    return parts[1]


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
            if node.module == "graphslam":
                out += [f"graphslam.{a.name}" for a in node.names]
    return out


def _violations(root: Path = PKG) -> list[str]:
    bad = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        own = rel.parts[0].removesuffix(".py")
        if own in ("__init__", "__main__", "py"):
            continue  # the package facade re-exports lazily from every layer
        for mod in _imports(path):
            other = _part(mod)
            if other is None or other not in LAYER or other == own:
                continue
            if LAYER[other] > LAYER[own] or (own in PEERS and other in PEERS):
                bad.append(f"{rel} imports {mod}")
    return bad


def test_no_module_imports_from_a_higher_layer() -> None:
    assert _violations() == []


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    # a core module that lazily imports the app layer, and viz importing its peer sim, must be caught
    (tmp_path / "core").mkdir()
    (tmp_path / "viz").mkdir()
    (tmp_path / "core" / "probe.py").write_text("def f():\n    from graphslam.app.survey import run_survey\n")
    (tmp_path / "viz" / "probe.py").write_text("import graphslam.sim.radio\nfrom graphslam.core import types\n")
    assert _violations(tmp_path) == ["core/probe.py imports graphslam.app.survey", "viz/probe.py imports graphslam.sim.radio"]
