"""Write-then-rename helpers: an output file is either complete or absent, and an output
folder is one run's set of files (``FolderStage``).

A process killed at any moment (SIGKILL, OOM killer, power cut aside) leaves the previous file
or folder, or the new one, complete; what it was building is left beside it, marked so that the
next write of the same output removes it (``clean_stale``), and only it: each temporary file
or stage folder is held by its writer with ``flock``, which the kernel drops when the writer
dies, so "can be locked" means "its writer is gone", and a live writer's stage is never touched.

Test hooks (the kill tests): ``GRAPHSLAM_TEST_KILL_AT=POINT[,POINT...]`` makes the process
SIGKILL itself at the named points (``kill_point``), e.g. between the two renames of a swap;
``POINT@N``: only at its first N passes, counted (across processes) by files in
``$GRAPHSLAM_TEST_KILL_DIR``. Unset, a point costs one dictionary look-up.
``GRAPHSLAM_NO_EXCHANGE=1`` makes ``FolderStage`` use the two-rename swap of systems without
``renameat2``.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import re
import shutil
import signal
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Collection, Iterator

KILL_ENV, KILL_DIR_ENV = "GRAPHSLAM_TEST_KILL_AT", "GRAPHSLAM_TEST_KILL_DIR"


def kill_point(name: str) -> None:
    """SIGKILL this process here if ``name`` is listed in ``$GRAPHSLAM_TEST_KILL_AT`` (tests only)."""
    points = os.environ.get(KILL_ENV)
    if not points:
        return
    for point in points.split(","):
        base, _, times = point.partition("@")
        if base != name:
            continue
        if times:  # the first N passes only
            folder = Path(os.environ[KILL_DIR_ENV])
            tag = re.sub(r"[^A-Za-z0-9_.-]", "_", name)
            for i in range(int(times)):
                try:
                    os.close(os.open(folder / f"{tag}.{i}", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                except FileExistsError:
                    continue
                break
            else:
                return
        os.kill(os.getpid(), signal.SIGKILL)


def _tmp_pattern(name: str) -> re.Pattern[str]:
    """The names ``atomic_open`` gives its temporary files for ``name`` (mkstemp's 8 characters)."""
    return re.compile(re.escape(f".{name}.") + r"[a-z0-9_]{8}" + re.escape(".tmp"))


def _lock_now(fd: int) -> bool:
    """Take ``fd``'s exclusive flock without waiting; False if another process holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def remove_stale_temp_files(path: str | Path) -> list[Path]:
    """Remove ``atomic_open``'s temporary files for ``path`` whose writer is gone (killed before
    its rename): each is locked by its writer while it writes. Returns what was removed."""
    path = Path(path)
    pattern = _tmp_pattern(path.name)
    removed = []
    try:
        names = [n for n in os.listdir(path.parent) if pattern.fullmatch(n)]
    except OSError:
        return removed
    for n in names:
        tmp = path.parent / n
        try:
            fd = os.open(tmp, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if _lock_now(fd):
                os.unlink(tmp)
                removed.append(tmp)
        except OSError:
            pass
        finally:
            os.close(fd)
    return removed


@contextmanager
def atomic_open(path: str | Path, mode: str = "wb", **kwargs: object) -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it onto ``path`` only on success.

    The file gets the permissions a plain ``open`` would give (mkstemp's are 0600).
    """

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temp_files(path)  # what a killed writer of the same file left
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise _output_error(path, e) from None
    fh = None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # held until closed, after the rename: never stale while we live
        os.chmod(tmp, 0o666 & ~_umask())
        fh = os.fdopen(fd, mode, **kwargs)  # type: ignore[call-overload]
        try:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
            kill_point(f"atomic:{path.name}")
            os.replace(tmp, path)
        except OSError as e:  # e.g. the disk full in the middle of the file
            raise _output_error(path, e) from None
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    finally:
        if fh is not None:
            try:
                fh.close()
            except OSError:  # a buffered write that failed already raised above
                pass
        else:
            os.close(fd)


def _output_error(path: Path, e: OSError) -> Exception:
    """``OutputError`` "PATH: cannot write (REASON)"; ``.reason`` keeps REASON for a caller that
    names a folder instead (a file of a stage is no name an operator knows)."""
    from graphslam.errors import OutputError

    reason = e.strerror or str(e)
    err = OutputError(f"{path}: cannot write ({reason})")
    err.reason = reason  # type: ignore[attr-defined]
    return err


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


