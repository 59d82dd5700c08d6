"""Dask or Ray for survey-batch: start-up of a 2-worker local cluster, and worker death.

Run in a venv that has the engine (Ray is not a graphslam dependency):

    python -m venv /tmp/v-dask && /tmp/v-dask/bin/pip install distributed
    du -sh /tmp/v-dask/lib/python3*/site-packages
    python -m venv /tmp/v-ray && /tmp/v-ray/bin/pip install ray && du -sh /tmp/v-ray/lib/python3*/site-packages
    /tmp/v-dask/bin/python lab/batch/bench_engines.py dask --repeats 3
    /tmp/v-ray/bin/python lab/batch/bench_engines.py ray --repeats 3

Prints one JSON line: import, cluster start, first task, shutdown (medians, s); a task whose worker
is SIGKILLed mid-task (retried? seconds); a task that kills its worker every time (what error, after
how long).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time


def sleeper(x: int) -> int:
    time.sleep(2.0)
    return os.getpid()


def sleeper_free(x: int) -> int:
    return abs(x)


def suicide(x: int) -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def start_dask() -> dict:
    t0 = time.perf_counter()
    from distributed import Client, LocalCluster

    t1 = time.perf_counter()
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None)
    client = Client(cluster)
    t2 = time.perf_counter()
    assert client.submit(sleeper_free, -1).result() == 1
    t3 = time.perf_counter()
    client.close()
    cluster.close()
    return {"import": t1 - t0, "start": t2 - t1, "first_task": t3 - t2, "stop": time.perf_counter() - t3}


def start_ray() -> dict:
    t0 = time.perf_counter()
    import ray

    t1 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    t2 = time.perf_counter()
    assert ray.get(ray.remote(sleeper_free).remote(-1)) == 1
    t3 = time.perf_counter()
    ray.shutdown()
    return {"import": t1 - t0, "start": t2 - t1, "first_task": t3 - t2, "stop": time.perf_counter() - t3}


def deaths_dask() -> dict:
    from distributed import Client, LocalCluster

    out = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster, Client(cluster) as c:
        pids = c.run(os.getpid)
        t = time.perf_counter()
        fut = c.submit(sleeper, 1, pure=False)
        while not any(c.processing().values()):
            time.sleep(0.01)
        busy = [a for a, k in c.processing().items() if k][0]
        os.kill(pids[busy], signal.SIGKILL)
        try:
            fut.result(timeout=120)
            out["killed_mid_task"] = {"retried": True, "seconds": round(time.perf_counter() - t, 2)}
        except Exception as e:  # noqa: BLE001
            out["killed_mid_task"] = {"retried": False, "error": f"{type(e).__name__}: {e}"[:200]}
        t = time.perf_counter()
        try:
            c.submit(suicide, 1, pure=False).result(timeout=300)
        except Exception as e:  # noqa: BLE001
            out["always_dies"] = {"error": f"{type(e).__name__}: {e}"[:160],
                                  "seconds": round(time.perf_counter() - t, 2)}
    return out


def deaths_ray() -> dict:
    import ray

    out = {}
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    import psutil  # Ray's vendored copy is importable once it is initialised
    t = time.perf_counter()
    ref = ray.remote(sleeper).remote(1)
    time.sleep(1.0)
    me = os.getpid()
    for p in psutil.Process(me).children(recursive=True):  # the worker running the task is asleep in it
        try:
            if "ray::sleeper" in " ".join(p.cmdline()):
                os.kill(p.pid, signal.SIGKILL)
        except psutil.Error:
            pass
    try:
        ray.get(ref, timeout=120)
        out["killed_mid_task"] = {"retried": True, "seconds": round(time.perf_counter() - t, 2)}
    except Exception as e:  # noqa: BLE001
        out["killed_mid_task"] = {"retried": False, "error": f"{type(e).__name__}: {e}"[:200]}
    t = time.perf_counter()
    try:
        ray.get(ray.remote(suicide).remote(1), timeout=300)
    except Exception as e:  # noqa: BLE001
        out["always_dies"] = {"error": f"{type(e).__name__}: {e}"[:160], "seconds": round(time.perf_counter() - t, 2)}
    ray.shutdown()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("engine", choices=["dask", "ray"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:  # one start-up measurement in a fresh interpreter (imports are not cached)
        print(json.dumps((start_dask if args.engine == "dask" else start_ray)()))
        return
    runs = []
    for _ in range(args.repeats):
        p = subprocess.run([sys.executable, __file__, args.engine, "--child"],
                           capture_output=True, text=True, check=True)
        runs.append(json.loads(p.stdout.strip().splitlines()[-1]))
    res = {"engine": args.engine, "repeats": args.repeats, "load_average": [round(v, 2) for v in os.getloadavg()]}
    res["startup_s_median"] = {k: round(statistics.median(r[k] for r in runs), 2) for k in runs[0]}
    res.update((deaths_dask if args.engine == "dask" else deaths_ray)())
    print(json.dumps(res))


if __name__ == "__main__":
    main()
