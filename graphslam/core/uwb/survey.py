"""UWB in the survey: attach every range to step poses, place the walks, decide the frame.

``uwb_terms`` is the one entry point ``graphslam.core.survey.align`` calls (a marked hook):

- every ``/uwb/range`` of every session is attached to step nodes (``attach_ranges``; the
  stride model of ``motion``, factors of ``factors``);
- with ranges to anchors, the survey is solved in the **site frame**: the anchors fix it (no
  reference pose), and walks are placed window by window from the ranges
  (``initialise.place_windows``: anchors first, then peers), the rest by their WiFi edges to
  placed walks; a walk none of this reaches is unaligned;
- without anchors, the frame stays the reference walk's: the WiFi placement is kept and walks it
  could not place are placed by peer ranges to placed walks (walks that share no WiFi edge are
  joined by ranges).

Only ``steps``, ``uwb_*`` and the WiFi edges are read: never ground truth.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig, UwbConfig
from graphslam.core.types import Survey, wrap_angle
from graphslam.core.uwb.factors import SurveyRanges
from graphslam.core.uwb.initialise import RangeObservations, place_by_wifi, place_windows
from graphslam.core.uwb.motion import median_step_s, stride_fraction
from graphslam.core.uwb.nlos import chord_flags, reject_nlos
from graphslam.core.uwb.ranging import horizontal_range

log = logging.getLogger(__name__)


def _antenna(t_steps: NDArray, xy: NDArray, h: NDArray, t: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per range time: step k, the antenna in the dead-reckoning frame q, its body-frame offset from
    pose k, and the distance from q to the nearer of steps k, k+1 (with that step)."""
    move = median_step_s(t_steps)
    k, f = stride_fraction(t_steps, t, move)
    if len(t_steps) == 1:
        q = np.repeat(xy[:1], len(t), 0)
        return k, q, np.zeros((len(t), 2)), np.column_stack([np.zeros(len(t)), k])
    q = xy[k] + f[:, None] * (xy[k + 1] - xy[k])
    d = q - xy[k]
    c, s = np.cos(h[k]), np.sin(h[k])
    off = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    d0 = np.linalg.norm(q - xy[k], axis=1)
    d1 = np.linalg.norm(q - xy[k + 1], axis=1)
    near = np.where(d0 <= d1, k, k + 1)
    return k, q, off, np.column_stack([np.minimum(d0, d1), near])


