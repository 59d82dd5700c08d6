"""UJIIndoorLoc kNN benchmark: train on trainingData, test on validationData.

Errors are Euclidean distances between estimate and truth in EPSG:3857 metres (the
dataset's coordinates), as the UJIIndoorLoc literature reports them; building and
floor hit rates are the fractions of validation fingerprints whose weighted
neighbour vote is right. Speed is the median over ``repeats`` timed runs of the
query phase (encoding the queries over the map's AP index + search + estimate).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from graphslam import DEFAULT_MIN_RSSI_DBM, DEFAULT_MISSING_DBM, InputError, KnnConfig, KnnLocator, progress_over
from lab.bench.ujiindoorloc import read_ujiindoorloc

log = logging.getLogger(__name__)

TRAIN_FILE = "trainingData.csv"
TEST_FILE = "validationData.csv"


@dataclass(frozen=True)
class UjiBenchResult:
    n_train: int
    n_test: int
    k: int
    weighted: bool
    min_rssi_dbm: float
    missing_dbm: float
    min_common: int
    mean_error_m: float
    median_error_m: float
    p75_error_m: float
    p95_error_m: float
    building_hit: float
    floor_hit: float
    n_unlocated: int
    queries_per_s: float
    query_time_s: float  # median over repeats, all test queries
    repeats: int
    threads: int
    index: str  # "exact" or "ivf"
    metric: str  # KnnConfig.metric
    ivf_clusters: int  # 0 for exact
    ivf_probes: int
    recall: float  # queries whose k neighbours (as a set) are the exact search's; 1.0 for exact
    build_s: float  # locator construction (IVF: k-means), seconds

    def as_dict(self) -> dict[str, float | int | bool | str]:
        d = asdict(self)
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}


def find_uji_file(data_dir: str | Path, stem: str) -> Path:
    """``stem`` or ``stem.gz`` inside ``data_dir`` (or its ``ujiindoorloc`` sub-folder)."""
    base = Path(data_dir)
    for folder in (base, base / "ujiindoorloc"):
        for name in (stem, stem + ".gz"):
            if (folder / name).is_file():
                return folder / name
    raise InputError(base, f"no {stem}[.gz] in this folder (UJIIndoorLoc data)")


def run_ujiindoorloc_benchmark(
    data_dir: str | Path,
    *,
    k: int = 3,
    weighted: bool = True,
    min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM,
    missing_dbm: float = DEFAULT_MISSING_DBM,
    min_common: int = 1,
    repeats: int = 5,
    threads: int | None = None,
    index: str = "exact",
    ivf_clusters: int | None = None,
    ivf_probes: int | None = None,
    metric: str = "eq9",
) -> UjiBenchResult:
    """Build the radio map from trainingData, locate every validationData fingerprint. With an
    IVF index, ``recall`` is the fraction of queries whose k neighbours are the exact search's."""
    train = read_ujiindoorloc(find_uji_file(data_dir, TRAIN_FILE))
    test = read_ujiindoorloc(find_uji_file(data_dir, TEST_FILE))
    rm = train.to_radio_map(missing_dbm=missing_dbm, min_rssi_dbm=min_rssi_dbm)
    ivf = {"ivf_clusters": ivf_clusters} | ({"ivf_probes": ivf_probes} if ivf_probes is not None else {})
    config = KnnConfig(k=k, weighted=weighted, min_common=min_common, index=index, metric=metric, **ivf)  # type: ignore[arg-type]
    t0 = time.perf_counter()
    locator = KnnLocator(rm, config, threads=threads)
    build_s = time.perf_counter() - t0
    queries = test.fingerprints(missing_dbm=missing_dbm, min_rssi_dbm=min_rssi_dbm)
    times = []
    res = None
    for _ in progress_over(range(max(1, repeats)), "bench ujiindoorloc", unit="runs"):
        t0 = time.perf_counter()
        res = locator.locate(queries)
        times.append(time.perf_counter() - t0)
    assert res is not None
    recall = 1.0
    if locator.index_kind != "exact":
        ref = KnnLocator(rm, KnnConfig(k=k, weighted=weighted, min_common=min_common, metric=metric, index="exact"), threads=threads).locate(queries)  # type: ignore[arg-type]
        same = (np.sort(ref.neighbours, axis=1) == np.sort(res.neighbours, axis=1)).all(axis=1)
        recall = float(same.mean())
    ok = res.valid
    err = np.linalg.norm(res.xy[ok] - test.xy[ok], axis=1)
    if (~ok).any():
        log.warning("%d validation fingerprints could not be located (counted as misses)", int((~ok).sum()))
    assert res.floor is not None and res.building is not None
    n = len(test)
    t_med = float(np.median(times))
    return UjiBenchResult(
        n_train=len(train),
        n_test=n,
        k=k,
        weighted=weighted,
        min_rssi_dbm=min_rssi_dbm,
        missing_dbm=missing_dbm,
        min_common=min_common,
        mean_error_m=float(err.mean()) if len(err) else float("nan"),
        median_error_m=float(np.median(err)) if len(err) else float("nan"),
        p75_error_m=float(np.percentile(err, 75)) if len(err) else float("nan"),
        p95_error_m=float(np.percentile(err, 95)) if len(err) else float("nan"),
        building_hit=float(np.mean(res.building == test.building.astype(str))),
        floor_hit=float(np.mean(res.floor == test.floor.astype(str))),
        n_unlocated=int((~ok).sum()),
        queries_per_s=n / t_med,
        query_time_s=t_med,
        repeats=len(times),
        threads=locator.threads,
        index=locator.index_kind,
        metric=config.metric,
        ivf_clusters=locator.ivf.n_clusters if locator.ivf is not None else 0,
        ivf_probes=config.ivf_probes if locator.ivf is not None else 0,
        recall=recall,
        build_s=build_s,
    )
