"""``recordings_cache.npz``: the parsed recordings of a survey, keyed by each file's content hash.

A survey output keeps it so that ``survey --update`` takes the walks whose files are byte for byte
the ones it read last time from here instead of parsing them again (paper ``--size 12``: 63 files,
1.2 s to parse, 0.2 s from the cache). A file that changed, or moved to a new name that its id may
come from, is parsed as usual; so is every file when the cache is missing, unreadable, or
written by another version of graphslam or of this format. The cache is never an input: a problem
with it is a log line and a full read, not an error.

A NumPy ``.npz`` archive (no pickles). S cached walks, arrays concatenated over them, each with an
``*_off`` (S+1) array of its rows:

==============  ===========  ==================================================
array           dtype        meaning
==============  ===========  ==================================================
format_version  int64 ()     2
graphslam       str ()       the version of graphslam that parsed the files
key             str (S,)     BLAKE2b-128 of the file's bytes (hex)
session_id      str (S,)     the walk's id
stem            str (S,)     its file's name without suffix (an id equal to it may have come from it)
site, floor     str (S,)     ``graphslam.session``'s site and floor
uwb_id          str (S,)     ``graphslam.session``'s ``uwb_id``
step_*          t, xy, h     ``/foot/pose`` (ns; m; rad)
gt_*            t, xy, h     ``/ground_truth/pose``; ``gt_has`` (S,) bool: the topic is present
hd_*            t, yaw       ``/phone/heading``; ``hd_has`` (S,) bool
mg_*            t, enu       ``/phone/magnetic`` (ns; µT east, north, up); ``mg_has`` (S,) bool
lm_*            t, id, x, y  ``/landmarks``
scan_*          t            ``/wifi/scan`` (ns); ``read_off`` (scans+1) its readings
read_ap, rssi   int64, f8    each reading's access point (index into ``aps``) and RSS (dBm)
uwb_*           t, resp,     ``/uwb/range`` (ns; responder id; it is an anchor; m); ``uwb_has`` (S,) bool
                anchor, m
anc_*           id, xyz, dim the walk's UWB anchors (site frame, m; z NaN where ``dim`` is 2)
aps             str (A,)     BSSIDs
==============  ===========  ==================================================
"""

from __future__ import annotations

import hashlib
import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

import graphslam
from graphslam.core.types import (
    HeadingTrack, LandmarkMark, MagneticTrack, PoseTrack, Scan, Session, Survey, UwbRanges, shared_floats,
)
from graphslam.io.atomic import atomic_open

log = logging.getLogger(__name__)

CACHE_FILE = "recordings_cache.npz"
CACHE_FORMAT = 2  # bumped whenever the reader's Sessions change (a release's version changes anyway)


def recording_key(buf: bytes) -> str:
    """The cache's key of a recording: BLAKE2b-128 of its bytes."""
    return hashlib.blake2b(buf, digest_size=16).hexdigest()


