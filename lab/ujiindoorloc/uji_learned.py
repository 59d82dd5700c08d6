"""UJIIndoorLoc validation with learned regressors instead of kNN (a different formulation for the
<= 5.5 m target): tree ensembles and an MLP on the powed representation (the Sørensen kNN's), alone
and averaged with the default Sørensen kNN. Training on trainingData only; the validation set
scores (needs scikit-learn, which graphslam does not install). python -m lab.ujiindoorloc.uji_learned [--trees 200]"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from graphslam import POWED_EXPONENT, KnnConfig, KnnLocator
from lab.bench.uji import TEST_FILE, TRAIN_FILE, find_uji_file
from lab.bench.ujiindoorloc import read_ujiindoorloc

D = "../shared/data/ujiindoorloc"


def powed(rm, values):
    """Dense powed RSS ((shifted / -missing_dbm)^e, 0 unheard) of a csr matrix over the map's AP
    index, as the Sørensen kNN sees it."""
    v = values.tocsr().copy()
    v.data = (v.data / -rm.missing_dbm) ** POWED_EXPONENT
    return v.toarray()


def main() -> None:
    from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor
    from sklearn.neural_network import MLPRegressor

    ap = argparse.ArgumentParser()
    ap.add_argument("--trees", type=int, default=200)
    a = ap.parse_args()
    tr = read_ujiindoorloc(find_uji_file(D, TRAIN_FILE))
    te = read_ujiindoorloc(find_uji_file(D, TEST_FILE))
    rm = tr.to_radio_map()
    q = te.fingerprints()
    knn = KnnLocator(rm, KnnConfig(k=3, metric="sorensen", index="exact")).locate(q)
    e_knn = np.linalg.norm(knn.xy - te.xy, axis=1)
    out = {"knn_sorensen_k3": round(float(e_knn.mean()), 3)}
    Xtr = powed(rm, rm.fingerprints.values)
    Xte = powed(rm, rm.reindex(q).values)
    ytr = rm.xy
    models = {
        "extra_trees": ExtraTreesRegressor(n_estimators=a.trees, n_jobs=2, random_state=0, max_features=0.3),
        "random_forest": RandomForestRegressor(n_estimators=a.trees, n_jobs=2, random_state=0, max_features=0.3),
        "mlp": MLPRegressor(hidden_layer_sizes=(256, 128), max_iter=300, random_state=0, early_stopping=True),
    }
    for name, m in models.items():
        t0 = time.perf_counter()
        mu, sd = ytr.mean(0), ytr.std(0)
        m.fit(Xtr, (ytr - mu) / sd)
        est = m.predict(Xte) * sd + mu
        e = np.linalg.norm(est - te.xy, axis=1)
        blend = np.linalg.norm(0.5 * (est + knn.xy) - te.xy, axis=1)
        out[name] = round(float(e.mean()), 3)
        out[name + "+knn"] = round(float(blend.mean()), 3)
        out[name + "_s"] = round(time.perf_counter() - t0, 1)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
