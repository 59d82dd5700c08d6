"""The recordings a list of paths names: a module of its own, free of numpy, so that the commands
refuse a missing input (one line, exit code 2) before importing any of the work's libraries."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Iterator

from graphslam.errors import InputError


def expand_paths(paths: Iterable[str | Path]) -> list[Path]:
    """Files as given; a folder means the ``*.mcap`` files directly in it (not its sub-folders:
    a simulator's held-out ``test/`` walks or another floor must not join a survey by accident).
    Sorted, de-duplicated."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(p.glob("*.mcap"))
            if not found:
                raise InputError(p, "folder contains no .mcap recordings")
            out.extend(found)
        elif p.exists():
            out.append(p)
        else:
            raise InputError(p, "no such file or folder")
    seen: set[Path] = set()
    unique = []
    for p in out:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(p)
    if not unique:
        raise InputError(", ".join(map(str, paths)) or "<none>", "no recordings given")
    return unique


def walk_folders(root: str | Path) -> Iterator[tuple[Path, list[str], list[str]]]:
    """``os.walk(root)`` top-down, sub-folders sorted, following symbolic links to folders (a site
    assembled of links to floors on other disks) and entering each real folder once (a link back up the
    tree ends there). Yields (folder, its sub-folder names, its file names); emptying the sub-folder list
    in place prunes the walk below that folder, as with ``os.walk``."""
    seen: set[str] = set()
    for d, dirs, files in os.walk(root, followlinks=True):
        real = os.path.realpath(d)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs.sort()
        yield Path(d), dirs, files
