"""Can one sigma_m serve queries where the map has walked and where it has not? A second
calibration set without truth ("neighbourhood out": a walk located on the map with every
fingerprint within R m of its path removed) and a score term,
sigma^2 = (scale * sqrt(spread^2 + 2^2))^2 + (c * max(0, score - s0))^2, (c, s0) the cheapest with
95 % of that set inside (s0 a quantile of the covered set's scores, or Q given). Scored on held-out
walks (truth: evaluation only).
python lab/radiomap/uncovered_calibration.py FLOOR route|FOLDS R Q   (Q: 0 = search s0)"""
import numpy as np, graphslam as gs, sys, math
from scipy.spatial import cKDTree
from graphslam import KnnConfig, KnnLocator, oracle_radio_map, RadioMap
R95 = math.sqrt(-2*math.log(0.05)); FLOOR=2.0

def sample(rm, seed=0, max_sessions=12, per=25):
    rng=np.random.default_rng(seed); ses=np.unique(rm.session_ids)
    if len(ses)>max_sessions: ses=np.sort(rng.choice(ses,max_sessions,replace=False))
    out=[]
    for s in ses:
        own=rm.session_ids==s; rows=np.flatnonzero(own)
        if len(rows)>per: rows=np.sort(rng.choice(rows,per,replace=False))
        out.append((own,rows))
    return out

def run(rm, own, rows, keep):
    others=RadioMap.from_fingerprints(rm.fingerprints.rows(keep), rm.xy[keep], session_ids=rm.session_ids[keep], t_ns=rm.t_ns[keep], frame=rm.frame, min_rssi_dbm=rm.min_rssi_dbm)
    res=KnnLocator(others,KnnConfig(index="exact"),threads=1).locate(others.reindex(rm.fingerprints.rows(rows)))
    ok=res.valid
    return np.linalg.norm(res.xy[ok]-rm.xy[rows[ok]],axis=1), res.spread[ok], res.score[ok]

def calib(rm, R=5.0):
    A=[];B=[]
    tree=None
    for own,rows in sample(rm):
        keep=np.flatnonzero(~own)
        if len(keep)==0: continue
        A.append(run(rm,own,rows,keep))
        d,_=cKDTree(rm.xy[own]).query(rm.xy[keep])
        keepb=keep[d>R]
        if len(keepb): B.append(run(rm,own,rows,keepb))
    cat=lambda L:[np.concatenate(x) for x in zip(*L)]
    ea,sa,ca=cat(A); eb,sb,cb=cat(B)
    base_a=np.sqrt(sa**2+FLOOR**2); scale=np.quantile(ea/(R95*base_a),0.95)
    best=(np.inf,0.0,0.0,0.0)
    for q in ([Q] if Q > 0 else np.arange(0,1.0,0.1)):
        s0=np.quantile(ca,q)
        for c in np.concatenate([[0],np.geomspace(1,4000,100)]):
            sig_b=np.sqrt((scale*np.sqrt(sb**2+FLOOR**2))**2+(c*np.maximum(0,cb-s0))**2)
            if np.mean(eb<=R95*sig_b)>=0.95: break
        sig_a=np.sqrt((scale*base_a)**2+(c*np.maximum(0,ca-s0))**2)
        cost=np.median(np.concatenate([sig_a,sig_b]))
        if np.mean(eb<=R95*sig_b)>=0.95 and cost<best[0]: best=(cost,c,s0,np.mean(eb<=R95*sig_b))
    _,c,s0,cov_b=best
    return scale,c,cov_b,s0

folder=sys.argv[1]; folds=None if sys.argv[2]=="route" else int(sys.argv[2]); R=float(sys.argv[3]); Q=float(sys.argv[4])
from graphslam import held_out_folds
walks=[w for w in gs.read_survey([folder]) if len(w.landmarks)>=2]
ins0=[];ins1=[];E=[]
for _,ti in held_out_folds(walks, folds, 0):
    tr=[w for i,w in enumerate(walks) if i not in set(ti)]; te=[walks[i] for i in ti]
    rm=oracle_radio_map(tr); truth=oracle_radio_map(te).xy
    u=gs.calibrate_uncertainty(rm)
    scale,c,covb,s0=calib(rm,R)
    res=KnnLocator(rm,KnnConfig()).locate([dict(s.readings) for w in te for s in w.scans]); ok=res.valid
    e=np.linalg.norm(res.xy[ok]-truth[ok],axis=1)
    ins0.append(e<=R95*u.sigma(res.spread[ok]))
    sig=np.sqrt((scale*np.sqrt(res.spread[ok]**2+FLOOR**2))**2+(c*np.maximum(0,res.score[ok]-s0))**2); ins1.append(e<=R95*sig)
    print(f"  fold scale {scale:.2f} c {c:.1f} covb {covb:.3f} old-scale {u.scale:.2f}", flush=True)
    E.append(R95*sig)
print(folder, sys.argv[2], "R",R, "old coverage", np.concatenate(ins0).mean().round(3), "new", np.concatenate(ins1).mean().round(3), "median r95 new", np.median(np.concatenate(E)).round(2))