@dataclass(frozen=True, eq=False)
class RecordingCache:
    """The walks of one ``recordings_cache.npz``, rebuilt on demand by key."""

    arrays: Mapping[str, NDArray]
    index: Mapping[str, int]  # key -> walk
    _aps: list[str]

    def __len__(self) -> int:
        return len(self.index)

    def session(self, key: str, path: Path) -> Session | None:
        """The walk parsed from a file with key ``key``, as the reader makes it from ``path``; None if
        not cached."""
        k = self.index.get(key)
        if k is None:
            return None
        sid, stem = str(self.arrays["session_id"][k]), str(self.arrays["stem"][k])
        if sid == stem and path.stem != stem:  # the id may be the old file name's: parse the renamed file
            return None
        try:
            return self._session(k, sid, path)
        except (ValueError, TypeError, IndexError) as e:  # arrays that do not fit: the file is parsed
            log.warning("recordings cache: walk %r unusable (%s), its file is parsed", sid, e)
            return None

    def _session(self, k: int, sid: str, path: Path) -> Session:
        a = self.arrays

        def rows(name: str) -> slice:
            off = a[f"{name}_off"]
            return slice(int(off[k]), int(off[k + 1]))

        s = rows("step")
        steps = PoseTrack(a["step_t"][s], a["step_xy"][s], a["step_h"][s])
        g = rows("gt")
        gt = PoseTrack(a["gt_t"][g], a["gt_xy"][g], a["gt_h"][g]) if a["gt_has"][k] else None
        h = rows("hd")
        heading = HeadingTrack(a["hd_t"][h], a["hd_yaw"][h]) if a["hd_has"][k] else None
        g = rows("mg")
        magnetic = MagneticTrack(a["mg_t"][g], a["mg_enu"][g]) if a["mg_has"][k] else None
        m = rows("lm")
        marks = tuple(LandmarkMark(int(t), str(i), float(x), float(y)) for t, i, x, y in
                      zip(a["lm_t"][m], a["lm_id"][m], a["lm_x"][m], a["lm_y"][m]))
        u = rows("uwb")
        uwb = UwbRanges(a["uwb_t"][u], tuple(a["uwb_resp"][u].tolist()), a["uwb_anchor"][u],
                        a["uwb_m"][u]) if a["uwb_has"][k] else None
        n = rows("anc")
        anchors = {str(i): tuple(float(v) for v in xyz[:d]) for i, xyz, d in
                   zip(a["anc_id"][n], a["anc_xyz"][n], a["anc_dim"][n])}
        c = rows("scan")
        r_off = a["read_off"][c.start : c.stop + 1].tolist()
        r0, r1 = r_off[0], r_off[-1]
        aps = list(map(self._aps.__getitem__, a["read_ap"][r0:r1].tolist()))
        rssi = shared_floats(a["rssi"][r0:r1])
        scans = tuple(Scan._validated(t, dict(zip(aps[q0 - r0 : q1 - r0], rssi[q0 - r0 : q1 - r0])))
                      for t, q0, q1 in zip(a["scan_t"][c].tolist(), r_off[:-1], r_off[1:]))
        return Session(
            session_id=sid, steps=steps, scans=scans, landmarks=marks, ground_truth=gt,
            site=str(a["site"][k]), floor=str(a["floor"][k]), source=str(path), uwb_id=str(a["uwb_id"][k]),
            uwb_ranges=uwb, uwb_anchors=anchors, heading=heading, magnetic=magnetic,
        )


def read_recording_cache(path: str | Path) -> RecordingCache | None:
    """The cache at ``path``; None (and why, in the log) if it is missing or cannot be used."""
    path = Path(path)
    if not path.is_file():
        log.info("%s: no recordings cache, every recording is parsed", path)
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        if int(a["format_version"]) != CACHE_FORMAT or str(a["graphslam"]) != graphslam.__version__:
            log.info("%s: recordings cache of another format or graphslam version, every recording is parsed", path)
            return None
        keys = [str(k) for k in a["key"].reshape(-1)]
        n = len(keys)
        for name in ("step", "gt", "hd", "mg", "lm", "scan", "uwb", "anc"):
            off, rows = a[f"{name}_off"], a[f"{name}_id" if name == "anc" else f"{name}_t"]
            if off.shape != (n + 1,) or off[0] != 0 or np.any(np.diff(off) < 0) or off[-1] != len(rows):
                raise ValueError(f"{name}_off does not index its rows")
        n_read = len(a["read_ap"])
        if len(a["read_off"]) != len(a["scan_t"]) + 1 or a["read_off"][-1] != n_read or len(a["rssi"]) != n_read:
            raise ValueError("read_off does not index the readings")
        if len(a["read_ap"]) and (a["read_ap"].min() < 0 or a["read_ap"].max() >= len(a["aps"])):
            raise ValueError("read_ap out of range")
    except (OSError, ValueError, KeyError, TypeError, IndexError, zipfile.BadZipFile, EOFError) as e:
        log.warning("%s: unusable recordings cache (%s: %s), every recording is parsed", path, type(e).__name__, e)
        return None
    return RecordingCache(a, {k: i for i, k in enumerate(keys)}, [str(b) for b in a["aps"]])


