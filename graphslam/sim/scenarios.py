"""Named scenarios (section IV of Paper 004) and ``simulate()``.

Determinism: everything is drawn from ``numpy`` Generators seeded by
``SeedSequence(seed, spawn_key=(stream, i))``: stream 0 = building (APs,
shadowing), stream 1 = survey walk i, stream 2 = test walk i. So walk i is the
same whatever ``size`` or ``test_walks`` are, and test walks never perturb the
survey. The ``museum`` scenario draws its layout from stream 3 (PDR heading field:
(3, 1)) and walk k of route r from ``spawn_key=(1, r, k)``. The phone's azimuth
(``/phone/heading``, ``graphslam.sim.heading``) has stream 4 of its own: the site's
magnetic distortion ``(4, 0)``, survey walk i ``(4, 1, i)`` (museum: ``(4, 1, r, k)``),
test walk i ``(4, 2, i)``; so headings on or off, every other value is the same. The magnetic
field (``/phone/magnetic``, ``graphslam.sim.magnetic``) has stream 5, keyed the same way: the
site's anomaly ``(5, 0)``, survey walk i ``(5, 1, i)`` (museum: ``(5, 1, r, k)``), test walk i
``(5, 2, i)``.
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
from graphslam.errors import ConfigError, SimulationError
from graphslam.io.atomic import atomic_write_text
from graphslam.io.mcap_writer import write_session
from graphslam.sim.floorplan import FloorPlan, Landmark, corridor_plan, office_plan
from graphslam.sim.heading import HeadingModel, distortion_field, phone_heading
from graphslam.sim.magnetic import MagneticModel, anomaly_field, field_at, phone_magnetic
from graphslam.sim.museum import MuseumParams, Route, heading_field, museum_layout, simulate_museum_walk
from graphslam.sim.radio import AccessPoints, RadioEnvironment, RadioParams, ShadowingField, make_radio
from graphslam.sim.walker import ImuErrorParams, WalkerParams, WalkSpec, simulate_walk

log = logging.getLogger(__name__)

# 2026-01-01T00:00:00Z; survey walks start at 08:00 that day, test walks 30 days later.
EPOCH_2026_NS = 1_767_225_600 * 1_000_000_000
_DAY_NS = 86_400 * 1_000_000_000
_HOUR_NS = 3_600 * 1_000_000_000

_STREAM_BUILDING, _STREAM_WALK, _STREAM_TEST, _STREAM_LAYOUT, _STREAM_HEADING, _STREAM_MAGNETIC = 0, 1, 2, 3, 4, 5


def _rng(seed: int, stream: int, i: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(stream, i)))


def _heading_rng(seed: int, *key: int) -> np.random.Generator:
    """The phone heading's generator for ``key`` (``(stream, i)`` or ``(stream, r, k)``), apart from the walks'."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_STREAM_HEADING, *key)))


