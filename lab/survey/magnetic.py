"""The magnetic field and the reference map on real floors: what the survey's links and placements are
worth, scored against the landmarks (ground truth only scores; it never reaches a solver).

    python lab/survey/magnetic.py links FOLDER [key=value ...]    # magnetic links: right or wrong, pair precision
    python lab/survey/magnetic.py recall FOLDER [K]               # the WiFi-anchored search (K anchors) against all pairs
    python lab/survey/magnetic.py null FOLDER                     # real vs surrogate match rates per threshold
    python lab/survey/magnetic.py survey FOLDER [cp] [ref] [key=value ...]   # the product survey per component

``key=value``: ``magnetic.*`` settings (``links``) or any ``section.key`` of the configuration (``survey``);
``cp``: with the folder's control_points.csv; ``ref``: the folder's reference_map.csv held, the crowd being
every walk whose scans it does not hold verbatim.

Truth per step: each walk's dead reckoning between consecutive landmarks mapped by the two-point similarity
that puts its ends on the marks (``piecewise_truth``; ~1 m).
"""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import numpy as np

import graphslam as gs
from graphslam import (
    GrowthParams, PowerCosine, SurveyInputs, associate, component_errors, interpolate_xy, load_config,
    parse_overrides, run_survey, survey_magnetic as M, walk_headings,
)


def piecewise_truth(sess: gs.Session) -> np.ndarray:
    """Per step: the dead reckoning between consecutive landmarks mapped onto them (NaN without two marks)."""
    st = sess.steps
    xy = np.asarray(st.xy)
    out = np.full_like(xy, np.nan)
    if len(sess.landmarks) < 2:
        return out
    t = np.array([m.t_ns for m in sess.landmarks], float)
    true = np.array([[m.x, m.y] for m in sess.landmarks])
    t, u = np.unique(t, return_index=True)
    true = true[u]
    est = interpolate_xy(st, t)
    seg = np.clip(np.searchsorted(t, st.t_ns.astype(float)) - 1, 0, len(t) - 2)
    for k in range(len(t) - 1):
        dp, dq = complex(*(est[k + 1] - est[k])), complex(*(true[k + 1] - true[k]))
        a = dq / dp if abs(dp) > 1e-3 else 1.0 + 0j
        if abs(a) < 1e-6:
            a = 1.0 + 0j
        elif abs(abs(a) - 1) > 0.5:  # a standstill between marks or a bad mark: rigid
            a = a / abs(a)
        m = seg == k
        z = (xy[m, 0] - est[k, 0]) + 1j * (xy[m, 1] - est[k, 1])
        w = a * z + complex(*true[k])
        out[m] = np.column_stack([w.real, w.imag])
    return out


def short(sid: str) -> str:
    m = re.search(r"Trial(\d+)_repetition0?(\d+)(_s\d)?", sid)
    return f"{m.group(1)}.{m.group(2)}{m.group(3) or ''}" if m else sid[-8:]


def _setup(folder: str, k: int = 5) -> tuple:
    survey = gs.read_survey([folder])
    fp = associate(survey, max_gap_s=1.5, missing_dbm=-110, min_rssi_dbm=-100, standstill_max_s=120)
    mt = PowerCosine.of(fp.fingerprints, 10.0).top_matches(fp.session, k)
    rot = walk_headings(survey, sigma_floor_rad=np.radians(25.0)).rotation
    truth = np.concatenate([piecewise_truth(s) for s in survey])
    return survey, fp, mt, rot, truth


def cmd_links(folder: str, kv: list[str]) -> None:
    p = M.MagneticParams(**{k: type(getattr(M.MagneticParams, k))(v) for k, v in (a.split("=") for a in kv)})
    survey, fp, mt, rot, truth = _setup(folder)
    t0 = time.perf_counter()
    links = M.magnetic_links(survey, fp.offsets, rot, fp.node[mt.i], fp.node[mt.j], p)
    dt = time.perf_counter() - t0
    e = np.linalg.norm(truth[links.pair_nodes[:, 0]] - truth[links.pair_nodes[:, 1]], axis=1)
    ids = [short(s.session_id) for s in survey]
    right = 0
    for k in range(len(links)):
        med = float(np.nanmedian(e[links.pair_link == k]))
        right += med < 3.0
        print(f"  {ids[links.a[k]]:>10} {ids[links.b[k]]:>10}  windows {links.windows[k]}  pairs' truth gap "
              f"{med:.2f} m {'' if med < 3.0 else 'WRONG'}")
    print(f"{Path(folder).name}: threshold {links.threshold:.3f}, {links.matches} window matches, {len(links)} links, "
          f"{right} right (< 3 m); node pairs {len(e)}: truth gap median {np.nanmedian(e):.2f} m, "
          f"within 1.5 m {np.nanmean(e < 1.5):.3f}; {dt:.2f} s")


def _all_pairs(seq: object, win: object, p: object) -> object:
    """Every (window, other walk)'s best match over all of the other walk (no anchors): the reference
    the anchored search is measured against."""
    n = len(seq.features)
    anchors_a, anchors_b = [], []
    for w, i in zip(win.walk, win.start):
        c = i + p.window // 2
        for b in range(seq.n_walks):
            if b == w:
                continue
            lo, hi = int(seq.offsets[b]), int(seq.offsets[b + 1])
            for j in range(lo, hi, max(1, p.search)):
                anchors_a.append(c)
                anchors_b.append(j)
    return M.window_matches(seq, win, p, np.array(anchors_a, np.int64), np.array(anchors_b, np.int64))


