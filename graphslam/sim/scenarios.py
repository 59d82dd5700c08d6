"""Named scenarios (section IV of Paper 004) and ``simulate()``.

Determinism: everything is drawn from ``numpy`` Generators seeded by
``SeedSequence(seed, spawn_key=(stream, i))``: stream 0 = building (APs,
shadowing), stream 1 = survey walk i, stream 2 = test walk i. So walk i is the
same whatever ``size`` or ``test_walks`` are, and test walks never perturb the
survey.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from graphslam.core.progress import progress_over
from graphslam.core.types import Session, Survey
from graphslam.errors import ConfigError
from graphslam.io.atomic import atomic_write_text
from graphslam.io.mcap_writer import write_session
from graphslam.sim.floorplan import FloorPlan, Landmark, corridor_plan, office_plan
from graphslam.sim.radio import AccessPoints, RadioEnvironment, RadioParams, make_radio
from graphslam.sim.walker import ImuErrorParams, WalkerParams, WalkSpec, simulate_walk

log = logging.getLogger(__name__)

# 2026-01-01T00:00:00Z; survey walks start at 08:00 that day, test walks 30 days later.
EPOCH_2026_NS = 1_767_225_600 * 1_000_000_000
_DAY_NS = 86_400 * 1_000_000_000
_HOUR_NS = 3_600 * 1_000_000_000

_STREAM_BUILDING, _STREAM_WALK, _STREAM_TEST = 0, 1, 2


def _rng(seed: int, stream: int, i: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(stream, i)))


@dataclass(frozen=True)
class Scenario:
    """What to simulate. ``n_walks`` is multiplied by ``size`` in ``simulate``.

    Walk durations: walk i lasts ``durations_min[i % len]`` minutes if
    ``durations_min`` is given, else uniform in ``duration_range_min``; ``line``
    routes ignore both (a walk ends at the end of the marked line).
    """

    name: str
    description: str
    plan: Literal["office", "corridor"]
    route: Literal["graph", "line"]
    n_walks: int
    n_aps: int
    durations_min: tuple[float, ...] = ()
    duration_range_min: tuple[float, float] = (1.0, 4.0)
    test_duration_range_min: tuple[float, float] = (3.0, 6.0)
    walk_spacing_s: float = 3600.0  # start of walk i = 08:00 + i * spacing (+ up to a minute)
    radio: RadioParams = field(default_factory=RadioParams)
    walker: WalkerParams = field(default_factory=WalkerParams)
    imu: ImuErrorParams = field(default_factory=ImuErrorParams)

    def __post_init__(self) -> None:
        if self.n_walks < 1 or self.n_aps < 1:
            raise ConfigError(f"scenario {self.name!r}: n_walks and n_aps must be >= 1")
        for r in (self.duration_range_min, self.test_duration_range_min):
            if not 0 < r[0] <= r[1]:
                raise ConfigError(f"scenario {self.name!r}: bad duration range {r}")
        if any(d <= 0 for d in self.durations_min) or self.walk_spacing_s <= 0:
            raise ConfigError(f"scenario {self.name!r}: durations and spacing must be > 0")

    def floor_plan(self) -> FloorPlan:
        return office_plan() if self.plan == "office" else corridor_plan()


SCENARIOS: dict[str, Scenario] = {
    "paper": Scenario(
        name="paper",
        description="Paper 004 IV-A.2: 5 long walks (9-28 min, ~5.6 km) in a 120 m x 60 m office floor",
        plan="office",
        route="graph",
        n_walks=5,
        n_aps=60,
        durations_min=(9.0, 11.0, 14.0, 16.0, 28.0),
        test_duration_range_min=(3.0, 6.0),
        walk_spacing_s=3600.0,
    ),
    "corridor": Scenario(
        name="corridor",
        description="Paper 004 IV-A.1: 12 walks along one marked straight line in a corridor",
        plan="corridor",
        route="line",
        n_walks=12,
        n_aps=16,
        walk_spacing_s=300.0,
        # A marked line: little sway; start heading within +-60 deg of the line.
        walker=WalkerParams(lateral_sigma_m=0.08, stop_prob=0.0, initial_heading_spread_rad=math.radians(60)),
    ),
    "crowd": Scenario(
        name="crowd",
        description="48 short walks (1-4 min) by many walkers over the office floor",
        plan="office",
        route="graph",
        n_walks=48,
        n_aps=60,
        duration_range_min=(1.0, 4.0),
        test_duration_range_min=(1.0, 4.0),
        walk_spacing_s=300.0,
    ),
}


def get_scenario(name: str) -> Scenario:
    """The named scenario; ``ConfigError`` listing the known names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ConfigError(f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}") from None


@dataclass(frozen=True, eq=False)
class Building:
    """The simulated site: floor plan (walls, walkable graph, landmarks) and radio environment."""

    plan: FloorPlan
    radio: RadioEnvironment
    site: str
    floor: str

    @property
    def walls(self) -> NDArray[np.float64]:
        return self.plan.walls

    @property
    def aps(self) -> AccessPoints:
        return self.radio.aps

    @property
    def landmarks(self) -> tuple[Landmark, ...]:
        return self.plan.landmarks

    def mean_rss(self, xy: NDArray, *, walls: bool = True, shadowing: bool = True) -> NDArray[np.float64]:
        """(N, A) noiseless mean RSS (dBm) of every AP at ``xy`` (N, 2, site frame); see ``RadioEnvironment``."""
        return self.radio.mean_rss(xy, walls=walls, shadowing=shadowing)

    def to_dict(self) -> dict:
        """JSON-ready description (no shadowing field: regenerate it with ``build_building``)."""
        a = self.aps
        return {
            "site": self.site,
            "floor": self.floor,
            "frame": "site: metres, x east, y north, origin at the south-west outer corner",
            "width_m": self.plan.width_m,
            "height_m": self.plan.height_m,
            "walls": np.round(self.plan.walls, 6).tolist(),
            "landmarks": [{"landmark_id": lm.landmark_id, "x": lm.x, "y": lm.y} for lm in self.landmarks],
            "access_points": [
                {"bssid": b, "x": float(x), "y": float(y), "p0_dbm": float(p0), "gamma": float(g)}
                for b, (x, y), p0, g in zip(a.bssids, a.xy.tolist(), a.p0_dbm, a.gamma)
            ],
            "radio": {k: v for k, v in vars(self.radio.params).items()},
        }


