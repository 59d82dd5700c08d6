"""The package is layered errors, names -> config -> core -> io -> sim / service / viz -> app -> cli:
no module imports (at module level or lazily inside a function) from a layer above its own,
and core does no file I/O beyond what its own layer allows. Inside core the sub-packages depend in
one direction too: common (with types, progress, summary) -> radiomap -> uwb -> survey, and
tracking beside survey (on radiomap); neither of survey and tracking imports the other. And no two
modules of one core sub-package (or of core's own modules) import each other, directly or through
others: what two modules share goes into a third that both import."""

from __future__ import annotations

import ast
from pathlib import Path

import graphslam

PKG = Path(graphslam.__file__).parent
LAYER = {"errors": 0, "names": 0, "config": 1, "tracking_config": 1, "core": 2, "io": 3, "sim": 4, "service": 4, "viz": 4, "app": 5, "cli": 6}
# sim/service/viz are side by side: none may import another of the three
PEERS = {"sim", "service", "viz"}
# the core sub-packages (and core's own modules, which count as common)
CORE = {"common": 0, "types": 0, "progress": 0, "summary": 0, "radiomap": 1, "uwb": 2, "survey": 3, "tracking": 3}
CORE_PEERS = {"survey", "tracking"}


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


def _core_part(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[:2] == ["graphslam", "core"] else None


def _core_violation(rel: Path, mod: str) -> bool:
    """A core module importing a core sub-package above its own (or its peer)."""
    if len(rel.parts) < 2 or rel.parts[0] != "core":
        return False
    own, other = rel.parts[1].removesuffix(".py"), _core_part(mod)
    if own == "__init__" or other is None or other == own or other not in CORE or own not in CORE:
        return False
    return CORE[other] > CORE[own] or (own in CORE_PEERS and other in CORE_PEERS)


def _violations(root: Path = PKG) -> list[str]:
    bad = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        own = rel.parts[0].removesuffix(".py")
        if own in ("__init__", "__main__", "py"):
            continue  # the package facade re-exports lazily from every layer
        for mod in _imports(path):
            other = _part(mod)
            if other is None or other not in LAYER:
                continue
            if other == own:
                if _core_violation(rel, mod):
                    bad.append(f"{rel} imports {mod}")
                continue
            if LAYER[other] > LAYER[own] or (own in PEERS and other in PEERS):
                bad.append(f"{rel} imports {mod}")
    return bad


def _import_targets(path: Path) -> list[str]:
    """Every module ``path`` imports (at module level, lazily or for type checking): ``from P import
    n`` counts as ``P.n`` (a module, when ``n`` is one) and ``P``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [node.module] + [f"{node.module}.{a.name}" for a in node.names]
    return out


def _circles(folder: Path, package: str) -> list[list[str]]:
    """The circles among the modules of ``folder`` (the package ``package``): the groups of two or
    more modules each of which imports, directly or through the others, every other (strongly
    connected components of the import graph), each sorted, in order."""
    names = {p.stem for p in folder.glob("*.py")}
    graph: dict[str, set[str]] = {}
    for path in sorted(folder.glob("*.py")):
        deps = set()
        for target in _import_targets(path):
            if target.startswith(package + "."):
                name = target[len(package) + 1:].split(".")[0]
                if name in names and name != path.stem:
                    deps.add(name)
        graph[path.stem] = deps
    # Tarjan's strongly connected components
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(circles)


def _core_circles(root: Path = PKG) -> list[str]:
    """Per core sub-package (and core's own modules): its modules that import each other."""
    core = root / "core"
    folders = [core] + sorted(p for p in core.iterdir() if p.is_dir() and p.name != "__pycache__")
    out = []
    for folder in folders:
        package = ".".join(["graphslam", *folder.relative_to(root).parts])
        for group in _circles(folder, package):
            out.append(f"{folder.relative_to(root).as_posix()}: {', '.join(group)} import each other")
    return out


def test_every_core_sub_package_has_a_rank() -> None:
    # a new core sub-package must be placed in the order (else the check would skip it)
    names = {p.name.removesuffix(".py") for p in (PKG / "core").iterdir() if p.name != "__pycache__"}
    assert names - {"__init__"} <= set(CORE)


def test_no_module_imports_from_a_higher_layer() -> None:
    assert _violations() == []


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    # a core module that lazily imports the app layer, and viz importing its peer sim, must be caught
    (tmp_path / "core").mkdir()
    (tmp_path / "viz").mkdir()
    (tmp_path / "core" / "probe.py").write_text("def f():\n    from graphslam.app.survey import run_survey\n")
    (tmp_path / "viz" / "probe.py").write_text("import graphslam.sim.radio\nfrom graphslam.core import types\n")
    assert _violations(tmp_path) == ["core/probe.py imports graphslam.app.survey", "viz/probe.py imports graphslam.sim.radio"]


def test_the_checker_sees_a_core_sub_package_violation(tmp_path: Path) -> None:
    # radiomap importing survey (above it), uwb lazily importing survey, survey and tracking (peers)
    # importing each other, and common importing a sub-package: all caught; survey -> radiomap is fine
    for sub in ("radiomap", "uwb", "survey", "tracking", "common"):
        (tmp_path / "core" / sub).mkdir(parents=True)
    (tmp_path / "core" / "radiomap" / "probe.py").write_text("from graphslam.core.survey.align import Alignment\n")
    (tmp_path / "core" / "uwb" / "probe.py").write_text("def f():\n    import graphslam.core.survey.factors\n")
    (tmp_path / "core" / "survey" / "probe.py").write_text(
        "from graphslam.core.radiomap import knn\nfrom graphslam.core.tracking.filters import FusionModel\n")
    (tmp_path / "core" / "tracking" / "probe.py").write_text("from graphslam.core.survey import align\n")
    (tmp_path / "core" / "common" / "probe.py").write_text("from graphslam.core.types import Survey\nimport graphslam.core.uwb\n")
    assert _violations(tmp_path) == [
        "core/common/probe.py imports graphslam.core.uwb",
        "core/radiomap/probe.py imports graphslam.core.survey.align",
        "core/survey/probe.py imports graphslam.core.tracking.filters",
        "core/tracking/probe.py imports graphslam.core.survey",
        "core/uwb/probe.py imports graphslam.core.survey.factors",
    ]


def test_no_circle_inside_a_core_sub_package() -> None:
    assert _core_circles() == []


def test_the_checker_sees_a_circle(tmp_path: Path) -> None:
    # in radiomap: a -> b lazily, b -> c, c -> a for type checking only (one circle of three); d <-> e
    # through "from package import module"; f -> a is no circle. In survey: a module importing
    # itself, and one importing radiomap's a (another sub-package): neither is a circle
    rm, sv = tmp_path / "core" / "radiomap", tmp_path / "core" / "survey"
    rm.mkdir(parents=True)
    sv.mkdir()
    (rm / "__init__.py").write_text("")
    (rm / "a.py").write_text("def f():\n    from graphslam.core.radiomap.b import g\n")
    (rm / "b.py").write_text("import graphslam.core.radiomap.c\n")
    (rm / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from graphslam.core.radiomap.a import f\n")
    (rm / "d.py").write_text("from graphslam.core.radiomap import e\n")
    (rm / "e.py").write_text("from graphslam.core.radiomap import d as D\n")
    (rm / "f.py").write_text("from graphslam.core.radiomap.a import f\n")
    (sv / "s.py").write_text("from graphslam.core.survey import s\nfrom graphslam.core.radiomap.a import f\n")
    (sv / "t.py").write_text("from graphslam.core.survey.s import x\n")
    (tmp_path / "core" / "types.py").write_text("from graphslam.core import summary\n")
    (tmp_path / "core" / "summary.py").write_text("from graphslam.core.types import Survey\n")
    assert _core_circles(tmp_path) == [
        "core: summary, types import each other",
        "core/radiomap: a, b, c import each other",
        "core/radiomap: d, e import each other",
    ]