def attach_ranges(
    survey: Survey, offsets: NDArray, cfg: UwbConfig
) -> tuple[SurveyRanges, RangeObservations] | None:
    """Factor inputs and placement inputs for every range of the survey (None: no ranges)."""
    sessions = survey.sessions
    if not any(s.uwb_ranges is not None and len(s.uwb_ranges) for s in sessions):
        return None
    anchors: dict[str, tuple[float, ...]] = {}
    for s in sessions:
        anchors.update(s.uwb_anchors)
    anchor_ids = tuple(sorted(anchors))
    a_index = {a: i for i, a in enumerate(anchor_ids)}
    anchor_xy = np.array([anchors[a][:2] for a in anchor_ids], float).reshape(-1, 2)
    anchor_dz = np.array([(anchors[a][2] - cfg.tag_height_m) if len(anchors[a]) == 3 else 0.0 for a in anchor_ids])
    by_tag = {s.uwb_id: i for i, s in enumerate(sessions) if s.uwb_id}
    t0 = min(int(s.steps.t_ns[0]) for s in sessions)
    dropped = {"anchor_below_min_horizontal": 0, "tag_not_in_survey": 0, "outside_walk": 0, "peer_off_step": 0}
    A: dict[str, list] = {k: [] for k in ("node", "anchor", "range", "sigma", "offset", "walk", "t", "q")}
    P: dict[str, list] = {k: [] for k in ("node", "range", "sigma", "offset", "walk", "t", "qa", "qb")}
    per_walk = [(s.steps.t_ns, s.steps.xy, s.steps.heading) for s in sessions]
    one_s = 1_000_000_000  # a range this far outside the walk's steps still belongs to it
    for i, s in enumerate(sessions):
        r = s.uwb_ranges
        if r is None or not len(r):
            continue
        t_steps, xy, h = per_walk[i]
        inside = (r.t_ns >= t_steps[0] - one_s) & (r.t_ns <= t_steps[-1] + one_s)
        dropped["outside_walk"] += int((~inside).sum())
        k, q, off, near = _antenna(t_steps, xy, h, r.t_ns)
        t_s = (r.t_ns - t0) / 1e9
        am = r.is_anchor & inside
        if am.any():
            ai = np.array([a_index[x] for x, m in zip(r.responder_id, am) if m], np.int64)
            rh, sh = horizontal_range(r.range_m[am], anchor_dz[ai], cfg.range_sigma_m)
            ok = np.isfinite(sh) & (rh >= cfg.min_horizontal_m)
            dropped["anchor_below_min_horizontal"] += int((~ok).sum())
            idx = np.flatnonzero(am)[ok]
            A["node"].append(offsets[i] + k[idx])
            A["anchor"].append(ai[ok])
            A["range"].append(rh[ok])
            A["sigma"].append(sh[ok])
            A["offset"].append(off[idx])
            A["walk"].append(np.full(len(idx), i))
            A["t"].append(t_s[idx])
            A["q"].append(q[idx])
        peer = np.flatnonzero(~r.is_anchor & inside)
        other = np.array([by_tag.get(r.responder_id[j], -1) for j in peer], np.int64)
        unknown = (other < 0) | (other == i)
        dropped["tag_not_in_survey"] += int(unknown.sum())
        for b in np.unique(other[~unknown]).tolist():  # one batch per responding walk
            tb, xyb, hb = per_walk[b]
            j = peer[other == b]
            live = (r.t_ns[j] >= tb[0] - one_s) & (r.t_ns[j] <= tb[-1] + one_s)
            dropped["outside_walk"] += int((~live).sum())
            j = j[live]
            if not len(j):
                continue
            kb, qb, offb, nearb = _antenna(tb, xyb, hb, r.t_ns[j])
            # the walker nearer one of its step poses takes the plain end, the other end is moved
            a_plain = near[j, 0] <= nearb[:, 0]
            gap = np.where(a_plain, near[j, 0], nearb[:, 0])
            plain = np.where(a_plain, offsets[i] + near[j, 1], offsets[b] + nearb[:, 1]).astype(np.int64)
            moved = np.where(a_plain, offsets[b] + kb, offsets[i] + k[j]).astype(np.int64)
            moved_off = np.where(a_plain[:, None], offb, off[j])
            ok = gap <= cfg.peer_max_offset_m
            dropped["peer_off_step"] += int((~ok).sum())
            P["node"].append(np.column_stack([moved, plain])[ok])
            P["range"].append(r.range_m[j][ok])
            P["sigma"].append(np.hypot(cfg.range_sigma_m, gap[ok]))
            P["offset"].append(moved_off[ok])
            P["walk"].append(np.column_stack([np.full(len(j), i), np.full(len(j), b)])[ok])
            P["t"].append(t_s[j][ok])
            P["qa"].append(q[j][ok])
            P["qb"].append(qb[ok])

    def cat(parts: list, shape: tuple[int, ...], dtype: type = float) -> NDArray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

    sr = SurveyRanges(
        anchor_ids, anchor_xy,
        cat(A["node"], (0,), np.int64), cat(A["anchor"], (0,), np.int64), cat(A["range"], (0,)),
        cat(A["sigma"], (0,)), cat(A["offset"], (0, 2)),
        cat(P["node"], (0, 2), np.int64), cat(P["range"], (0,)), cat(P["sigma"], (0,)), cat(P["offset"], (0, 2)),
        dropped,
    )
    obs = RangeObservations(
        cat(A["walk"], (0,), np.int64), cat(A["t"], (0,)), cat(A["q"], (0, 2)), sr.a_anchor, sr.a_range,
        cat(P["walk"], (0, 2), np.int64), cat(P["t"], (0,)), cat(P["qa"], (0, 2)), cat(P["qb"], (0, 2)), sr.p_range,
    )
    return sr, obs


@dataclass(frozen=True, eq=False)
class UwbTerms:
    """What the survey's graph gets from UWB (see the module docstring)."""

    ranges: SurveyRanges  # only ranges between walks in the graph
    site_frame: bool  # anchors fix the frame (no reference-pose prior)
    included: NDArray[np.bool_]
    unaligned: dict[str, str]
    init_xyh: NDArray[np.float64]  # (N, 3) initial poses of the walks UWB placed (NaN elsewhere)
    placed_by: dict[str, str] = field(default_factory=dict)  # session id -> anchors | ranges | wifi | registration

    @property
    def nodes(self) -> NDArray[np.int64]:
        return self.ranges.nodes

    def summary(self) -> "UwbSummary":
        r = self.ranges
        return UwbSummary(
            frame="site" if self.site_frame else "aligned",
            anchors=tuple(r.anchor_ids[a] for a in np.unique(r.a_anchor).tolist()) if self.site_frame else (),
            anchor_ranges=int(len(r.a_node)) if self.site_frame else 0,
            peer_ranges=int(len(r.p_node)),
            dropped=dict(r.dropped),
            placed_by=dict(self.placed_by),
        )


@dataclass(frozen=True)
class UwbSummary:
    frame: str
    anchors: tuple[str, ...]
    anchor_ranges: int
    peer_ranges: int
    dropped: dict[str, int]
    placed_by: dict[str, str]

    def as_dict(self) -> dict:
        counts: dict[str, int] = {}
        for how in self.placed_by.values():
            counts[how] = counts.get(how, 0) + 1
        return {
            "frame": self.frame, "anchors": list(self.anchors), "anchor_ranges": self.anchor_ranges,
            "peer_ranges": self.peer_ranges, "dropped": self.dropped, "walks_placed_by": counts,
        }


