"""Lab code builds on the public API only: ``import graphslam`` / ``from graphslam import NAME`` with
NAME one of its exports, never a sub-module."""

from __future__ import annotations

import ast
from pathlib import Path

import graphslam

LAB = Path(__file__).resolve().parents[1]


def _violations(root: Path) -> list[str]:
    bad = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                bad += [f"{rel}: import {a.name}" for a in node.names if a.name.startswith("graphslam.")]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                if node.module.startswith("graphslam."):
                    bad.append(f"{rel}: from {node.module} import ...")
                elif node.module == "graphslam":
                    bad += [f"{rel}: graphslam.{a.name} is not exported" for a in node.names
                            if a.name not in graphslam.__all__]
    return bad


def test_lab_imports_only_the_public_api() -> None:
    assert _violations(LAB) == []


def test_every_export_the_lab_uses_resolves() -> None:
    used = {a.name for p in LAB.rglob("*.py")
            for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.ImportFrom) and n.module == "graphslam"
            for a in n.names}
    assert used and all(getattr(graphslam, name) is not None for name in used)


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    (tmp_path / "probe.py").write_text(
        "import graphslam.core.types\nfrom graphslam.core.survey.align import align\nfrom graphslam import align, no_such\n")
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "own.py").write_text("from graphslam.core.survey.align import align\n")
    assert _violations(tmp_path) == [
        "experiments/own.py: from graphslam.core.survey.align import ...",  # no folder is exempt
        "probe.py: import graphslam.core.types",
        "probe.py: from graphslam.core.survey.align import ...",
        "probe.py: graphslam.no_such is not exported",
    ]
