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
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

try:
    __version__ = version("graphslam")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"

_EXPORTS: dict[str, str] = {
    # errors
    **{n: "graphslam.errors" for n in (
        "GraphSlamError", "InputError", "ConfigError", "SolverError", "RadioMapError", "QueryError",
        "SimulationError", "VisualizationError", "EstimationError", "OutputError",
    )},
    # configuration
    **{n: "graphslam.config" for n in ("GraphSlamConfig", "load_config", "config_from_dict")},
    # domain objects
    **{n: "graphslam.core.types" for n in ("PoseTrack", "Scan", "Session", "Survey", "LandmarkMark", "UwbRanges")},
    # alignment and its evaluation
    **{n: "graphslam.core.survey.align" for n in ("align", "Alignment")},
    **{n: "graphslam.core.survey.evaluate" for n in ("evaluate", "Evaluation", "ErrorStats")},
    **{n: "graphslam.app.survey" for n in ("run_survey", "write_outputs", "SurveyResult")},
    # radio map, positioning, access points
    "RadioMap": "graphslam.core.radiomap.radiomap",
    **{n: "graphslam.core.radiomap.knn" for n in ("KnnConfig", "KnnLocator", "KnnResult")},
    **{n: "graphslam.core.tracking.apmodel" for n in ("ApFitConfig", "ApModel", "ApModels", "UnfittedAp")},
    # filters, smoothers, tracking
    **{n: "graphslam.core.tracking.filters" for n in (
        "PathLossModel", "FusionModel", "Shadowing", "GaussianState", "Epochs", "FilterRun", "make_filter", "run_epochs",
    )},
    **{n: "graphslam.core.tracking.smoother" for n in ("SmoothedRun", "smooth", "rts_smooth", "map_smooth", "MapProblem")},
    **{n: "graphslam.app.track" for n in ("TrackConfig", "SessionTrack", "track_sessions")},
    # UWB (Paper 003): the collaborative EKF
    **{n: "graphslam.core.uwb.ekf" for n in ("UwbEkfConfig", "UwbEpoch", "TagTrack", "track_tags")},
    "track_uwb_sessions": "graphslam.app.uwb_track",
    # files
    **{n: "graphslam.io.mcap_reader" for n in ("read_survey", "read_session")},
    "write_session": "graphslam.io.mcap_writer",
    **{n: "graphslam.io.radiomap_io" for n in ("read_radio_map", "write_radio_map")},
    **{n: "graphslam.io.apmodel_io" for n in ("read_ap_models", "write_ap_models")},
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'graphslam' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
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
        Epochs, FilterRun, FusionModel, GaussianState, PathLossModel, Shadowing, make_filter, run_epochs,
    )
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator, KnnResult
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.core.tracking.smoother import MapProblem, SmoothedRun, map_smooth, rts_smooth, smooth
    from graphslam.core.types import LandmarkMark, PoseTrack, Scan, Session, Survey, UwbRanges
    from graphslam.core.uwb.ekf import TagTrack, UwbEkfConfig, UwbEpoch, track_tags
    from graphslam.errors import (
        ConfigError, EstimationError, GraphSlamError, InputError, OutputError, QueryError, RadioMapError,
        SimulationError, SolverError, VisualizationError,
    )
    from graphslam.io.apmodel_io import read_ap_models, write_ap_models
    from graphslam.io.mcap_reader import read_session, read_survey
    from graphslam.io.mcap_writer import write_session
    from graphslam.io.radiomap_io import read_radio_map, write_radio_map
    from graphslam.app.survey import SurveyResult, run_survey, write_outputs
    from graphslam.app.track import SessionTrack, TrackConfig, track_sessions
    from graphslam.app.uwb_track import track_uwb_sessions
