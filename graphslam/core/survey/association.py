"""Scan-to-step association: which step pose each WiFi fingerprint belongs to.

Scheme (as the paper's ref. [9]: a fingerprint is attached to the pose at which
it was recorded): each scan goes to the step whose timestamp is nearest. Steps come
every ~0.5 s, so the attachment error is at most half a step (~0.35 m).

A scan further than ``max_gap_s`` from every step was recorded while the walker stood
still: in a pause between steps k and k + 1 the foot module last put the foot down at
step k, so that is where the walker stands; before the first step it stands at the
first, after the last at the last. Such a scan is attached there when the pause (or the
time to the first / from the last step) is at most ``standstill_max_s``, otherwise it is
dropped (its position is not known). IPIN 2023 walkers stand 10-43 s at some points:
309 of the 310 scans the nearest-step rule drops on floor -2 lie in such pauses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.types import Survey


@dataclass(frozen=True, eq=False)
class FingerprintNodes:
    """The survey's fingerprints, each tied to one step node.

    Step nodes are numbered globally: session ``s`` owns nodes
    ``offsets[s] .. offsets[s + 1] - 1`` in step order.
    """

    fingerprints: FingerprintMatrix
    session: NDArray[np.int64]  # (F,) session index
    step: NDArray[np.int64]  # (F,) step index within its session
    scan: NDArray[np.int64]  # (F,) scan index within its session
    node: NDArray[np.int64]  # (F,) global node index
    t_ns: NDArray[np.int64]  # (F,) scan time
    path_m: NDArray[np.float64]  # (F,) distance walked along its session (dead reckoning) at that step
    offsets: NDArray[np.int64]  # (S + 1,) first global node index of each session
    dropped: int  # scans that could not be associated
    standstill: int = 0  # scans attached to a pose where the walker stood still

    def __len__(self) -> int:
        return len(self.node)


def associate(
    survey: Survey,
    *,
    max_gap_s: float = 1.5,
    missing_dbm: float = -110.0,
    min_rssi_dbm: float = -100.0,
    standstill_max_s: float = 0.0,
) -> FingerprintNodes:
    """Attach every scan of every session to its nearest step in time."""
    sizes = np.array([len(s.steps) for s in survey], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    max_gap = int(max_gap_s * 1e9)
    max_still = int(standstill_max_s * 1e9)
    scans, sess, step, scan_idx, t_all, path = [], [], [], [], [], []
    dropped = still = 0
    for si, s in enumerate(survey):
        if not s.scans:
            continue
        t_steps = s.steps.t_ns
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(s.steps.xy, axis=0), axis=1))])
        t_scan = np.array([sc.t_ns for sc in s.scans], dtype=np.int64)
        j = np.clip(np.searchsorted(t_steps, t_scan), 1, max(1, len(t_steps) - 1))
        if len(t_steps) == 1:
            near = np.zeros_like(t_scan)
        else:
            left, right = t_steps[j - 1], t_steps[j]
            near = np.where(np.abs(t_scan - left) <= np.abs(right - t_scan), j - 1, j)
        ok = np.abs(t_steps[near] - t_scan) <= max_gap
        if max_still > 0:
            near, standing = _standstill(t_steps, t_scan, near, ok, max_still)
            still += int(standing.sum())
            ok |= standing
        ok &= np.array([len(sc.readings) > 0 for sc in s.scans])
        dropped += int((~ok).sum())
        for k in np.flatnonzero(ok):
            scans.append(s.scans[k].readings)
        sess.append(np.full(ok.sum(), si, np.int64))
        step.append(near[ok])
        scan_idx.append(np.flatnonzero(ok))
        t_all.append(t_scan[ok])
        path.append(cum[near[ok]])
    fp = FingerprintMatrix.from_scans(scans, missing_dbm=missing_dbm, min_rssi_dbm=min_rssi_dbm)
    cat = lambda parts, dt: np.concatenate(parts).astype(dt) if parts else np.zeros(0, dt)  # noqa: E731
    session = cat(sess, np.int64)
    stp = cat(step, np.int64)
    return FingerprintNodes(
        fingerprints=fp,
        session=session,
        step=stp,
        scan=cat(scan_idx, np.int64),
        node=offsets[session] + stp if len(session) else np.zeros(0, np.int64),
        t_ns=cat(t_all, np.int64),
        path_m=cat(path, np.float64),
        offsets=offsets,
        dropped=dropped,
        standstill=still,
    )


def _standstill(
    t_steps: NDArray[np.int64], t_scan: NDArray[np.int64], near: NDArray[np.int64], ok: NDArray[np.bool_], max_still: int
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """(step per scan, scans attached as standing still): see the module docstring."""
    k = np.searchsorted(t_steps, t_scan, side="right") - 1  # last step at or before the scan (-1: none)
    last = len(t_steps) - 1
    before = k < 0
    after = k >= last
    inside = ~before & ~after
    kk = np.clip(k, 0, last)
    pause = np.where(inside, t_steps[np.minimum(kk + 1, last)] - t_steps[kk], 0)
    standing = ~ok & (
        (before & (t_steps[0] - t_scan <= max_still))
        | (after & (t_scan - t_steps[last] <= max_still))
        | (inside & (pause <= max_still))
    )
    at = np.where(before, 0, kk)
    return np.where(standing, at, near), standing
