"""Survey simulator: office floors, WiFi radio model, walkers with foot-module drift, and the
``museum`` scenario (out-and-back routes with a phone's PDR, shaped like IPIN 2023 floor -2).

Typical use::

    from graphslam.sim import simulate
    sim = simulate("paper", seed=0, test_walks=3)
    sim.survey                 # graphslam.core.types.Survey (ground truth + landmark marks)
    sim.test_sessions          # held-out walks, same building
    sim.building.mean_rss(xy)  # (N, A) noiseless mean RSS, columns = sim.building.aps.bssids
    sim.write("out/")          # OUT/*.mcap, OUT/test/*.mcap, OUT/building.json
    sim.survey.sessions[0].heading  # the phone's azimuth per step (Earth frame; HeadingModel: scenario.heading)
    sim.survey.sessions[0].magnetic  # the phone's magnetic field per step (µT; MagneticModel: scenario.magnetic)

See docs/simulator.md for the models and their parameters.
"""

from graphslam.sim.cart import CartNoise, CartPath, CartRun, simulate_cart
from graphslam.sim.floorplan import FloorPlan, Landmark, corridor_plan, office_plan
from graphslam.sim.heading import HeadingModel, distortion_field, phone_heading, walk_offset, wrap_yaw
from graphslam.sim.magnetic import MagneticModel, anomaly_field, phone_magnetic
from graphslam.sim.museum import (
    LayoutParams,
    MuseumParams,
    MuseumWalkerParams,
    PhoneModel,
    PhonePdrParams,
    Route,
    museum_layout,
    simulate_museum_walk,
)
from graphslam.sim.radio import (
    AccessPoints,
    RadioEnvironment,
    RadioParams,
    ShadowingField,
    make_radio,
    wall_crossings,
)
from graphslam.sim.scenarios import (
    SCENARIOS,
    Building,
    Scenario,
    SimulatedSurvey,
    build_building,
    get_scenario,
    simulate,
    with_overrides,
)
from graphslam.sim.shape import route_of, shape_walks, survey_shape
from graphslam.sim.stats import SurveyStats, WalkStats, align_by_start, raw_drift
from graphslam.sim.walker import ImuErrorParams, WalkerParams, WalkSpec, dead_reckon, simulate_walk

__all__ = [
    "CartNoise",
    "CartPath",
    "CartRun",
    "simulate_cart",
    "AccessPoints",
    "Building",
    "FloorPlan",
    "HeadingModel",
    "ImuErrorParams",
    "Landmark",
    "LayoutParams",
    "MagneticModel",
    "MuseumParams",
    "MuseumWalkerParams",
    "PhoneModel",
    "PhonePdrParams",
    "Route",
    "RadioEnvironment",
    "RadioParams",
    "SCENARIOS",
    "Scenario",
    "ShadowingField",
    "SimulatedSurvey",
    "SurveyStats",
    "WalkSpec",
    "WalkStats",
    "WalkerParams",
    "align_by_start",
    "anomaly_field",
    "build_building",
    "corridor_plan",
    "distortion_field",
    "dead_reckon",
    "get_scenario",
    "make_radio",
    "museum_layout",
    "office_plan",
    "phone_heading",
    "phone_magnetic",
    "raw_drift",
    "route_of",
    "shape_walks",
    "simulate",
    "simulate_museum_walk",
    "simulate_walk",
    "survey_shape",
    "walk_offset",
    "wall_crossings",
    "with_overrides",
    "wrap_yaw",
]