def write_recording_cache(path: str | Path, survey: Survey, keys: Mapping[str, str]) -> Path:
    """Write the cache of ``survey``'s walks whose file key ``keys`` holds (by session id)."""
    path = Path(path)
    walks: Sequence[Session] = [s for s in survey if s.session_id in keys]
    aps: dict[str, int] = {}
    read_ap: list[int] = []
    rssi: list[float] = []
    n_read: list[int] = []
    for s in walks:
        for sc in s.scans:
            r = sc.readings
            read_ap.extend(aps.setdefault(b, len(aps)) for b in r)
            rssi.extend(r.values())
            n_read.append(len(r))

    def off(sizes: Sequence[int]) -> NDArray[np.int64]:
        return np.concatenate([[0], np.cumsum(np.asarray(sizes, np.int64))]).astype(np.int64)

    def cat(parts: Sequence[NDArray], dtype: object, shape: tuple[int, ...] = ()) -> NDArray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros((0, *shape), dtype)

    gts = [s.ground_truth for s in walks if s.ground_truth is not None]
    hds = [s.heading for s in walks if s.heading is not None]
    mgs = [s.magnetic for s in walks if s.magnetic is not None]
    marks = [m for s in walks for m in s.landmarks]
    uwbs = [s.uwb_ranges for s in walks if s.uwb_ranges is not None]
    anchors = [(i, xyz) for s in walks for i, xyz in s.uwb_anchors.items()]
    arrays = {
        "format_version": np.int64(CACHE_FORMAT),
        "graphslam": np.array(graphslam.__version__),
        "key": np.array([keys[s.session_id] for s in walks], dtype=str).reshape(-1),
        "session_id": np.array([s.session_id for s in walks], dtype=str).reshape(-1),
        "stem": np.array([Path(s.source).stem for s in walks], dtype=str).reshape(-1),
        "site": np.array([s.site for s in walks], dtype=str).reshape(-1),
        "floor": np.array([s.floor for s in walks], dtype=str).reshape(-1),
        "uwb_id": np.array([s.uwb_id for s in walks], dtype=str).reshape(-1),
        "step_off": off([len(s.steps) for s in walks]),
        "step_t": cat([s.steps.t_ns for s in walks], np.int64),
        "step_xy": cat([s.steps.xy for s in walks], np.float64, (2,)),
        "step_h": cat([s.steps.heading for s in walks], np.float64),
        "gt_has": np.array([s.ground_truth is not None for s in walks], bool),
        "gt_off": off([len(s.ground_truth) if s.ground_truth is not None else 0 for s in walks]),
        "gt_t": cat([g.t_ns for g in gts], np.int64),
        "gt_xy": cat([g.xy for g in gts], np.float64, (2,)),
        "gt_h": cat([g.heading for g in gts], np.float64),
        "hd_has": np.array([s.heading is not None for s in walks], bool),
        "hd_off": off([len(s.heading) if s.heading is not None else 0 for s in walks]),
        "hd_t": cat([h.t_ns for h in hds], np.int64),
        "hd_yaw": cat([h.yaw for h in hds], np.float64),
        "mg_has": np.array([s.magnetic is not None for s in walks], bool),
        "mg_off": off([len(s.magnetic) if s.magnetic is not None else 0 for s in walks]),
        "mg_t": cat([m.t_ns for m in mgs], np.int64),
        "mg_enu": cat([m.enu for m in mgs], np.float64, (3,)),
        "lm_off": off([len(s.landmarks) for s in walks]),
        "lm_t": np.array([m.t_ns for m in marks], np.int64),
        "lm_id": np.array([m.landmark_id for m in marks], dtype=str).reshape(-1),
        "lm_x": np.array([m.x for m in marks], np.float64),
        "lm_y": np.array([m.y for m in marks], np.float64),
        "uwb_has": np.array([s.uwb_ranges is not None for s in walks], bool),
        "uwb_off": off([len(s.uwb_ranges) if s.uwb_ranges is not None else 0 for s in walks]),
        "uwb_t": cat([u.t_ns for u in uwbs], np.int64),
        "uwb_resp": np.array([r for u in uwbs for r in u.responder_id], dtype=str).reshape(-1),
        "uwb_anchor": cat([u.is_anchor for u in uwbs], bool),
        "uwb_m": cat([u.range_m for u in uwbs], np.float64),
        "anc_off": off([len(s.uwb_anchors) for s in walks]),
        "anc_id": np.array([i for i, _ in anchors], dtype=str).reshape(-1),
        "anc_xyz": np.array([(*xyz, np.nan)[:3] for _, xyz in anchors], np.float64).reshape(-1, 3),
        "anc_dim": np.array([len(xyz) for _, xyz in anchors], np.int64),
        "scan_off": off([len(s.scans) for s in walks]),
        "scan_t": np.array([sc.t_ns for s in walks for sc in s.scans], np.int64),
        "read_off": off(n_read),
        "read_ap": np.array(read_ap, np.int64),
        "rssi": np.array(rssi, np.float64),
        "aps": np.array(list(aps), dtype=str).reshape(-1),
    }
    with atomic_open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path
