"""Evaluation against ground truth (landmarks, true poses). Never called by the solver.

Landmark error: each landmark mark (time t, surveyed x, y) is compared with the
walk's pose at t (linear interpolation between steps) after one SE(2) fit of all
estimated mark positions onto the surveyed ones: the aligned frame is the
reference walk's, so only its relation to the site frame is fitted, once for all
walks. A survey split into components (``Alignment.components``, each in a frame of its
own) is scored per component by ``component_errors``: one fit per component, and for a
component 0 in the site frame (control points) also the error with no fit.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.common.geometry import fit_se2, interpolate_xy, se2_apply  # noqa: F401 (interpolate_xy re-exported)
from graphslam.core.types import PoseTrack, Survey, wrap_angle

if TYPE_CHECKING:
    from graphslam.core.survey.align import Alignment

HIST_BIN_M = 0.5


@dataclass(frozen=True)
class ErrorStats:
    n: int
    mean_m: float
    median_m: float
    p90_m: float
    max_m: float
    std_m: float
    histogram: tuple[tuple[float, int], ...]  # (bin start m, count), bins of HIST_BIN_M (the paper's fig. 7)

    @classmethod
    def of(cls, e: NDArray) -> "ErrorStats":
        e = np.asarray(e, dtype=float)
        if e.size == 0:
            return cls(0, float("nan"), float("nan"), float("nan"), float("nan"), float("nan"), ())
        edges = np.arange(0.0, np.ceil(e.max() / HIST_BIN_M + 1) * HIST_BIN_M, HIST_BIN_M)
        counts, _ = np.histogram(e, bins=edges)
        return cls(
            int(e.size),
            float(e.mean()),
            float(np.median(e)),
            float(np.percentile(e, 90)),
            float(e.max()),
            float(e.std()),
            tuple((round(float(b), 3), int(c)) for b, c in zip(edges[:-1], counts)),
        )

    def as_dict(self) -> dict:
        d = asdict(self)
        d["histogram"] = [list(x) for x in self.histogram]
        return d


def _marks(sessions: Mapping[str, PoseTrack], survey: Survey) -> tuple[NDArray, NDArray, NDArray]:
    est, true, owner = [], [], []
    for s in survey:
        if s.session_id not in sessions or not s.landmarks:
            continue
        t = np.array([m.t_ns for m in s.landmarks], dtype=float)
        est.append(interpolate_xy(sessions[s.session_id], t))
        true.append(np.array([[m.x, m.y] for m in s.landmarks]))
        owner += [s.session_id] * len(t)
    if not est:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=object)
    return np.concatenate(est), np.concatenate(true), np.array(owner, dtype=object)


def landmark_errors(tracks: Mapping[str, PoseTrack], survey: Survey) -> tuple[ErrorStats, NDArray, dict[str, float]]:
    """(stats, SE(2) site-from-aligned transform, mean error per walk) after one global fit."""
    est, true, owner = _marks(tracks, survey)
    if len(est) < 2:
        return ErrorStats.of(np.zeros(0)), np.zeros(3), {}
    T = fit_se2(est, true)
    e = np.linalg.norm(se2_apply(T, est) - true, axis=1)
    per = {sid: float(e[owner == sid].mean()) for sid in dict.fromkeys(owner)}
    return ErrorStats.of(e), T, per


def raw_landmark_errors(survey: Survey) -> ErrorStats:
    """Raw dead reckoning: each walk placed at its true start pose (needs ground truth), no correction."""
    errs = []
    for s in survey:
        if s.ground_truth is None or not s.landmarks:
            continue
        g = s.ground_truth
        T = np.array([g.xy[0, 0], g.xy[0, 1], g.heading[0] - s.steps.heading[0]])
        T[:2] -= se2_apply(np.array([0.0, 0.0, T[2]]), s.steps.xy[:1])[0]
        placed = PoseTrack(s.steps.t_ns, se2_apply(T, s.steps.xy), s.steps.heading + T[2])
        est, true, _ = _marks({s.session_id: placed}, Survey((s,)))
        errs.append(np.linalg.norm(est - true, axis=1))
    return ErrorStats.of(np.concatenate(errs) if errs else np.zeros(0))


def per_walk_rigid_errors(survey: Survey) -> ErrorStats:
    """Oracle bound on drift alone: each walk's dead reckoning rigidly fitted to its own landmarks."""
    errs = []
    for s in survey:
        if len(s.landmarks) < 2:
            continue
        est, true, _ = _marks({s.session_id: s.steps}, Survey((s,)))
        T = fit_se2(est, true)
        errs.append(np.linalg.norm(se2_apply(T, est) - true, axis=1))
    return ErrorStats.of(np.concatenate(errs) if errs else np.zeros(0))


