"""``graphslam survey-batch SITES_ROOT --out OUT_ROOT``: many floors on a Dask cluster.

Every folder under SITES_ROOT that holds ``.mcap`` files directly is one floor; it is surveyed
as one task (``survey_floor``: ``run_survey`` of that folder) into the same relative path under
OUT_ROOT. A local cluster (``workers`` processes, one thread each, forked from a server that
has imported the survey code once, no Dask profiler) is started by default;
``address`` joins a running Dask scheduler instead, whose workers must see SITES_ROOT and
OUT_ROOT at the same paths (a shared file system) and have graphslam installed.

A floor surveyed whose main map (component 0) holds under half of its walks is ``partial``
(``graphslam.app.survey.main_map_warning``, the rule ``graphslam survey`` warns by; the text is
the row's ``warning``): its outputs are written, the batch still succeeds. A floor folder
holding ``control_points.csv`` is surveyed with those control points (``survey
--control-points``), one holding ``reference_map.csv`` on that surveyed map (``survey
--reference-map``), one holding ``floor_image.png`` and ``floor_info.json`` gets its survey.png over
that plan (``survey --floor-plan``); the row's ``frame`` says which frame the floor's main map came out in.

Failures stay per floor: bad input or a solver error is the floor's ``error`` (the message
names the file); a worker that dies while surveying a floor (OOM killer, a lost machine)
makes the scheduler run the floor again on another worker, up to
``distributed.scheduler.allowed-failures`` (Dask's default 3) more times, after which the floor
fails with "worker lost after retries: ..." (how many tries, the last worker). What a killed try
left beside the floor's output (its stage) is removed by the next try (``FolderStage``). The
other floors go on. ``OUT_ROOT/summary.json`` lists them all; it is written atomically (the
previous summary or the new one). An OUT_ROOT that cannot be written is refused before any work.

Why Dask and not Ray: a fifth of the installed size, and a local cluster that starts several
times faster (``survey-batch`` pays that on every run; lab/journal/benchmarks-history.md). On worker death both do what is needed: a task whose worker is killed
mid-task is run again, and one that kills every worker ends in a clear error after a few tries
(Dask ``KilledWorker``, Ray ``WorkerCrashedError``), so that did not decide it.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import multiprocessing.forkserver
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import GraphSlamConfig, config_from_dict
from graphslam.errors import ConfigError, GraphSlamError, InputError, require_extra
from graphslam.io.atomic import atomic_write_json, kill_point
from graphslam.io.paths import walk_folders

log = logging.getLogger(__name__)

SUMMARY_FILE = "summary.json"
STATUSES = ("ok", "partial", "failed")
# One thread per floor process: a survey is single-threaded in GTSAM; BLAS threads on top of
# two workers on two cores would only compete.
_WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "RERUN": "off"}
# Local workers are forked from a fork server that has imported these once (numpy, scipy,
# GTSAM, the survey code: ~1 CPU-s per worker otherwise, a fifth of a 16-floor run of small
# floors); a fork server is single-threaded, so forking it is safe where forking this
# process (an event-loop thread) is not.
_FORKSERVER_PRELOAD = ["distributed", "numpy", "graphslam.app.survey"]


@dataclass(frozen=True)
class FloorRow:
    """One line of summary.json: the main map first, as ``graphslam survey`` counts it."""

    floor: str  # folder relative to SITES_ROOT ("." for SITES_ROOT itself)
    status: str  # "ok" | "partial" (the main map holds under half of the walks) | "failed"
    error: str | None
    walks: int  # walks read
    main: int = 0  # walks in the main map (component 0, the radio map's)
    other_walks: int = 0  # walks in the other components (a frame each, not in the radio map)
    other_components: int = 0
    unaligned: int = 0
    main_map: str = ""  # the same counts as `survey`'s first line ("main map: 8 of 40 walks; ...")
    aligned: int = 0  # walks aligned, in any component (main + other_walks)
    # the main map's frame, as report.json's: "site" (control points or a reference map placed it),
    # "earth" (the phones' headings) or "aligned"; None for a failed floor
    frame: str | None = None
    seconds: float = 0.0
    warning: str | None = None  # why the floor is partial


def check_sites_root(sites_root: Path) -> None:
    """``InputError`` unless ``sites_root`` is a folder (the command checks it before importing Dask)."""
    if not sites_root.is_dir():
        raise InputError(sites_root, "not a folder (expected SITES_ROOT with one folder of .mcap recordings per floor)")


def find_floors(sites_root: Path, out_root: Path) -> list[Path]:
    """Folders under ``sites_root`` (itself included; linked folders too, each real folder once) that hold
    ``.mcap`` files directly, sorted; nothing inside ``out_root`` (its aligned.mcap files are outputs, not floors)."""
    check_sites_root(sites_root)
    out = out_root.resolve()
    floors = []
    for here, dirs, files in walk_folders(sites_root):  # linked floor folders too, each once
        if here.resolve() == out or out in here.resolve().parents:
            dirs[:] = []
            continue
        if any(f.endswith(".mcap") for f in files):
            floors.append(here)
    if not floors:
        raise InputError(sites_root, "no folder under it holds .mcap recordings")
    return sorted(floors)


def survey_floor(floor_dir: str, out_dir: str, config_json: str, floor: str, update: bool = False) -> dict[str, Any]:
    """The task: survey one floor, never raise for the floor's own failures (they are its row).
    ``update``: a previous output in ``out_dir`` seeds ``survey --update`` (none: a full survey)."""
    from graphslam.app.survey import main_map_warning, run_survey
    from graphslam.core.summary import report_main_map_counts

    t = time.perf_counter()
    counts: dict[str, Any] = {}
    error = warning = None
    kill_point(f"floor:{floor}")  # (a test hook: this worker killed while surveying this floor)
    try:
        import json

        cfg = config_from_dict(json.loads(config_json), "survey-batch configuration")
        result = run_survey(SurveyInputs.for_floor(floor_dir, out_dir, update=update), cfg)
        r = result.report
        comps = r["components"]
        counts = {"walks": r["sessions"], "main": comps[0]["n_walks"] if comps else 0,
                  "other_walks": sum(c["n_walks"] for c in comps[1:]), "other_components": max(0, len(comps) - 1),
                  "unaligned": len(r["unaligned"]), "main_map": report_main_map_counts(r),
                  "aligned": r["aligned_sessions"], "frame": r["frame"]}
        warning = main_map_warning(r)
    except GraphSlamError as e:
        error = str(e)
    except Exception as e:  # noqa: BLE001 - a floor's internal error must not stop the others
        log.exception("floor %s", floor)
        error = f"internal error: {type(e).__name__}: {e}"
    seconds = round(time.perf_counter() - t, 3)
    status = "failed" if error else "partial" if warning else "ok"
    if error:
        counts = {}
    return asdict(FloorRow(floor, status, error, **({"walks": 0} | counts), seconds=seconds,
                           warning=None if error else warning))


@dataclass(frozen=True)
class BatchResult:
    rows: list[FloorRow]
    summary: Path
    seconds: float

    @property
    def failed(self) -> int:
        return sum(r.status == "failed" for r in self.rows)

    @property
    def partial(self) -> int:
        return sum(r.status == "partial" for r in self.rows)

    @property
    def ok(self) -> int:
        return sum(r.status == "ok" for r in self.rows)


def run_batch(
    sites_root: str | Path,
    out_root: str | Path,
    config: GraphSlamConfig | None = None,
    *,
    address: str | None = None,
    workers: int | None = None,
    update: bool = False,
    on_floor: Callable[[FloorRow], None] | None = None,
    on_start: Callable[[int], None] | None = None,
) -> BatchResult:
    """Survey every floor under ``sites_root`` into ``out_root``; ``summary.json`` lists them.
    ``update``: floors already surveyed into ``out_root`` are updated (``survey --update``)."""
    require_extra("distributed", "survey-batch (Dask)")
    t0 = time.perf_counter()
    cfg = config or GraphSlamConfig()
    sites, out = Path(sites_root), Path(out_root)
    _check_out_root(out)
    floors = find_floors(sites, out)
    rels = [str(f.relative_to(sites)) for f in floors]
    if on_start is not None:
        on_start(len(floors))
    rows: dict[str, FloorRow] = {}
    with _client(address, workers) as client:
        from distributed import as_completed

        # Largest floors first (bytes of recordings, a proxy for the solve; submitted in that order
        # and prioritised so): the last to finish are small ones, and the workers run out of work
        # at nearly the same time instead of one waiting for the other's big floor.
        size = {f: _recorded_bytes(f) for f in floors}
        order = sorted(range(len(floors)), key=lambda k: -size[floors[k]])
        futures = {
            client.submit(survey_floor, str(floors[k]), str(out / rels[k]), cfg.model_dump_json(), rels[k], update,
                          key=f"floor-{k}-{rels[k]}", pure=False, priority=len(floors) - rank): rels[k]
            for rank, k in enumerate(order)
        }
        for fut in as_completed(futures):
            rel = futures[fut]
            try:
                row = FloorRow(**fut.result())
            except Exception as e:  # noqa: BLE001 - KilledWorker, a lost connection: this floor only
                row = FloorRow(rel, "failed", _lost_why(e), 0)
            rows[rel] = row
            if row.status == "failed":
                log.warning("floor %s failed: %s", rel, row.error)
            if on_floor is not None:
                on_floor(row)
    ordered = [rows[r] for r in rels]
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        from graphslam.errors import OutputError

        raise OutputError(f"{out}: cannot write ({e.strerror or e})") from None
    summary = out / SUMMARY_FILE
    atomic_write_json(summary, [asdict(r) for r in ordered])
    return BatchResult(ordered, summary, time.perf_counter() - t0)


def _check_out_root(out: Path) -> None:
    """``OutputError`` before any work when OUT_ROOT is not a folder, or cannot be written (a
    read-only mount, no permission): every floor would fail after its survey."""
    from graphslam.errors import OutputError

    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder")
    probe = out
    while not probe.exists():  # created on the way
        probe = probe.parent
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: cannot write into {probe}")


def _lost_why(e: BaseException) -> str:
    """A failed row's ``error`` for a floor whose task did not return: the worker surveying it
    died on every allowed try (``KilledWorker``), or the cluster lost it otherwise."""
    from distributed import KilledWorker

    if isinstance(e, KilledWorker):
        last = getattr(getattr(e, "last_worker", None), "address", "?")
        return (f"worker lost after retries: the process surveying this floor died on each of "
                f"{e.allowed_failures + 1} tries (killed, e.g. out of memory; the last: {last}, see its log)")
    return f"{type(e).__name__}: {e}"


def _recorded_bytes(floor: Path) -> int:
    return sum(f.stat().st_size for f in floor.glob("*.mcap") if f.is_file())


class _client:
    """A Dask client: on a new local cluster, or connected to ``address``. Closes what it started."""

    def __init__(self, address: str | None, workers: int | None) -> None:
        self.address, self.workers = address, workers
        self.cluster: Any = None
        self.client: Any = None
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> Any:
        if not self.address:
            self._stack.enter_context(_local_workers())
        from distributed import Client, LocalCluster

        if not logging.getLogger().isEnabledFor(logging.INFO):  # Dask's INFO lines only with --verbose
            logging.getLogger("distributed").setLevel(logging.WARNING)
        if self.address:
            try:
                self.client = Client(self.address, timeout="10s")
            except (OSError, TimeoutError) as e:
                raise ConfigError(f"--address {self.address}: cannot connect to a Dask scheduler ({e})") from None
            return self.client
        n = self.workers or os.cpu_count() or 1
        try:
            self.cluster = LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, env=_WORKER_ENV,
            )
            self.client = Client(self.cluster)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        log.info("local Dask cluster: %d workers", n)
        return self.client

    def __exit__(self, *exc: object) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        self._stack.close()


@contextlib.contextmanager
def _local_workers() -> Iterator[None]:
    """Within: Dask starts local workers (a) from a fork server preloaded with
    ``_FORKSERVER_PRELOAD`` where there is one, started first so that its imports overlap the
    cluster's start-up and stopped at the end (no process with the survey code loaded outlives
    the batch, and the workers' CPU time is accounted to this process's children); (b) without
    Dask's statistical profiler, which samples the floor's thread every 10 ms for a dashboard
    that is not started (a noticeable share of a floor's time)."""
    forkserver = "forkserver" in multiprocessing.get_all_start_methods()
    if forkserver:
        # A server already running (started elsewhere in this process) keeps its own preload.
        multiprocessing.get_context("forkserver").set_forkserver_preload(_FORKSERVER_PRELOAD)
        saved = {k: os.environ.get(k) for k in _WORKER_ENV}
        os.environ.update(_WORKER_ENV)  # BLAS reads its thread count once, as the server imports numpy
        try:
            multiprocessing.forkserver.ensure_running()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    import dask
    import distributed  # noqa: F401 - its config defaults first, or leaving the context below drops them

    # One floor per worker thread at a time (Dask's default lets a worker hold 2 with 1 thread):
    # a worker that dies is blamed (counted towards allowed-failures) only for the floor it ran.
    settings: dict[str, Any] = {"distributed.worker.profile.enabled": False,
                                "distributed.scheduler.worker-saturation": 1.0}
    if forkserver:
        settings["distributed.worker.multiprocessing-method"] = "forkserver"
    try:
        with dask.config.set(settings):
            yield
    finally:
        stop = getattr(multiprocessing.forkserver._forkserver, "_stop", None) if forkserver else None
        if stop is not None:  # CPython's; there is no public API to stop the server
            stop()
