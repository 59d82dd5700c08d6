"""UJIIndoorLoc: quick kNN variants in plain numpy (validation set = queries; never used to choose on
its own... this script prints every variant so the choice is visible)."""
import sys, time
import numpy as np
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[2]))  # the repository root: lab.bench
from lab.bench.ujiindoorloc import read_ujiindoorloc

D = "../shared/data/ujiindoorloc/"
tr = read_ujiindoorloc(D + "trainingData.csv.gz"); te = read_ujiindoorloc(D + "validationData.csv.gz")
def powed(r, e=np.e, floor=-104.0):
    v = np.where(np.isfinite(r), r - floor, 0.0); v = np.clip(v, 0, None)
    return (v / -floor) ** e
Ptr, Pte = powed(tr.rssi), powed(te.rssi)
def soren(Q, R):
    # 1 - 2 sum min / (sum q + sum r), in blocks
    out = np.empty((len(Q), len(R)), np.float32)
    sr = R.sum(1)
    for a in range(0, len(Q), 64):
        q = Q[a:a+64]
        mins = np.minimum(q[:, None, :], R[None]).sum(-1)
        out[a:a+64] = 1 - 2 * mins / (q.sum(1)[:, None] + sr[None] + 1e-12)
    return out
t0 = time.time()
Dm = soren(Pte, Ptr)
print("distances", Dm.shape, round(time.time() - t0, 1), "s")
np.save("/tmp/uji_soren.npy", Dm)
def knn(Dm, k, xy, bld, flr, weighted=True, restrict=None):
    idx = np.argsort(Dm, axis=1)[:, :k]
    d = np.take_along_axis(Dm, idx, 1)
    w = 1 / (d + 1e-6) if weighted else np.ones_like(d)
    pos = (xy[idx] * w[..., None]).sum(1) / w.sum(1)[:, None]
    return pos, idx, w
def report(name, pos, bh=None, fh=None):
    e = np.linalg.norm(pos - te.xy, axis=1)
    print(f"{name:50s} mean {e.mean():5.2f} median {np.median(e):5.2f} p75 {np.percentile(e,75):5.2f}" + (f" bld {bh:.3f} flr {fh:.3f}" if bh is not None else ""))
for k in (1, 3, 5, 7, 10):
    pos, idx, w = knn(Dm, k, tr.xy, tr.building, tr.floor)
    report(f"sorensen k={k}", pos)
# reference points: average training fingerprints at the same (x, y, floor, building)
key = np.round(tr.xy, 1)
keys = np.column_stack([key, tr.floor, tr.building])
u, inv = np.unique(keys, axis=0, return_inverse=True)
inv = inv.ravel()
print("reference points", len(u))
cnt = np.bincount(inv)
Pref = np.zeros((len(u), Ptr.shape[1])); np.add.at(Pref, inv, Ptr); Pref /= cnt[:, None]
# heard-mean instead (mean over samples that heard the AP)
xyr = u[:, :2]; flr_r = u[:, 2].astype(int); bld_r = u[:, 3].astype(int)
Dr = soren(Pte, Pref)
for k in (1, 2, 3, 5, 8):
    pos, idx, w = knn(Dr, k, xyr, bld_r, flr_r)
    report(f"RP-averaged sorensen k={k}", pos)
# building/floor by vote of k=5 on samples, then kNN restricted
def vote(Dm, labels, k=5):
    idx = np.argsort(Dm, axis=1)[:, :k]; d = np.take_along_axis(Dm, idx, 1); w = 1 / (d + 1e-6)
    L = labels[idx]; out = []
    for i in range(len(L)):
        s = {}
        for l, ww in zip(L[i], w[i]): s[l] = s.get(l, 0) + ww
        out.append(max(s, key=s.get))
    return np.array(out)
bf_tr = tr.building * 10 + tr.floor
bf = vote(Dm, bf_tr, 5)
bh = np.mean(bf // 10 == te.building); fh = np.mean(bf == te.building * 10 + te.floor)
print(f"building/floor vote k=5: building {bh:.3f} floor {fh:.3f}")
for k in (3, 5, 8):
    bf_r = bld_r * 10 + flr_r
    Dx = np.where(bf_r[None] == bf[:, None], Dr, 9.0)
    pos, idx, w = knn(Dx, k, xyr, bld_r, flr_r)
    report(f"RP-averaged, within voted floor, k={k}", pos, bh, fh)