def _magnetic_rng(seed: int, *key: int) -> np.random.Generator:
    """The magnetic field's generator for ``key`` (as ``_heading_rng``'s), apart from the walks' and the heading's."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_STREAM_MAGNETIC, *key)))


@dataclass(frozen=True)
class Scenario:
    """What to simulate. ``n_walks`` is multiplied by ``size`` in ``simulate``.

    Walk durations: walk i lasts ``durations_min[i % len]`` minutes if
    ``durations_min`` is given, else uniform in ``duration_range_min``; ``line``
    routes ignore both (a walk ends at the end of the marked line), and so do
    ``out_and_back`` routes (the museum's designed routes, ``museum`` parameters:
    ``n_walks`` is then only what ``size`` 1 gives).
    """

    name: str
    description: str
    plan: Literal["office", "corridor", "museum"]
    route: Literal["graph", "line", "out_and_back"]
    n_walks: int
    n_aps: int
    durations_min: tuple[float, ...] = ()
    duration_range_min: tuple[float, float] = (1.0, 4.0)
    test_duration_range_min: tuple[float, float] = (3.0, 6.0)
    walk_spacing_s: float = 3600.0  # start of walk i = 08:00 + i * spacing (+ up to a minute)
    radio: RadioParams = field(default_factory=RadioParams)
    walker: WalkerParams = field(default_factory=WalkerParams)
    imu: ImuErrorParams = field(default_factory=ImuErrorParams)
    museum: MuseumParams = field(default_factory=MuseumParams)
    heading: HeadingModel = field(default_factory=HeadingModel)  # /phone/heading; enabled=False: none
    magnetic: MagneticModel = field(default_factory=MagneticModel)  # /phone/magnetic; enabled=False: none

    def __post_init__(self) -> None:
        if self.n_walks < 1 or self.n_aps < 1:
            raise ConfigError(f"scenario {self.name!r}: n_walks and n_aps must be >= 1")
        for r in (self.duration_range_min, self.test_duration_range_min):
            if not 0 < r[0] <= r[1]:
                raise ConfigError(f"scenario {self.name!r}: bad duration range {r}")
        if any(d <= 0 for d in self.durations_min) or self.walk_spacing_s <= 0:
            raise ConfigError(f"scenario {self.name!r}: durations and spacing must be > 0")
        if (self.plan == "museum") != (self.route == "out_and_back"):
            raise ConfigError(f"scenario {self.name!r}: the museum plan goes with out_and_back routes, and only it")

    def floor_plan(self) -> FloorPlan:
        """The fixed plans; the museum's depends on the seed (``build_building``)."""
        if self.plan == "museum":
            raise ConfigError("the museum floor plan is drawn per seed: use build_building(scenario, seed)")
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
    "museum": Scenario(
        name="museum",
        description=(
            "IPIN 2023 museum floor -2 shape: 7 out-and-back routes along a tree of corridors, 4 walks each, "
            "plus 3 stair/lift spots x 4 short walks; phone PDR, 2 or 4 s scans by phone, pauses"
        ),
        plan="museum",
        route="out_and_back",
        n_walks=40,
        n_aps=139,
        walk_spacing_s=300.0,
        # Calibrated on IPIN 2023 floor -2 (scripts/sim_vs_real_shape.py): ~14 APs heard almost everywhere
        # (here: on the floor above, no walls in the way), the rest weak and local behind thick walls;
        # phones miss many weak beacons. Gives ~15 readings per scan of 139 APs and a real-like
        # fingerprint resolution (the nearest fingerprint of another walk a few metres away).
        radio=RadioParams(
            p0_dbm_range=(-80.0, -55.0),
            gamma_range=(2.5, 3.5),
            wall_loss_db=10.0,
            shadowing_sigma_db=2.5,
            shadowing_corr_m=8.0,
            noise_sigma_db=2.2,  # white part; the museum walker adds fading correlated over seconds
            floor_dbm=-97.0,
            miss_prob=0.07,
            weak_miss_prob=0.35,
            ap_min_separation_m=3.5,
            other_floor_fraction=0.1,
            other_floor_p0_dbm_range=(-50.0, -40.0),
            other_floor_gamma_range=(1.8, 2.2),
        ),
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
    routes: tuple[Route, ...] = ()  # designed routes (museum), site frame
    heading_field: ShadowingField | None = None  # phone PDR heading disturbance, rad (museum)
    # The phone azimuth's magnetic distortion (rad, site-frame grid) and the Earth azimuth of
    # site +x (deg); None: no /phone/heading simulated.
    magnetic_field: ShadowingField | None = None
    earth_from_site_deg: float | None = None
    # The site's magnetic field (/phone/magnetic): its model (the Earth's part) and the building's
    # anomaly (µT; layers east, north, up; site-frame grid); None: no /phone/magnetic simulated.
    field_model: MagneticModel | None = None
    field_anomaly: ShadowingField | None = None

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

    def field_ut(self, xy: NDArray) -> NDArray[np.float64]:
        """(N, 3) the site's true magnetic field (east, north, up; µT) at ``xy`` (N, 2, site frame)."""
        if self.field_model is None or self.field_anomaly is None:
            raise SimulationError(f"{self.site}: no magnetic field simulated")
        return field_at(xy, self.field_model, self.field_anomaly)

    def to_dict(self) -> dict:
        """JSON-ready description (no shadowing field: regenerate it with ``build_building``)."""
        a = self.aps
        return {
            "site": self.site,
            "floor": self.floor,
            "frame": (
                "site: metres, x along the building's axis, y 90 deg counter-clockwise from it, origin at the "
                "outer walls' corner of least x and y; Earth (east, north) = site rotated by earth_from_site_deg"
            ),
            "earth_from_site_deg": self.earth_from_site_deg,
            "magnetic": None if self.field_model is None else {
                "earth_ut": {"east": 0.0, "north": self.field_model.horizontal_ut, "up": self.field_model.vertical_ut},
                "anomaly_sigma_ut": self.field_model.anomaly_sigma_ut,
                "anomaly_corr_m": self.field_model.anomaly_corr_m,
            },
            "width_m": self.plan.width_m,
            "height_m": self.plan.height_m,
            "walls": np.round(self.plan.walls, 6).tolist(),
            "landmarks": [{"landmark_id": lm.landmark_id, "x": lm.x, "y": lm.y} for lm in self.landmarks],
            "access_points": [
                {
                    "bssid": b, "x": float(x), "y": float(y), "p0_dbm": float(p0), "gamma": float(g),
                    "floor_offset": int(f),
                }
                for b, (x, y), p0, g, f in zip(a.bssids, a.xy.tolist(), a.p0_dbm, a.gamma, a.floor_offset)
            ],
            "radio": {k: v for k, v in vars(self.radio.params).items()},
            "routes": [
                {"name": r.name, "kind": r.kind, "xy": np.round(r.xy, 6).tolist(), "landmark_ids": list(r.landmark_ids)}
                for r in self.routes
            ],
        }


def build_building(scenario: str | Scenario, seed: int = 0) -> Building:
    """The building of ``scenario`` for ``seed`` (cheap: no walks). Same as ``simulate(...).building``."""
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    if sc.plan != "museum":
        plan = sc.floor_plan()
        radio = make_radio(plan, sc.n_aps, sc.radio, _rng(seed, _STREAM_BUILDING))
        return Building(
            plan, radio, site=f"sim-{sc.name}", floor="F1", **_magnetic(sc, seed, plan), **_field(sc, seed, plan)
        )
    layout = museum_layout(sc.museum.layout, _rng(seed, _STREAM_LAYOUT))
    radio = make_radio(layout.plan, sc.n_aps, sc.radio, _rng(seed, _STREAM_BUILDING))
    hfield = heading_field(layout.plan, sc.museum.pdr, _rng(seed, _STREAM_LAYOUT, 1))
    return Building(
        layout.plan, radio, site=f"sim-{sc.name}", floor="F1", routes=layout.routes, heading_field=hfield,
        **_magnetic(sc, seed, layout.plan), **_field(sc, seed, layout.plan),
    )


def _magnetic(sc: Scenario, seed: int, plan: FloorPlan) -> dict:
    """The ``Building`` fields of the phone azimuth: its distortion field and the site's rotation."""
    if not sc.heading.enabled:
        return {}
    return {
        "magnetic_field": distortion_field(plan, sc.heading, _heading_rng(seed, 0)),
        "earth_from_site_deg": sc.heading.earth_from_site_deg,
    }


def _field(sc: Scenario, seed: int, plan: FloorPlan) -> dict:
    """The ``Building`` fields of ``/phone/magnetic``: the model and the building's anomaly."""
    if not sc.magnetic.enabled:
        return {}
    return {"field_model": sc.magnetic, "field_anomaly": anomaly_field(plan, sc.magnetic, _magnetic_rng(seed, 0))}


def _with_phone(session: Session, sc: Scenario, b: Building, seed: int, *key: int) -> Session:
    """``session`` with its ``/phone/heading`` and ``/phone/magnetic``, each from its own generator for ``key``."""
    return _with_magnetic(_with_heading(session, sc, b, _heading_rng(seed, *key)), sc, b, _magnetic_rng(seed, *key))


def _with_magnetic(session: Session, sc: Scenario, b: Building, rng: np.random.Generator) -> Session:
    """``session`` with its ``/phone/magnetic`` (from ``rng`` alone), or as it is when the field is off."""
    if not sc.magnetic.enabled:
        return session
    if b.field_anomaly is None or session.ground_truth is None:
        raise SimulationError(f"{session.session_id}: no magnetic field or ground truth to simulate its field from")
    return replace(session, magnetic=phone_magnetic(session.ground_truth, sc.magnetic, b.field_anomaly, rng))


def _with_heading(session: Session, sc: Scenario, b: Building, rng: np.random.Generator) -> Session:
    """``session`` with its ``/phone/heading`` (from ``rng`` alone), or as it is when headings are off."""
    if not sc.heading.enabled:
        return session
    if b.magnetic_field is None or session.ground_truth is None:
        raise SimulationError(f"{session.session_id}: no magnetic field or ground truth to simulate a heading from")
    return replace(session, heading=phone_heading(session.ground_truth, sc.heading, b.magnetic_field, rng))


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


def _museum_sessions(
    sc: Scenario, seed: int, size: float, test_walks: int, b: Building
) -> tuple[list[Session], list[Session]]:
    """Every route and stair/lift spot walked ``repetitions * size`` times (rounded, >= 1), then the test walks.

    Walk k of route r has its own stream ``(1, r, k)`` and starts at 08:00 + r * 4 h +
    k * spacing (+ up to a minute); test walk i walks route ``i % routes`` with phone ``i % phones``.
    """
    mp = sc.museum
    reps = max(1, int(round(mp.repetitions * size)))
    day0 = EPOCH_2026_NS + 8 * _HOUR_NS
    jobs = []
    for r, route in enumerate(b.routes):
        for k in range(reps):
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_STREAM_WALK, r, k)))
            start = day0 + r * 4 * _HOUR_NS + int(k * sc.walk_spacing_s * 1e9)
            start += int(rng.integers(0, 60_000)) * 1_000_000
            jobs.append((f"{sc.name}-s{seed}-{route.name}-rep{k + 1:02d}", start, route, mp.phone_for(r, k), rng))
    n_survey = len(jobs)
    width = max(2, len(str(test_walks - 1)))
    for i in range(test_walks):
        rng = _rng(seed, _STREAM_TEST, i)
        start = day0 + 30 * _DAY_NS + int(i * sc.walk_spacing_s * 1e9) + int(rng.integers(0, 60_000)) * 1_000_000
        route = b.routes[i % len(b.routes)]
        jobs.append((f"{sc.name}-s{seed}-t{i:0{width}d}", start, route, mp.phones[i % len(mp.phones)], rng))
    if b.heading_field is None:
        raise SimulationError(f"scenario {sc.name!r}: the building has no heading-disturbance field")
    hkeys = [(_STREAM_WALK, r, k) for r in range(len(b.routes)) for k in range(reps)]
    hkeys += [(_STREAM_TEST, i) for i in range(test_walks)]
    sessions = [
        _with_phone(
            simulate_museum_walk(
                sid, start, route, b.plan, b.radio, b.heading_field, mp, phone, rng, site=b.site, floor=b.floor
            ),
            sc, b, seed, *hkey,
        )
        for (sid, start, route, phone, rng), hkey in progress_over(list(zip(jobs, hkeys)), "simulate", unit="walks")
    ]
    return sessions[:n_survey], sessions[n_survey:]


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

    def run(specs: list[tuple[WalkSpec, np.random.Generator]], stream: int) -> list[Session]:
        return [
            _with_phone(
                simulate_walk(
                    spec, building.plan, building.radio, sc.walker, sc.imu, rng, site=building.site,
                    floor=building.floor,
                ),
                sc, building, int(seed), stream, i,
            )
            for i, (spec, rng) in enumerate(progress_over(specs, "simulate", unit="walks"))
        ]

    if sc.route == "out_and_back":
        sessions, tests = _museum_sessions(sc, int(seed), size, test_walks, building)
    else:
        sessions = run(_walk_specs(sc, int(seed), n, test=False), _STREAM_WALK)
        tests = run(_walk_specs(sc, int(seed), test_walks, test=True), _STREAM_TEST) if test_walks else []
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
