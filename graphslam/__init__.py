"""graphslam: factor-graph alignment of crowdsourced WiFi site surveys, radio maps, kNN and tracking.

The public API, re-exported here (imported on first use, so ``import graphslam`` stays cheap and
does not load GTSAM until a solver is needed)::

    import graphslam as gs

    survey = gs.read_survey(["walks/"])                 # MCAP recordings -> Survey
    result = gs.align(survey, gs.load_config())         # factor graph + LM -> Alignment
    rm = gs.read_radio_map("out/radio_map.parquet")
    fix = gs.KnnLocator(rm).locate([{"02:00:00:00:00:01": -61.0}])

Frames and units: metres, radians, dBm, nanosecond timestamps; see docs/ for each module's
conventions. Every library failure is a ``GraphSlamError`` subclass.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS: dict[str, str] = {
    # errors
    **{n: "graphslam.errors" for n in (
        "GraphSlamError", "InputError", "ConfigError", "SolverError", "RadioMapError", "QueryError",
        "SimulationError", "VisualizationError", "EstimationError", "OutputError",
    )},
    # configuration
    **{n: "graphslam.config" for n in ("GraphSlamConfig", "load_config", "config_from_dict")},
    # domain objects
    **{n: "graphslam.core.types" for n in (
        "PoseTrack", "Scan", "Session", "Survey", "LandmarkMark", "UwbRanges", "HeadingTrack", "MagneticTrack",
    )},
    # alignment and its evaluation
    **{n: "graphslam.core.survey.align" for n in ("align", "Alignment")},
    **{n: "graphslam.core.survey.evaluate" for n in ("evaluate", "Evaluation", "ErrorStats")},
    **{n: "graphslam.app.survey" for n in ("run_survey", "write_outputs", "SurveyResult")},
    "SurveyInputs": "graphslam.app.survey_inputs",
    # radio map, positioning, access points
    "RadioMap": "graphslam.core.radiomap.radiomap",
    **{n: "graphslam.core.radiomap.knn" for n in ("KnnConfig", "KnnLocator", "KnnResult")},
    **{n: "graphslam.core.radiomap.uncertainty" for n in ("KnnUncertainty", "calibrate_uncertainty")},
    **{n: "graphslam.core.radiomap.field" for n in ("RssField", "rss_field")},
    **{n: "graphslam.core.tracking.apmodel" for n in ("ApFitConfig", "ApModel", "ApModels", "UnfittedAp")},
    # filters, smoothers, tracking
    "PathLossModel": "graphslam.core.tracking.pathloss",
    **{n: "graphslam.core.tracking.filters" for n in (
        "FusionModel", "Shadowing", "GaussianState", "Epochs", "FilterRun", "make_filter", "run_epochs",
    )},
    **{n: "graphslam.core.tracking.smoother" for n in ("SmoothedRun", "smooth", "rts_smooth", "map_smooth", "MapProblem")},
    **{n: "graphslam.tracking_config" for n in ("TrackConfig", "load_track_config")},
    **{n: "graphslam.core.tracking.tracker" for n in ("Tracker", "SessionTrack", "track_sessions")},
    # UWB (Paper 003): the collaborative EKF
    **{n: "graphslam.core.uwb.ekf" for n in ("UwbEkfConfig", "UwbEpoch", "TagTrack", "track_tags")},
    "track_uwb_sessions": "graphslam.app.uwb_track",
    # files
    **{n: "graphslam.io.mcap_reader" for n in ("read_survey", "read_session")},
    "write_session": "graphslam.io.mcap_writer",
    **{n: "graphslam.io.radiomap_io" for n in ("read_radio_map", "write_radio_map")},
    **{n: "graphslam.io.magnetic_map_io" for n in ("read_magnetic_map", "write_magnetic_map")},
    "MagneticMap": "graphslam.core.radiomap.magnetic_map",
    "read_reference_map": "graphslam.io.reference_map",
    **{n: "graphslam.io.apmodel_io" for n in ("read_ap_models", "write_ap_models")},
    # --- for experiments (lab/: studies, diagnostics, the simulator benchmarks). The lab imports
    # nothing but this module (lab/tests/test_imports.py); these are what it builds on: the survey's
    # stages and solver, the tracking bench's pieces, the simulators, plots, the command-line
    # plumbing. Stable enough for studies, not promised to applications. "module:attr" exports
    # attr under another name (a private or ambiguous one); "module:" exports the module itself.
    "run_batch": "graphslam.app.batch",
    **{n: "graphslam.app.soak" for n in ("free_port", "http_exchange", "query_bodies", "wait_for_port")},
    "soak_loopback": "graphslam.app.soak:LOOPBACK",
    **{n: "graphslam.app.bench_real" for n in ("crowd_walks", "real_floors", "real_floor_rows")},
    "show_progress": "graphslam.app.progress",
    "POWED_EXPONENT": "graphslam.core.radiomap.neighbours",
    "tracking_pipeline": "graphslam.core.tracking.tracker:",
    **{n: "graphslam.app.tracking_bench" for n in ("Variant", "crowdsourced_map", "floor_plan_area", "held_out_folds", "interpolate_cov", "oracle_radio_map", "score_walks", "standard_variants", "tracking_real", "walk_landmarks")},
    "load_previous": "graphslam.app.update",
    **{n: "graphslam.cli.options" for n in ("parse_lags", "parse_metric", "parse_smoothers")},
    "run_app": "graphslam.cli",
    "cli_main": "graphslam.cli:main",
    "parse_overrides": "graphslam.config",
    **{n: "graphslam.core.common.geometry" for n in ("fit_se2", "interpolate_xy", "ransac_se2", "se2_apply", "se2_compose")},
    "progress_over": "graphslam.core.progress",
    **{n: "graphslam.core.radiomap.fingerprints" for n in ("DEFAULT_MIN_RSSI_DBM", "DEFAULT_MISSING_DBM", "DistanceEngine", "FingerprintMatrix")},
    "limit_blas_threads": "graphslam.core.radiomap.ivf",
    "WEIGHT_EPS_DB": "graphslam.core.radiomap.knn_types",
    "with_uncertainty": "graphslam.core.radiomap.uncertainty",
    "draw_radio_map": "graphslam.viz.radiomap_picture",
    "Problem": "graphslam.core.survey.problem",
    "build_problem": "graphslam.core.survey.align",
    **{n: "graphslam.core.survey.graph" for n in ("lm_params", "native_graph", "pose_graph", "dead_reckoned_nodes", "values_to_xyh")},
    "solve_problem": "graphslam.core.survey.align:solve",
    "survey_align": "graphslam.core.survey.align:",
    "associate": "graphslam.core.survey.association",
    **{n: "graphslam.core.radiomap.similarity" for n in ("PowerCosine", "Matches")},
    "walk_headings": "graphslam.core.survey.heading",
    "survey_magnetic": "graphslam.core.survey.magnetic:",
    **{n: "graphslam.core.survey.placement" for n in ("GrowthParams", "grow_placement")},
    **{n: "graphslam.core.survey.components" for n in ("Component", "place_components")},
    **{n: "graphslam.core.survey.evaluate" for n in ("landmark_errors", "component_errors")},
    "landmark_marks": "graphslam.core.survey.evaluate:_marks",
    **{n: "graphslam.io.floor_plan" for n in ("load_floor_plan", "read_walkable_area")},
    "expand_chains": "graphslam.core.survey.chains:expand",
    **{n: "graphslam.core.survey.edges" for n in ("propose_edges", "window_thresholds")},
    "trajectory_errors": "graphslam.core.survey.evaluate",
    "survey_factors": "graphslam.core.survey.factors:",
    "warm_start": "graphslam.core.survey.incremental",
    **{n: "graphslam.core.survey.radio_maps" for n in ("crowdsourced_radio_map", "surveyed_radio_map")},
    "survey_solver": "graphslam.core.survey.solver:",
    **{n: "graphslam.core.tracking.apmodel" for n in ("ap_position_errors", "fit_ap", "residual_field")},
    **{n: "graphslam.core.tracking.calibration" for n in ("ellipse_coverage", "leave_one_session_out_error_vectors")},
    "velocity_matrix": "graphslam.core.tracking.filters",
    **{n: "graphslam.core.tracking.fixed_lag" for n in ("FixedLagConfig", "fixed_lag_smooth")},
    "dead_reckoning_starts": "graphslam.core.tracking.smoother",
    "map_levenberg_marquardt": "graphslam.core.tracking.smoother:levenberg_marquardt",
    "wrap_angle": "graphslam.core.types",
    "MEASUREMENT_TYPES": "graphslam.core.uwb.ekf",
    "read_trajectories": "graphslam.io.csv_io",
    "floor_folders": "graphslam.io.mcap_reader",
    **{n: "graphslam.service.server" for n in ("reloading_app", "serve", "start_background_server")},
    "ServeConfig": "graphslam.service.config",
    **{n: "graphslam.sim" for n in ("shape_walks", "simulate", "survey_shape")},
    **{n: "graphslam.sim.cart" for n in ("CartNoise", "PAPER_P0", "PAPER_RMS_TARGETS_M", "PAPER_X0", "simulate_cart")},
    "get_scenario": "graphslam.sim.scenarios",
    **{n: "graphslam.sim.uwb.scenarios" for n in ("CrowdUwb", "nlos_fraction", "simulate_crowd", "simulate_zones")},
    "error_cdf": "graphslam.viz.plots",
    **{n: "graphslam.viz.survey_picture" for n in ("draw_survey", "scene_of_alignment")},
    "cart_figure": "graphslam.viz.tracking_plots",
    **{n: "graphslam.viz.uwb_plots" for n in ("error_over_time", "zones_map")},
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def _version() -> str:
    """The installed distribution's version (importlib.metadata: looked up on first use, not at import)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("graphslam")
    except PackageNotFoundError:  # running from a source tree that was not installed
        return "0+unknown"