def build_building(scenario: str | Scenario, seed: int = 0) -> Building:
    """The building of ``scenario`` for ``seed`` (cheap: no walks). Same as ``simulate(...).building``."""
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    plan = sc.floor_plan()
    radio = make_radio(plan, sc.n_aps, sc.radio, _rng(seed, _STREAM_BUILDING))
    return Building(plan, radio, site=f"sim-{sc.name}", floor="F1")


@dataclass(frozen=True, eq=False)
class SimulatedSurvey:
    """Result of ``simulate``: the survey (with ground truth), held-out test walks, the building."""

    scenario: Scenario
    seed: int
    size: float
    building: Building
    survey: Survey
    test_sessions: tuple[Session, ...] = ()

    def write(self, out_dir: str | Path) -> list[Path]:
        """Write ``OUT/<session_id>.mcap``, ``OUT/test/<session_id>.mcap`` and ``OUT/building.json``.

        Every file is written atomically. Note: a reader given ``OUT`` as a folder
        searches it recursively and so also finds ``OUT/test``; pass the survey
        files (``OUT/*.mcap``) when the test walks must stay held out.
        """
        out = Path(out_dir)
        every = [(s, out / f"{s.session_id}.mcap") for s in self.survey]
        every += [(s, out / "test" / f"{s.session_id}.mcap") for s in self.test_sessions]
        paths = [write_session(s, p) for s, p in progress_over(every, "write", unit="walks")]
        info = {
            "scenario": self.scenario.name,
            "seed": self.seed,
            "size": self.size,
            "sessions": [s.session_id for s in self.survey],
            "test_sessions": [s.session_id for s in self.test_sessions],
            "building": self.building.to_dict(),
        }
        bpath = out / "building.json"
        atomic_write_text(bpath, json.dumps(info, indent=1))
        return paths + [bpath]


def _walk_specs(sc: Scenario, seed: int, n: int, test: bool) -> list[tuple[WalkSpec, np.random.Generator]]:
    stream = _STREAM_TEST if test else _STREAM_WALK
    width = max(2, len(str(n - 1)))
    tag = "t" if test else "w"
    day0 = EPOCH_2026_NS + 8 * _HOUR_NS + (30 * _DAY_NS if test else 0)
    out = []
    for i in range(n):
        rng = _rng(seed, stream, i)
        if sc.route == "line":
            duration = None
        elif test:
            duration = 60.0 * rng.uniform(*sc.test_duration_range_min)
        elif sc.durations_min:
            duration = 60.0 * sc.durations_min[i % len(sc.durations_min)]
        else:
            duration = 60.0 * rng.uniform(*sc.duration_range_min)
        start = day0 + int(i * sc.walk_spacing_s * 1e9) + int(rng.integers(0, 60_000)) * 1_000_000
        sid = f"{sc.name}-s{seed}-{tag}{i:0{width}d}"
        out.append((WalkSpec(sid, start, sc.route, duration), rng))
    return out


def simulate(
    scenario: str | Scenario,
    *,
    seed: int = 0,
    size: float = 1.0,
    test_walks: int = 0,
) -> SimulatedSurvey:
    """Simulate ``scenario`` (a name in ``SCENARIOS`` or a ``Scenario``).

    ``size`` multiplies the number of survey walks (rounded, at least 1; walk
    durations unchanged), e.g. ``size=12`` makes ``paper`` ~100k steps.
    ``test_walks`` extra walks (own random stream, same building) are returned
    in ``test_sessions``. Deterministic for a given (scenario, seed).
    """
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    if not (math.isfinite(size) and size > 0):
        raise ConfigError(f"size must be > 0, got {size!r}")
    if test_walks < 0:
        raise ConfigError(f"test_walks must be >= 0, got {test_walks}")
    t0 = time.perf_counter()
    building = build_building(sc, seed)
    n = max(1, int(round(sc.n_walks * size)))

    def run(specs: list[tuple[WalkSpec, np.random.Generator]]) -> list[Session]:
        return [
            simulate_walk(
                spec, building.plan, building.radio, sc.walker, sc.imu, rng, site=building.site, floor=building.floor
            )
            for spec, rng in progress_over(specs, "simulate", unit="walks")
        ]

    sessions = run(_walk_specs(sc, int(seed), n, test=False))
    tests = run(_walk_specs(sc, int(seed), test_walks, test=True)) if test_walks else []
    log.info(
        "simulated %s seed=%d size=%g: %d walks, %d test walks in %.1f s",
        sc.name,
        seed,
        size,
        len(sessions),
        len(tests),
        time.perf_counter() - t0,
    )
    return SimulatedSurvey(sc, int(seed), float(size), building, Survey(tuple(sessions)), tuple(tests))


def with_overrides(scenario: str | Scenario, **changes: object) -> Scenario:
    """A copy of ``scenario`` with fields replaced (e.g. ``n_aps=30``), checked on construction."""
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    try:
        return replace(sc, **changes)  # type: ignore[arg-type]
    except TypeError as e:
        raise ConfigError(f"scenario {sc.name!r}: {e}") from None
