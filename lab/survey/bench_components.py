"""Per floor: components of `align` (product config + --set overrides), each with its own SE(2) fit.
python lab/survey/bench_components.py FOLDER [key=value ...] [cp=FILE] [noLM]"""
import sys, time, csv
import numpy as np
import graphslam as gs
from graphslam import landmark_errors, landmark_marks as _marks
from graphslam import build_problem, solve_problem as solve
from graphslam import PoseTrack
from graphslam import se2_apply


def parse(v):
    for f in (int, float):
        try:
            return f(v)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(v, v)


def run(folder, sets, cp_file=None, lm=True, quiet=False):
    over = {}
    for kv in sets:
        k, v = kv.split("=", 1)
        a, b = k.split(".")
        over.setdefault(a, {})[b] = parse(v)
    cfg = gs.load_config(overrides=over)
    sv = gs.read_survey([folder])
    cps = None
    if cp_file:
        cps = {r["landmark_id"]: (float(r["x"]), float(r["y"])) for r in csv.DictReader(open(cp_file))}
    t0 = time.time()
    prob = build_problem(sv, cfg, control_points=cps)
    if lm:
        al = solve(prob, cfg)
        tracks = al.tracks
        comps = al.components
    else:
        tracks = {}
        for s, sess in enumerate(sv):
            if prob.included[s]:
                T = prob.placement.transforms[s]
                tracks[sess.session_id] = PoseTrack(sess.steps.t_ns, se2_apply(T, sess.steps.xy), sess.steps.heading + T[2])
        from graphslam import Component
        comps = prob.components
    dt = time.time() - t0
    rows = []
    over10 = 0
    for c in comps:
        tr = {k: tracks[k] for k in c.walks if k in tracks}
        st, T, per = landmark_errors(tr, sv)
        if c.index == 0 and cps:
            est, true, owner = _marks(tr, sv)
            e = np.linalg.norm(est - true, axis=1)
            site = float(e.mean()) if len(e) else float("nan")
            per = {sid: float(e[owner == sid].mean()) for sid in dict.fromkeys(owner)}
        else:
            site = None
        bad = sum(v > 10 for v in per.values())
        over10 += bad
        rows.append((c.index, len(c.walks), st.mean_m, site, bad))
    n = len(sv.sessions)
    main = rows[0]
    big = [r for r in rows if r[1] >= 5]
    nb = sum(r[1] for r in big)
    wmean = sum(r[1] * r[2] for r in big) / max(nb, 1)
    out = dict(floor=folder.rstrip("/").split("/")[-1], walks=n, main=main[1], main_frac=round(main[1] / n, 3),
               main_mean_m=round(main[2], 2), main_site_mean_m=None if main[3] is None else round(main[3], 2),
               in_comp5=nb, comp5_frac=round(nb / n, 3), comp5_wmean_m=round(wmean, 2), over10=over10,
               components=len(rows), time_s=round(dt, 2))
    if not quiet:
        for r in rows[:8]:
            print("   comp", r)
    return out


if __name__ == "__main__":
    folder = sys.argv[1]
    rest = sys.argv[2:]
    cp = next((a[3:] for a in rest if a.startswith("cp=")), None)
    lm = "noLM" not in rest
    sets = [a for a in rest if "=" in a and not a.startswith("cp=")]
    print(run(folder, sets, cp, lm))