def uwb_terms(
    survey: Survey,
    cfg: GraphSlamConfig,
    offsets: NDArray[np.int64],
    wifi_a: NDArray[np.int64],
    wifi_b: NDArray[np.int64],
    included: NDArray[np.bool_],
    transforms: NDArray[np.float64],
    unaligned: dict[str, str],
) -> UwbTerms | None:
    """The UWB hook of the survey (None: no ranges, or ``uwb.enabled`` false). ``included``,
    ``transforms``, ``unaligned``: the WiFi placement, kept when there are no anchors."""
    if not cfg.uwb.enabled:
        return None
    att = attach_ranges(survey, offsets, cfg.uwb)
    if att is None:
        return None
    sr, obs = att
    sessions = survey.sessions
    n_s = len(sessions)
    t0 = min(int(s.steps.t_ns[0]) for s in sessions)
    span = np.array([[(s.steps.t_ns[0] - t0) / 1e9, (s.steps.t_ns[-1] - t0) / 1e9] for s in sessions])
    node_walk = np.repeat(np.arange(n_s), np.diff(offsets))
    node_t = np.concatenate([(s.steps.t_ns - t0) / 1e9 for s in sessions])
    node_xyh = np.concatenate([s.steps.xyh for s in sessions])
    site = len(sr.a_node) > 0
    if site:
        wp = place_windows(obs, sr.anchor_xy, span, cfg.uwb.window_s)
        anchored = [s for s in range(n_s) if wp.method[s] == "anchors"]  # a window saw >= 2 anchors
        used = np.unique(obs.a_anchor[np.isin(obs.a_walk, anchored)])
        site = len(anchored) > 0 and len(used) >= 2
    if site:
        place_by_wifi(wp, node_walk, node_t, node_xyh[:, :2], wifi_a, wifi_b)
        reason = "no anchor, peer-range or WiFi link places it in the site frame"
    else:  # no anchors to speak of: the reference walk's frame; ranges join what WiFi could not
        base = {int(s): transforms[s] for s in np.flatnonzero(included)}
        peers_only = RangeObservations(
            obs.a_walk[:0], obs.a_t[:0], obs.a_q[:0], obs.a_anchor[:0], obs.a_range[:0],
            obs.p_walk, obs.p_t, obs.p_qa, obs.p_qb, obs.p_range,
        )
        wp = place_windows(peers_only, sr.anchor_xy, span, cfg.uwb.window_s, base=base)
        reason = unaligned
    inc = np.array([wp.placed(s) for s in range(n_s)])
    unal = {}
    for s in np.flatnonzero(~inc).tolist():
        sid = sessions[s].session_id
        unal[sid] = reason if isinstance(reason, str) else reason.get(sid, "no WiFi edge or peer range to a placed walk")
    init = np.full((len(node_walk), 3), np.nan)
    for s in np.flatnonzero(inc).tolist():
        a, b = int(offsets[s]), int(offsets[s + 1])
        T = wp.transform_at(s, node_t[a:b])
        init[a:b, :2] = wp.apply(s, node_t[a:b], node_xyh[a:b, :2])
        init[a:b, 2] = wrap_angle(node_xyh[a:b, 2] + T[:, 2])
    ranges = sr.select(inc[node_walk])
    too_long = None
    if cfg.uwb.nlos_chord_prefilter:  # the ranges the dead reckoning alone proves too long
        fa, fp = chord_flags(sr, obs.a_walk, obs.a_t, obs.a_q, obs.p_walk, obs.p_t, obs.p_qa, obs.p_qb, node_walk, cfg.uwb)
        ka = inc[node_walk][sr.a_node]
        kp = inc[node_walk][sr.p_node].all(axis=1) if len(sr.p_node) else np.zeros(0, bool)
        too_long = (fa[ka], fp[kp])
    if not site:  # anchor ranges cannot enter a graph whose frame is a walk's
        ranges = ranges.subset(np.zeros(len(ranges.a_node), bool), np.ones(len(ranges.p_node), bool))
        if too_long is not None:
            too_long = (np.zeros(0, bool), too_long[1])
    gauge = None if site else next((int(offsets[s]) for s in range(n_s) if wp.method[s] == "registration"), None)
    nl = reject_nlos(survey, offsets, inc, init, ranges, cfg, site_frame=site, gauge_node=gauge, too_long=too_long)
    ranges = ranges.subset(nl.keep_anchor, nl.keep_peer)
    ranges.dropped["nlos_anchor"] = int((~nl.keep_anchor).sum()) if site else 0
    ranges.dropped["nlos_peer"] = int((~nl.keep_peer).sum())
    init = np.where(np.isfinite(nl.xyh), nl.xyh, init)
    placed_by = {sessions[s].session_id: wp.method[s] for s in np.flatnonzero(inc).tolist()}
    log.info(
        "UWB: %s frame, %d anchor and %d peer ranges, walks placed: %s", "site" if site else "reference-walk",
        len(ranges.a_node), len(ranges.p_node), placed_by,
    )
    return UwbTerms(ranges, site, inc, unal, init, placed_by)
