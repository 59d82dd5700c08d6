"""Shared test helpers: tiny hand-made recordings, raw MCAP writer for bad-input cases; commands that
keep a cache (``graphslam track``'s self-calibration, ``$XDG_CACHE_HOME/graphslam``) keep it in a
temporary folder, never the user's. (No conftest.py at the repository root: the tests import this
one as ``conftest``, and so do the Dask workers of test_batch.)"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
import pytest
from mcap.writer import Writer

from graphslam.core.types import LandmarkMark, PoseTrack, Scan, Session
from graphslam.io.schemas import TOPIC_SCHEMAS, schema_bytes

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data"))
ILC = DATA / "ilc20" / "site1"

T0 = 1_767_225_600_000_000_000  # 2026-01-01T00:00:00Z in ns


@pytest.fixture(autouse=True, scope="session")
def _private_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("cache"))  # subprocesses inherit it
    yield
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


def needs_data(sub: str) -> Any:
    return pytest.mark.skipif(not (DATA / sub).exists(), reason=f"real data {DATA / sub} not present")


def pose_body(t_ns: int, x: float, y: float, h: float, frame: str = "fmip") -> dict:
    return {
        "timestamp": {"sec": t_ns // 10**9, "nsec": t_ns % 10**9},
        "frame_id": frame,
        "pose": {
            "position": {"x": x, "y": y, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(h / 2), "w": math.cos(h / 2)},
        },
    }


def scan_body(t_ns: int, readings: dict[str, float]) -> dict:
    return {
        "timestamp": {"sec": t_ns // 10**9, "nsec": t_ns % 10**9},
        "readings": [{"bssid": b, "rssi": r} for b, r in readings.items()],
    }


def write_raw_mcap(
    path: Path,
    messages: Iterable[tuple[str, Any, int]],
    *,
    metadata: dict[str, str] | None = None,
    schema_names: dict[str, str] | None = None,
) -> Path:
    """Write (topic, body, log_time) messages as-is (no checks): for bad-input tests."""
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        if metadata is not None:
            w.add_metadata("graphslam.session", metadata)
        channels: dict[str, int] = {}
        for topic, body, t in messages:
            if topic not in channels:
                name, schema = TOPIC_SCHEMAS.get(topic, ("unknown", {}))
                name = (schema_names or {}).get(topic, name)
                sid = w.register_schema(name=name, encoding="jsonschema", data=schema_bytes(schema))
                channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            data = body if isinstance(body, bytes) else json.dumps(body).encode()
            w.add_message(channels[topic], log_time=t, data=data, publish_time=t)
        w.finish()
    return path


def good_messages(n_steps: int = 10, n_scans: int = 3) -> list[tuple[str, Any, int]]:
    msgs: list[tuple[str, Any, int]] = []
    for i in range(n_steps):
        t = T0 + i * 500_000_000
        msgs.append(("/fmip/pose", pose_body(t, 0.7 * i, 0.0, 0.0), t))
    for j in range(n_scans):
        t = T0 + j * 2_000_000_000 + 100
        msgs.append(("/wifi/scan", scan_body(t, {"aa:bb": -50.0 - j, "cc:dd": -70.0}), t))
    return sorted(msgs, key=lambda m: m[2])


def make_session(
    session_id: str = "s0",
    n_steps: int = 20,
    *,
    with_truth: bool = True,
    seed: int = 0,
) -> Session:
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n_steps, dtype=np.int64) * 500_000_000
    h = np.cumsum(rng.normal(0, 0.05, n_steps))
    h[0] = 0.0
    xy = np.zeros((n_steps, 2))
    for i in range(1, n_steps):
        xy[i] = xy[i - 1] + 0.7 * np.array([np.cos(h[i - 1]), np.sin(h[i - 1])])
    scans = tuple(
        Scan(int(t[i]) + 1000, {f"ap{k}": float(-40 - 3 * k - rng.integers(0, 5)) for k in range(5)})
        for i in range(0, n_steps, 4)
    )
    truth = PoseTrack(t, xy + [10.0, 5.0], h) if with_truth else None
    marks = (LandmarkMark(int(t[3]), "L1", 12.0, 5.0),) if with_truth else ()
    return Session(session_id, PoseTrack(t, xy, h), scans, marks, truth, site="test", floor="0")


def run_cli(args: list[str]) -> int:
    """``graphslam ARGS`` in this process; its exit code (0 when it returns)."""
    from graphslam.cli import main

    try:
        main(args)
    except SystemExit as e:
        return int(e.code or 0)
    return 0


def walking_model() -> Any:
    """The tracker's fusion model for a walker (the papers' path loss; track's process noise, heading
    in the state): what the walk-axes and walkable-area tests track with."""
    from graphslam.core.tracking.filters import FusionModel

    base = FusionModel.paper_ekf()
    return FusionModel(base.path_loss, np.array([0.01, 0.01, 1.0, 1.0, 1e-6, 1e-6, 1e-4]), np.full(2, 0.15**2),
                       base.r_rssi, period_s=1.0, theta_rad=None)


def walk_epochs(t: np.ndarray, v: np.ndarray, p: np.ndarray, theta: float, fix_k: np.ndarray, rng: np.random.Generator) -> Any:
    """Epochs of a walk with true velocities ``v`` and positions ``p`` at times ``t`` (map frame):
    odometry turned by ``theta`` (eq. 4: y_v = M(theta) v, noise 0.05 m/s), a fix (std 4 m) at the
    epochs ``fix_k``, no RSSI."""
    from graphslam.core.tracking.filters import Epochs, velocity_matrix

    y_v = np.einsum("ij,kj->ki", velocity_matrix(theta), v) + rng.normal(0.0, 0.05, v.shape)
    none = np.zeros(0, np.int64)
    return Epochs(t, np.arange(len(t) - 1), y_v[:-1], none, none, np.zeros(0),
                  fix_k, p[fix_k] + rng.normal(0.0, 4.0, (len(fix_k), 2)), np.full(len(fix_k), 4.0))