def cmd_recall(folder: str, k: int) -> None:
    """Share of the right window matches an all-pairs search finds that the WiFi-anchored one keeps (each
    fingerprint's ``k`` most similar of other walks as anchors)."""
    survey, fp, mt, rot, truth = _setup(folder, k)
    p = M.MagneticParams()
    seq = M.walk_sequences(survey, fp.offsets, p.sample_m)
    win = M.windows(seq, p)
    aa, ab = M.fingerprint_anchors(seq, fp.node[mt.i], fp.node[mt.j])
    thr = M.null_threshold(seq, win, p, aa, ab)
    anchored = M.window_matches(seq, win, p, aa, ab)
    full = _all_pairs(seq, win, p)

    def right(m: object) -> set:
        a = seq.node[win.start[m.window] + p.window // 2]
        b = seq.node[m.start + p.window // 2]
        ok = (m.score >= thr) & (np.linalg.norm(truth[a] - truth[b], axis=1) < 1.5)
        return set(zip(m.window[ok].tolist(), m.other[ok].tolist()))

    rf, ra = right(full), right(anchored)
    print(f"{Path(folder).name}: {k} anchors per fingerprint: right matches above {thr:.3f}: all pairs {len(rf)}, "
          f"anchored {len(ra)}, kept {len(rf & ra) / max(len(rf), 1):.3f}; comparisons {len(M.anchored_windows(seq, win, p, aa, ab)[0])}")


def cmd_null(folder: str) -> None:
    """Share of windows whose best match beats a threshold, on the walks and on surrogates of them."""
    survey, fp, mt, rot, truth = _setup(folder)
    p = M.MagneticParams()
    seq = M.walk_sequences(survey, fp.offsets, p.sample_m)
    win = M.windows(seq, p)
    aa, ab = M.fingerprint_anchors(seq, fp.node[mt.i], fp.node[mt.j])
    real = M.window_matches(seq, win, p, aa, ab)
    fake = [M.window_matches(seq, win, p, aa, ab, features=M.surrogates(seq, np.random.default_rng(k))) for k in range(4)]
    for thr in (0.8, 0.85, 0.9, 0.94):
        print(f"{Path(folder).name}: score >= {thr}: real {np.mean(real.score >= thr):.4f}, surrogates "
              f"{np.mean([np.mean(f.score >= thr) for f in fake]):.4f}")


def cmd_survey(folder: str, args: list[str]) -> None:
    sets = [a for a in args if "=" in a]
    cfg = load_config(None, parse_overrides(sets)) if sets else load_config()
    cp = str(Path(folder) / "control_points.csv") if "cp" in args else None
    ref = str(Path(folder) / "reference_map.csv") if "ref" in args else None
    paths = [folder]
    if ref is not None:
        paths = [str(p) for p in gs.crowd_walks(Path(folder), Path(ref))]
    t = time.perf_counter()
    r = run_survey(SurveyInputs.from_paths(paths, control_points=cp, reference_map=ref, picture=False), cfg)
    dt = time.perf_counter() - t
    al = r.alignment
    comps = component_errors(al, r.survey, site_frame=al.frame == "site")
    per = {}
    for c in comps:
        per.update(c.site_per_walk_mean_m if c.site_per_walk_mean_m is not None else c.per_walk_mean_m)
    big = [c for c in comps if len(c.walks) >= 4]
    scored = [c for c in big if c.landmarks.n]
    n4 = sum(len(c.walks) for c in big)
    w = sum(len(c.walks) for c in scored)
    m4 = sum(len(c.walks) * c.landmarks.mean_m for c in scored) / w if w else float("nan")
    print(f"{Path(folder).name} (cp {cp is not None}, ref {ref is not None}): {len(r.survey)} walks, "
          f"{n4} in components of >= 4 at {m4:.2f} m; worst walk {max(per.values()):.1f} m, over 6 m "
          f"{sum(v > 6 for v in per.values())}, over 10 m {sum(v > 10 for v in per.values())}; {dt:.2f} s")
    for c in comps:
        if len(c.walks) > 1:
            site = f", site frame {c.site.mean_m:.2f} m with no fit" if c.site is not None else ""
            print(f"  component {c.index}: {len(c.walks)} walks, {c.landmarks.mean_m:.2f} m (own fit){site}: "
                  + " ".join(sorted(short(s) for s in c.walks)))


def main(argv: list[str]) -> None:
    if len(argv) < 2 or argv[0] not in ("links", "recall", "null", "survey"):
        print(__doc__)
        sys.exit(0 if argv and argv[0] in ("-h", "--help") else 2)
    cmd, folder, rest = argv[0], argv[1], argv[2:]
    {"links": lambda: cmd_links(folder, rest), "recall": lambda: cmd_recall(folder, int(rest[0]) if rest else 5),
     "null": lambda: cmd_null(folder),
     "survey": lambda: cmd_survey(folder, rest)}[cmd]()


if __name__ == "__main__":
    main(sys.argv[1:])