STAGE_TAG, OLD_TAG, LOCK_SUFFIX = ".stage-", ".old-", ".lock"
# The first line of a stage's lock file: what makes a ``.NAME.stage-*`` folder ours. A folder of
# that name without a lock file holding it (made by anything else) is never touched.
STAGE_MARKER = "graphslam output stage\n"
_AT_FDCWD, _RENAME_EXCHANGE = -100, 2


def _libc_renameat2() -> object | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = getattr(ctypes.CDLL(None, use_errno=True), "renameat2")
    except (OSError, AttributeError):  # glibc < 2.28, musl without it
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_renameat2 = _libc_renameat2()


def exchange(a: Path, b: Path) -> bool:
    """Swap the names of ``a`` and ``b`` in one step (Linux ``renameat2(RENAME_EXCHANGE)``):
    there is no moment at which either name is missing. False where the system or the
    filesystem cannot (the caller falls back to two renames); ``OSError`` for other failures."""
    if _renameat2 is None or os.environ.get("GRAPHSLAM_NO_EXCHANGE"):
        return False
    if _renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:  # type: ignore[operator]
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(a))


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (a power cut after it keeps it); best effort."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _is_temp_of(name: str, owned: Collection[str]) -> bool:
    """A temporary file ``atomic_open`` makes for one of ``owned`` (a killed writer's, or a live one's)."""
    return name.startswith(".") and any(_tmp_pattern(o).fullmatch(name) for o in owned)


def check_replaceable_folder(target: str | Path, owned: Collection[str]) -> None:
    """``OutputError`` unless ``target`` can be replaced as a whole by ``FolderStage``: absent, or
    a folder that holds nothing but regular files named in ``owned`` (what a run writes there;
    their ``atomic_open`` temporary files too), that is not a mount point or filesystem root,
    and whose parent folder is writable."""
    from graphslam.errors import OutputError

    target = Path(target).resolve()
    parent = target.parent
    if target == parent:
        raise OutputError(f"{target}: a filesystem root cannot be an output folder")
    if target.exists():
        if not target.is_dir():
            raise OutputError(f"{target}: exists and is not a folder")
        foreign = sorted(
            p.name for p in target.iterdir()
            if (p.name not in owned and not _is_temp_of(p.name, owned)) or not p.is_file() or p.is_symlink()
        )
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


