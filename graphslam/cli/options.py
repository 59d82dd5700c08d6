"""Option parsing shared by the command modules (and the lab's commands): the survey configuration
from --config/--set, latencies, smoothers, kNN metrics; help texts used by several commands.
Each parser raises ``ConfigError`` (one line, exit code 2) before any file is read."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, List, Optional

if TYPE_CHECKING:
    from graphslam.config import GraphSlamConfig

def config_from_options(config: Optional[Path], set_: Optional[List[str]]) -> "GraphSlamConfig":
    """Config file (partial files merge over the defaults) plus ``--set a.b=value`` overrides."""
    from graphslam.config import load_config, parse_overrides

    return load_config(config, parse_overrides(set_))


INDEX_HELP = "kNN search: exact, ivf (approximate inverted file) or auto."


IVF_CLUSTERS_HELP = "IVF: k-means clusters (default ~2 sqrt(N))."


IVF_PROBES_HELP = "IVF: clusters searched per query (default 8)."


METRIC_HELP = (
    "Fingerprint distance: eq9 (the paper's RMS dB difference) or sorensen (Sørensen on powed RSS, "
    "Torres-Sospedra 2015; exact search only)."
)


def parse_lags(text: str) -> list[float]:
    """'0,1,2': fixed-lag latencies in s (finite, >= 0)."""
    try:
        lags = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        lags = [math.nan]
    if not all(math.isfinite(v) and v >= 0 for v in lags):
        from graphslam.errors import ConfigError

        raise ConfigError(f"--lags: {text!r} is not a comma-separated list of latencies >= 0 (s), e.g. 0,1,2")
    return lags


def parse_metric(text: str, option: str = "--metric") -> str:
    """A kNN fingerprint distance (``KnnConfig.metric``), checked before any file is read."""
    from graphslam.core.radiomap.knn import METRICS
    from graphslam.errors import ConfigError

    if text not in METRICS:
        raise ConfigError(f"{option}: {text!r} is not one of {', '.join(METRICS)}")
    return text


def parse_smoothers(text: str) -> list[str]:
    from graphslam.core.tracking.smoother import SMOOTH_METHODS

    names = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in names if v not in SMOOTH_METHODS]
    if bad:
        from graphslam.errors import ConfigError

        raise ConfigError(f"--smoothers: unknown smoother {bad[0]!r}; use {', '.join(SMOOTH_METHODS)}")
    return names


def require_rerun(wanted: object = True) -> None:
    """``--rerun`` / ``graphslam view`` without rerun-sdk: one line naming the extra, before any work."""
    if wanted:
        from graphslam.errors import require_extra

        require_extra("rerun", "Rerun recordings (--rerun, graphslam view)")


def require_plots(wanted: object = True) -> None:
    """A plot asked for without matplotlib: one line naming the extra, before any work."""
    if wanted:
        from graphslam.errors import require_extra

        require_extra("matplotlib", "plots")