def __getattr__(name: str) -> Any:
    if name == "__version__":
        globals()[name] = value = _version()
        return value
    target = _EXPORTS.get(name)
    if target is None:
        raise AttributeError(f"module 'graphslam' has no attribute {name!r}")
    module, sep, attr = target.partition(":")
    value = importlib.import_module(module)
    if not sep or attr:
        value = getattr(value, attr or name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # static analysers see the real objects
    from graphslam.config import GraphSlamConfig, config_from_dict, load_config
    from graphslam.core.survey.align import Alignment, align
    from graphslam.core.tracking.apmodel import ApFitConfig, ApModel, ApModels, UnfittedAp
    from graphslam.core.survey.evaluate import ErrorStats, Evaluation, evaluate
    from graphslam.core.tracking.filters import (
        Epochs, FilterRun, FusionModel, GaussianState, Shadowing, make_filter, run_epochs,
    )
    from graphslam.core.tracking.pathloss import PathLossModel
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator, KnnResult
    from graphslam.core.radiomap.uncertainty import KnnUncertainty, calibrate_uncertainty
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.core.tracking.smoother import MapProblem, SmoothedRun, map_smooth, rts_smooth, smooth
    from graphslam.core.radiomap.magnetic_map import MagneticMap
    from graphslam.core.types import (
        HeadingTrack, LandmarkMark, MagneticTrack, PoseTrack, Scan, Session, Survey, UwbRanges,
    )
    from graphslam.core.uwb.ekf import TagTrack, UwbEkfConfig, UwbEpoch, track_tags
    from graphslam.errors import (
        ConfigError, EstimationError, GraphSlamError, InputError, OutputError, QueryError, RadioMapError,
        SimulationError, SolverError, VisualizationError,
    )
    from graphslam.io.apmodel_io import read_ap_models, write_ap_models
    from graphslam.io.mcap_reader import read_session, read_survey
    from graphslam.io.mcap_writer import write_session
    from graphslam.io.magnetic_map_io import read_magnetic_map, write_magnetic_map
    from graphslam.io.radiomap_io import read_radio_map, write_radio_map
    from graphslam.io.reference_map import read_reference_map
    from graphslam.app.survey import SurveyResult, run_survey, write_outputs
    from graphslam.app.survey_inputs import SurveyInputs
    from graphslam.core.tracking.tracker import SessionTrack, Tracker, track_sessions
    from graphslam.tracking_config import TrackConfig, load_track_config
    from graphslam.app.uwb_track import track_uwb_sessions