def clean_stale(target: str | Path) -> list[Path]:
    """Remove what runs into folder ``target`` that were killed left beside it, and only that:
    for each ``PARENT/.NAME.stage-KEY.lock`` that is ours (``STAGE_MARKER``) and stale (its
    ``flock`` can be taken: its process is gone), the stage ``.NAME.stage-KEY`` and any
    ``.NAME.old-KEY``; if ``target`` is missing (a run killed between the two renames of the
    fallback swap), that ``.old-KEY`` folder, the previous set, is put back as ``target`` first.
    A stage whose run is alive (its lock held), and any folder named like a stage without our
    lock file, are left alone. Returns the paths removed or restored. Errors are ignored: this
    is housekeeping, the run goes on."""
    target = Path(target).resolve()  # as FolderStage names it
    parent, name = target.parent, target.name
    prefix = f".{name}{STAGE_TAG}"
    done: list[Path] = []
    try:
        locks = sorted(n for n in os.listdir(parent) if n.startswith(prefix) and n.endswith(LOCK_SUFFIX))
    except OSError:
        return done
    for n in locks:
        lock = parent / n
        key = n[len(prefix):-len(LOCK_SUFFIX)]
        try:
            fd = os.open(lock, os.O_RDWR | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if not _lock_now(fd):
                continue  # a live run's stage
            stage, old = parent / f"{prefix}{key}", parent / f".{name}{OLD_TAG}{key}"
            head = os.pread(fd, len(STAGE_MARKER), 0)
            if head == b"" and not os.path.lexists(stage):
                # ours, its writer killed between creating and marking it (it had made nothing
                # else); a live writer that loses it here sees it unlinked and makes another
                os.unlink(lock)
                done.append(lock)
                continue
            if head != STAGE_MARKER.encode():
                continue  # not ours
            if old.is_dir() and not old.is_symlink():
                if not os.path.lexists(target):
                    os.rename(old, target)  # the previous set, complete: killed between the two renames
                    done.append(target)
                else:
                    shutil.rmtree(old)
                    done.append(old)
            if stage.is_dir() and not stage.is_symlink():
                shutil.rmtree(stage)
                done.append(stage)
            os.unlink(lock)
            done.append(lock)
        except OSError:
            pass
        finally:
            os.close(fd)
    return done


class FolderStage:
    """The next content of folder ``target``, built in ``path`` (``PARENT/.NAME.stage-KEY``, same
    filesystem) and swapped in by ``publish()``. A reader sees the previous set or the new one,
    never a mix, and ``target`` is never missing: on Linux the swap is one
    ``renameat2(RENAME_EXCHANGE)`` (the stage name then holds the old set, which is deleted);
    elsewhere two renames (the old folder aside as ``.NAME.old-KEY``, the stage in), and a run
    killed between them leaves the old set there, which the next run puts back (``clean_stale``).
    A failed swap puts the old folder back.

    While the stage exists its process holds an ``flock`` on ``PARENT/.NAME.stage-KEY.lock``
    (marked ``STAGE_MARKER``); the lock file goes last. A run killed at any moment leaves a
    stage, an old set or a lock file that the next ``FolderStage`` (or ``clean_stale``) for the
    same target removes; a concurrent run's live stage is not touched."""

    def __init__(self, target: Path, path: Path, lock: Path | None = None, lock_fd: int | None = None) -> None:
        self.target, self.path = target, path
        self.lock, self._lock_fd = lock, lock_fd

    @classmethod
    def create(cls, target: str | Path, owned: Collection[str]) -> "FolderStage":
        from graphslam.errors import OutputError

        check_replaceable_folder(target, owned)
        target = Path(target).resolve()
        prefix = f".{target.name}{STAGE_TAG}"
        fd = None
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            clean_stale(target)
            while True:
                fd, lock = tempfile.mkstemp(prefix=prefix, suffix=LOCK_SUFFIX, dir=target.parent)
                fcntl.flock(fd, fcntl.LOCK_EX)
                if os.fstat(fd).st_nlink:
                    break
                os.close(fd)  # a cleaner took the empty file for a killed writer's first: another
                fd = None
            kill_point("stage.unmarked")
            os.write(fd, f"{STAGE_MARKER}pid {os.getpid()}\n".encode())
            path = target.parent / Path(lock).name[: -len(LOCK_SUFFIX)]
            os.mkdir(path, 0o777)  # (less the umask)
        except OSError as e:
            if fd is not None:
                os.unlink(lock)
                os.close(fd)
            raise OutputError(f"{target}: cannot create the output folder ({e.strerror or e})") from None
        return cls(target, path, Path(lock), fd)

    def publish(self) -> None:
        from graphslam.errors import OutputError

        target, parent = self.target, self.target.parent
        kill_point("publish.start")
        try:
            exchanged = target.exists() and exchange(self.path, target)
        except OSError as e:
            self.discard()
            raise OutputError(f"{target}: cannot replace the output folder ({e.strerror or e})") from None
        if exchanged:
            _fsync_dir(parent)
            kill_point("publish.exchanged")
            shutil.rmtree(self.path, ignore_errors=True)  # the old set, now under the stage's name
        else:
            self._publish_in_two_renames()
        kill_point("publish.cleaned")
        self._unlock()

    def _unlock(self) -> None:
        """Remove the lock file, then let go of its lock (the other order would let a cleaner in).
        If the stage (or the old set) could not be deleted in full, the lock file stays, unlocked:
        the next run into the target deletes the rest."""
        leftover = self.path.exists() or self.path.with_name(self.path.name.replace(STAGE_TAG, OLD_TAG, 1)).exists()
        if self.lock is not None and not leftover:
            try:
                os.unlink(self.lock)
            except OSError:
                pass
        self._close()

    def _publish_in_two_renames(self) -> None:
        from graphslam.errors import OutputError

        target, old = self.target, None
        try:
            if target.exists():
                old = target.parent / self.path.name.replace(STAGE_TAG, OLD_TAG, 1)
                os.rename(target, old)
                kill_point("publish.aside")
        except OSError as e:
            self.discard()
            raise OutputError(f"{target}: cannot replace the output folder ({e.strerror or e})") from None
        try:
            os.rename(self.path, target)
        except OSError as e:
            problem = f"{target}: cannot replace the output folder ({e.strerror or e})"
            if old is not None:
                try:
                    os.rename(old, target)  # put the previous set back
                except OSError:
                    shutil.rmtree(self.path, ignore_errors=True)
                    self._close()  # lock file kept: the next run puts the previous set back
                    raise OutputError(f"{problem}; the previous outputs are in {old}") from None
            self.discard()
            raise OutputError(problem) from None
        _fsync_dir(target.parent)
        if old is not None:
            kill_point("publish.renamed")
            shutil.rmtree(old, ignore_errors=True)

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
        self._unlock()

    def _close(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
