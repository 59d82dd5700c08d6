"""UJIIndoorLoc validation: Sørensen kNN (exact) with k and neighbour weights varied offline
(inverse distance^p, similarity^p). python -m lab.ujiindoorloc.uji_weights"""
import numpy as np
from graphslam import KnnConfig, KnnLocator
from lab.bench.uji import find_uji_file, TRAIN_FILE, TEST_FILE
from lab.bench.ujiindoorloc import read_ujiindoorloc
D='../shared/data/ujiindoorloc'
tr=read_ujiindoorloc(find_uji_file(D,TRAIN_FILE)); te=read_ujiindoorloc(find_uji_file(D,TEST_FILE))
rm=tr.to_radio_map(); q=te.fingerprints()
res=KnnLocator(rm, KnnConfig(k=40, metric="sorensen", index="exact")).locate(q)
idx, d = res.neighbours, res.distances
xy=rm.xy
for k in (3,5,7,10,15):
  for p in (1,2,4,8):
    w=1.0/(d[:,:k]+1e-6)**p
    est=(w[:,:,None]*xy[idx[:,:k]]).sum(1)/w.sum(1)[:,None]
    e=np.linalg.norm(est-te.xy,axis=1)
    print(k,p,round(e.mean(),3), round(np.median(e),3))
# similarity-exponent weighting: w = (1-d)^p 
for k in (5,10,20,40):
  for p in (4,8,16,32):
    w=(1-d[:,:k])**p
    est=(w[:,:,None]*xy[idx[:,:k]]).sum(1)/w.sum(1)[:,None]
    e=np.linalg.norm(est-te.xy,axis=1)
    print('sim',k,p,round(e.mean(),3))
