"""Per component and walk: route label, landmark error (component's own SE(2) fit). Truth scores only.
python lab/survey/ap/diag.py FOLDER [key=value ...] [cp=FILE]"""
import sys, re, csv
import numpy as np
import graphslam as gs
from graphslam import component_errors

folder = sys.argv[1]
rest = sys.argv[2:]
cp = next((a[3:] for a in rest if a.startswith("cp=")), None)
over = {}
for kv in rest:
    if kv.startswith("cp="): continue
    k, v = kv.split("=", 1); a, b = k.split(".")
    try: v = float(v) if "." in v or "e" in v else int(v)
    except ValueError: v = {"true": True, "false": False}.get(v, v)
    over.setdefault(a, {})[b] = v
cfg = gs.load_config(overrides=over)
sv = gs.read_survey([folder])
cps = {r["landmark_id"]: (float(r["x"]), float(r["y"])) for r in csv.DictReader(open(cp))} if cp else None
al = gs.align(sv, cfg, control_points=cps)
def lab(sid):
    m = re.search(r"Trial(\d+)_repetition(\d+)", sid)
    return f"{m.group(1)}.{int(m.group(2))}" if m else sid[-6:]
for ce in component_errors(al, sv, site_frame=bool(cps)):
    per = ce.site_per_walk_mean_m if (cps and ce.index == 0) else ce.per_walk_mean_m
    w = sorted(per.items(), key=lambda kv: lab(kv[0]))
    mean = (ce.site.mean_m if (cps and ce.index == 0) else ce.landmarks.mean_m)
    print(f"comp {ce.index:2d} n={len(ce.walks):2d} mean {mean:5.2f}: " + " ".join(f"{lab(k)}:{v:.1f}" for k, v in w))
