"""Write-then-rename helpers: an output file is either complete or absent, and an output
folder is one run's set of files (``FolderStage``)."""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Collection, Iterator


@contextmanager
def atomic_open(path: str | Path, mode: str = "wb", **kwargs: object) -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it onto ``path`` only on success.

    The file gets the permissions a plain ``open`` would give (mkstemp's are 0600).
    """
    from graphslam.errors import OutputError

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise OutputError(f"{path}: cannot write ({e.strerror or e})") from None
    try:
        os.chmod(tmp, 0o666 & ~_umask())
        with os.fdopen(fd, mode, **kwargs) as fh:  # type: ignore[call-overload]
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        try:
            os.replace(tmp, path)
        except OSError as e:
            raise OutputError(f"{path}: cannot write ({e.strerror or e})") from None
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_open(path, "w", encoding="utf-8") as fh:
        fh.write(text)


def json_safe(obj: object) -> object:
    """Replace NaN/inf floats by None (strict JSON), recursively; numpy scalars become Python numbers."""
    import math

    import numpy as np

    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def atomic_write_json(path: str | Path, obj: object) -> None:
    import json

    atomic_write_text(path, json.dumps(json_safe(obj), indent=2, allow_nan=False))


STAGE_TAG, OLD_TAG = ".stage-", ".old-"


def check_replaceable_folder(target: str | Path, owned: Collection[str]) -> None:
    """``OutputError`` unless ``target`` can be replaced as a whole by ``FolderStage``: absent, or
    a folder that holds nothing but regular files named in ``owned`` (what a run writes there),
    that is not a mount point or filesystem root, and whose parent folder is writable."""
    from graphslam.errors import OutputError

    target = Path(target).resolve()
    parent = target.parent
    if target == parent:
        raise OutputError(f"{target}: a filesystem root cannot be an output folder")
    if target.exists():
        if not target.is_dir():
            raise OutputError(f"{target}: exists and is not a folder")
        foreign = sorted(p.name for p in target.iterdir() if p.name not in owned or not p.is_file() or p.is_symlink())
        if foreign:
            more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
            raise OutputError(
                f"{target}: holds {foreign[0]!r}{more}, which this command does not write; the folder is replaced "
                "as a whole, so choose a new or empty --out (or move those files)"
            )
        if target.stat().st_dev != parent.stat().st_dev:
            raise OutputError(f"{target}: is a mount point; use a folder inside it as --out")
    probe = parent
    while not probe.exists():  # parents are created on publish
        probe = probe.parent
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OutputError(f"{target}: cannot write into {probe}")


class FolderStage:
    """The next content of folder ``target``, built in ``path`` (``PARENT/.NAME.stage-XXXX``, same
    filesystem) and swapped in by ``publish()``: two renames (the old folder aside, the stage in),
    then the old folder is deleted. A reader sees the previous set or the new one, never a mix;
    a failed swap puts the old folder back. Only a killed process leaves anything behind: a hidden
    ``PARENT/.NAME.stage-XXXX`` (a partial new set), or, killed between the two renames, the old
    set in ``PARENT/.NAME.old-XXXX`` with ``target`` missing. They are not removed automatically:
    another run into the same folder may be writing its own stage right now."""

    def __init__(self, target: Path, path: Path) -> None:
        self.target, self.path = target, path

    @classmethod
    def create(cls, target: str | Path, owned: Collection[str]) -> "FolderStage":
        from graphslam.errors import OutputError

        check_replaceable_folder(target, owned)
        target = Path(target).resolve()
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            path = Path(tempfile.mkdtemp(prefix=f".{target.name}{STAGE_TAG}", dir=target.parent))
            os.chmod(path, 0o777 & ~_umask())
        except OSError as e:
            raise OutputError(f"{target}: cannot create the output folder ({e.strerror or e})") from None
        return cls(target, path)

    def publish(self) -> None:
        from graphslam.errors import OutputError

        target, old = self.target, None
        try:
            if target.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{target.name}{OLD_TAG}", dir=target.parent))
                os.replace(target, old)  # onto the empty placeholder: rename(2) replaces an empty folder
        except OSError as e:
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)  # (still the empty placeholder)
            self.discard()
            raise OutputError(f"{target}: cannot replace the output folder ({e.strerror or e})") from None
        try:
            os.rename(self.path, target)
        except OSError as e:
            self.discard()
            problem = f"{target}: cannot replace the output folder ({e.strerror or e})"
            if old is not None:
                try:
                    os.rename(old, target)  # put the previous set back
                except OSError:
                    raise OutputError(f"{problem}; the previous outputs are in {old}") from None
            raise OutputError(problem) from None
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