def truth_at(truth: PoseTrack, t_ns: NDArray) -> tuple[NDArray, NDArray]:
    """True (xy, heading) at times ``t_ns``: ground truth may be logged at its own rate."""
    t = truth.t_ns.astype(float)
    h = np.interp(t_ns, t, np.unwrap(truth.heading))
    return interpolate_xy(truth, t_ns), h


def heading_alignment_errors(tracks: Mapping[str, PoseTrack], survey: Survey, T: NDArray) -> dict[str, float]:
    """Per walk: mean |heading error| in degrees vs the true poses, after the global fit ``T``."""
    out = {}
    for s in survey:
        if s.session_id not in tracks or s.ground_truth is None:
            continue
        a = tracks[s.session_id]
        _, true_h = truth_at(s.ground_truth, a.t_ns.astype(float))
        err = wrap_angle(a.heading + T[2] - true_h)
        # the mean heading offset of the walk: what alignment got wrong, not per-step noise
        off = float(np.degrees(np.abs(np.arctan2(np.sin(err).mean(), np.cos(err).mean()))))
        out[s.session_id] = off
    return out


def trajectory_errors(tracks: Mapping[str, PoseTrack], survey: Survey, T: NDArray) -> ErrorStats:
    """Position error of every step vs the true pose (simulations), after the global fit ``T``."""
    errs = []
    for s in survey:
        if s.session_id in tracks and s.ground_truth is not None:
            tr = tracks[s.session_id]
            true_xy, _ = truth_at(s.ground_truth, tr.t_ns.astype(float))
            errs.append(np.linalg.norm(se2_apply(T, tr.xy) - true_xy, axis=1))
    return ErrorStats.of(np.concatenate(errs) if errs else np.zeros(0))


@dataclass(frozen=True)
class Evaluation:
    landmarks: ErrorStats
    landmarks_raw: ErrorStats  # dead reckoning placed at the true start pose
    landmarks_per_walk_fit: ErrorStats  # oracle: each walk rigidly fitted to its own landmarks
    steps: ErrorStats  # every step vs ground truth pose (simulations)
    heading_deg: dict[str, float]
    heading_mean_deg: float
    per_walk_mean_m: dict[str, float]
    site_from_aligned: tuple[float, float, float]

    def as_dict(self) -> dict:
        return {
            "landmarks": self.landmarks.as_dict(),
            "landmarks_raw": self.landmarks_raw.as_dict(),
            "landmarks_per_walk_fit": self.landmarks_per_walk_fit.as_dict(),
            "steps": self.steps.as_dict(),
            "heading_mean_deg": self.heading_mean_deg,
            "heading_deg": self.heading_deg,
            "per_walk_mean_m": self.per_walk_mean_m,
            "site_from_aligned": list(self.site_from_aligned),
        }


def evaluate(tracks: Mapping[str, PoseTrack], survey: Survey) -> Evaluation:
    """Every figure we report against ground truth, for whatever ground truth the survey has."""
    lm, T, per = landmark_errors(tracks, survey)
    if lm.n < 2:
        # no landmarks: fit on true step poses instead (simulation without marks)
        src, dst = [], []
        for s in survey:
            if s.session_id in tracks and s.ground_truth is not None:
                src.append(tracks[s.session_id].xy)
                dst.append(truth_at(s.ground_truth, tracks[s.session_id].t_ns.astype(float))[0])
        if src:
            T = fit_se2(np.concatenate(src), np.concatenate(dst))
    heading = heading_alignment_errors(tracks, survey, T)
    return Evaluation(
        landmarks=lm,
        landmarks_raw=raw_landmark_errors(survey),
        landmarks_per_walk_fit=per_walk_rigid_errors(survey),
        steps=trajectory_errors(tracks, survey, T),
        heading_deg=heading,
        heading_mean_deg=float(np.mean(list(heading.values()))) if heading else float("nan"),
        per_walk_mean_m=per,
        site_from_aligned=(float(T[0]), float(T[1]), float(T[2])),
    )




