"""The house a newcomer reads: the lab and the docs are filed by subject, the docs are a reference.

- no file or folder under ``lab/`` or ``docs/`` is named after a ticket (``issue37/``, ``issue-40.md``);
- no page of ``docs/`` is over 400 lines;
- no line of ``docs/``, ``README.md`` or the package cites a ticket ("issue 16", "issues 15 and 18",
  "ticket 3", "(#37)"): they say what, not which ticket (the lab's journal may say what prompted an
  entry);
- every relative link of a page in ``docs/``, ``README.md`` or a lab README resolves, and every
  ``lab/...`` script or folder those pages name exists (the lab moves; its references follow).

Each checker takes a root folder, so the tests below also run it on a small tree that breaks each rule.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_DOC_LINES = 400

TICKET_NAME = re.compile(r"(?i)(?<![a-z])(issues?|tickets?|bugs?|gh|pr)[-_ ]?#?\d+|^#\d+")
# "#1" in an error message is a query's index; a ticket is cited as "#37", "(#37)", "issue 37", "gh-37"
TICKET_CITE = re.compile(r"(?i)\b(issues?|tickets?)\s*#?\d+|(?<![\w&#])#\d{2,3}\b|\bgh-\d+")
MD_LINK = re.compile(r"\]\(([^)\s]+)\)")
LAB_PATH = re.compile(r"\blab/[\w./-]*\w")
SKIP_DIRS = {"__pycache__", ".pytest_cache", ".mypy_cache", ".ruff_cache"}


def _walk(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if not SKIP_DIRS & set(p.relative_to(root).parts))


def ticket_named(root: Path, folders: tuple[str, ...] = ("lab", "docs")) -> list[str]:
    """Files and folders under ``folders`` whose name cites a ticket."""
    return [str(p.relative_to(root)) for f in folders if (root / f).is_dir()
            for p in _walk(root / f) if TICKET_NAME.search(p.stem)]


def long_pages(root: Path) -> list[str]:
    """Pages of docs/ over MAX_DOC_LINES lines."""
    return [f"{p.relative_to(root)}: {n} lines" for p in sorted((root / "docs").rglob("*.md"))
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_DOC_LINES]


def ticket_citations(root: Path) -> list[str]:
    """Lines of docs/, README.md and the package (code, docstrings, comments) that cite a ticket."""
    files = [root / "README.md", *sorted((root / "docs").rglob("*.md")), *sorted((root / "graphslam").rglob("*.py"))]
    return [f"{p.relative_to(root)}:{i}: {line.strip()}" for p in files if p.is_file()
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if TICKET_CITE.search(line)]


def _pages(root: Path) -> list[Path]:
    return [p for p in [root / "README.md", *sorted((root / "docs").rglob("*.md")),
                        *sorted((root / "lab").rglob("README.md"))] if p.is_file()]


def broken_references(root: Path) -> list[str]:
    """Relative links that lead nowhere, and lab/ paths that do not exist, in the docs, README and lab READMEs."""
    bad = []
    for page in _pages(root):
        text = page.read_text(encoding="utf-8")
        rel = page.relative_to(root)
        for target in MD_LINK.findall(text):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path = target.split("#", 1)[0]
            if path and not (page.parent / path).exists():
                bad.append(f"{rel}: link {target}")
        for ref in LAB_PATH.findall(text):
            if "*" not in ref and not (root / ref).exists():
                bad.append(f"{rel}: {ref}")
    return bad


def test_no_file_or_folder_is_named_after_a_ticket() -> None:
    assert ticket_named(REPO) == []


def test_no_docs_page_is_over_400_lines() -> None:
    assert long_pages(REPO) == []


def test_docs_readme_and_package_cite_no_ticket() -> None:
    assert ticket_citations(REPO) == []


def test_links_and_lab_paths_resolve() -> None:
    assert broken_references(REPO) == []


def test_the_checkers_see_each_violation(tmp_path: Path) -> None:
    (tmp_path / "lab" / "issue37").mkdir(parents=True)
    (tmp_path / "lab" / "issue37" / "try.py").write_text("x = 1\n")
    (tmp_path / "lab" / "tracking").mkdir()
    (tmp_path / "lab" / "tracking" / "README.md").write_text("Run `python lab/tracking/gone.py` ([x](../../docs/none.md)).\n")
    (tmp_path / "lab" / "journal").mkdir()
    (tmp_path / "lab" / "journal" / "issue-40.md").write_text("# a journal named after its ticket\n")
    (tmp_path / "lab" / "journal" / "survey.md").write_text("Prompted by issue 37 (a journal may say so).\n")
    (tmp_path / "lab" / "high2.py").write_text("x = 1\n")  # "gh2" inside a word is no ticket
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "long.md").write_text("line\n" * (MAX_DOC_LINES + 1))
    (tmp_path / "docs" / "ok.md").write_text("line\n" * (MAX_DOC_LINES - 2) + "see [long](long.md), [x](#anchor), [w](https://x.org)\n"
                                           "the error names the query (#1: no_known_ap) and (#2); #ffffff and &#160; are no tickets\n")
    (tmp_path / "docs" / "cites.md").write_text("The default since issue 16.\nFixed in (#37).\nIssues 15 and 18 added it.\n")
    (tmp_path / "README.md").write_text("See [tracking](docs/tracking.md) and `lab/tracking/`.\n")
    (tmp_path / "graphslam").mkdir()
    (tmp_path / "graphslam" / "m.py").write_text('"""The ticket 3 fix."""\nx = f"#{1}"\n')

    assert ticket_named(tmp_path) == ["lab/issue37", "lab/journal/issue-40.md"]
    assert long_pages(tmp_path) == [f"docs/long.md: {MAX_DOC_LINES + 1} lines"]  # 400 lines is allowed
    assert ticket_citations(tmp_path) == [
        "docs/cites.md:1: The default since issue 16.",
        "docs/cites.md:2: Fixed in (#37).",
        "docs/cites.md:3: Issues 15 and 18 added it.",
        "graphslam/m.py:1: \"\"\"The ticket 3 fix.\"\"\"",
    ]
    assert broken_references(tmp_path) == [
        "README.md: link docs/tracking.md",
        "lab/tracking/README.md: link ../../docs/none.md",
        "lab/tracking/README.md: lab/tracking/gone.py",
    ]
