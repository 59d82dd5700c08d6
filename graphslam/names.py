"""Names and defaults that several layers and the command line share, written once: the kNN
fingerprint distances and searches, the trackers and their options, the simulator's scenarios,
the export formats. No imports, so that the CLI lists them in ``--help`` without loading numpy.
"""

from __future__ import annotations

# kNN fingerprint distance (``KnnConfig.metric``, locate / serve / track --metric): Sørensen on
# powed RSS is the default, the better one measured on every data set (docs/radio_map.md); eq9 is
# the paper's RMS dB difference
METRICS = ("sorensen", "eq9")
DEFAULT_METRIC = "sorensen"
# kNN search (``KnnConfig.index``, locate / serve --index): auto = the IVF index from
# IVF_AUTO_MIN_REFS references (either metric), exact below
INDEXES = ("auto", "exact", "ivf")
DEFAULT_INDEX = "auto"
DEFAULT_K = 3  # neighbours

# the tracker (graphslam.tracking_config)
TRACKERS = ("fixed-lag", "ekf", "ukf", "particle")
SMOOTHERS = ("none", "rts", "map")
BANK_REPORTS = ("mixture", "best")
WALKABLE_MODES = ("snap", "prior", "both")

# the simulator (graphslam.sim.SCENARIOS, graphslam.sim.uwb)
SCENARIOS = ("paper", "corridor", "crowd", "museum")
UWB_SCENARIOS = ("zones", "crowd")

# the frame of a survey's main map (report.json ``frame``), named so in every file and answer made
# from it: the radio map's metadata, the CSVs' ``frame`` column, the pictures, the service's JSON
FRAMES = ("aligned", "earth", "site")
FRAME_DESCRIPTIONS = {
    "aligned": "aligned: origin at the reference walk's first pose, x along its first heading (metres)",
    "earth": "earth: x east, y north (phones' headings), origin at the reference walk's first pose",
    "site": "site: the site frame of the control points, UWB anchors or reference map (metres)",
}

# graphslam export: trajectory file formats (TUM and KITTI as evo reads them) and frames
EXPORT_FORMATS = ("tum", "kitti", "csv")
EXPORT_FRAMES = ("map", "site")

# uvicorn's log levels (serve --log-level); info logs one access line per request
LOG_LEVELS = ("critical", "error", "warning", "info", "debug", "trace")