WALK_OVER_M = 10.0  # ``walks_over_10m``: a walk whose mean landmark error exceeds this is counted


@dataclass(frozen=True)
class ComponentErrors:
    """Landmark errors of one component of an alignment (``component_errors``).

    ``landmarks``: after one SE(2) fit of the component's walks onto the surveyed landmark
    positions (n = 0 and no fit when the component's walks mark fewer than 2 landmarks);
    ``per_walk_mean_m`` and ``walks_over_10m`` (walks whose mean error exceeds ``WALK_OVER_M``)
    after that fit. ``site`` / ``site_per_walk_mean_m`` / ``site_walks_over_10m``: component 0 in
    the site frame, no fit (None otherwise)."""

    index: int
    walks: tuple[str, ...]
    landmarks: ErrorStats
    per_walk_mean_m: dict[str, float]
    walks_over_10m: int
    site_from_component: tuple[float, float, float] | None  # the fit; None: no fit
    site: ErrorStats | None = None
    site_per_walk_mean_m: dict[str, float] | None = None
    site_walks_over_10m: int | None = None

    def as_dict(self) -> dict:
        """report.json's ``evaluation.components[i]`` (NaN and no fit: null)."""
        lm = self.landmarks
        fitted = lm.n > 0

        def num(v: float) -> float | None:
            return float(v) if fitted and np.isfinite(v) else None

        d: dict = {
            "index": self.index,
            "walks": len(self.walks),
            "n": lm.n,
            "mean_m": num(lm.mean_m),
            "p90_m": num(lm.p90_m),
            "max_m": num(lm.max_m),
            "walks_over_10m": self.walks_over_10m,
            "per_walk_mean_m": self.per_walk_mean_m,
            "site_from_component": None if self.site_from_component is None else list(self.site_from_component),
        }
        if self.site is not None:
            s = self.site
            d.update({
                "site_n": s.n,
                "site_mean_m": float(s.mean_m) if s.n else None,
                "site_p90_m": float(s.p90_m) if s.n else None,
                "site_max_m": float(s.max_m) if s.n else None,
                "site_walks_over_10m": self.site_walks_over_10m,
                "site_per_walk_mean_m": self.site_per_walk_mean_m,
            })
        return d


def component_errors(alignment: "Alignment", survey: Survey, site_frame: bool) -> list[ComponentErrors]:
    """Per component of ``alignment`` (a ``graphslam.core.survey.align.Alignment``; component 0
    first): landmark errors after one SE(2) fit of that component's walks (each component stands
    in a frame of its own), per-walk means and the walks over ``WALK_OVER_M``; with ``site_frame``
    (component 0 is in the site frame, the landmarks' frame: control points, UWB anchors) also
    component 0's errors with no fit. Evaluation only: the solver never calls it."""
    out = []
    for c in alignment.components:
        tracks = {sid: alignment.tracks[sid] for sid in c.walks if sid in alignment.tracks}
        lm, T, per = landmark_errors(tracks, survey)
        row = ComponentErrors(
            index=c.index,
            walks=tuple(c.walks),
            landmarks=lm,
            per_walk_mean_m=per,
            walks_over_10m=_over(per),
            site_from_component=(float(T[0]), float(T[1]), float(T[2])) if lm.n else None,
        )
        if site_frame and c.index == 0:
            est, true, owner = _marks(tracks, survey)
            e = np.linalg.norm(est - true, axis=1)
            site_per = {sid: float(e[owner == sid].mean()) for sid in dict.fromkeys(owner)}
            row = replace(row, site=ErrorStats.of(e), site_per_walk_mean_m=site_per, site_walks_over_10m=_over(site_per))
        out.append(row)
    return out


def _over(per_walk: Mapping[str, float]) -> int:
    return int(sum(v > WALK_OVER_M for v in per_walk.values()))
