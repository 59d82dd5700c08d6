"""Option parsing shared by the command modules (and the lab's commands): the survey configuration
from --config/--set, latencies, smoothers, kNN metrics; help texts used by several commands.
Each parser raises ``ConfigError`` (one line, exit code 2) before any file is read."""

from __future__ import annotations

import math
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any, List, Optional, Sequence

from graphslam import names

if TYPE_CHECKING:
    from graphslam.config import GraphSlamConfig


def choices(name: str, values: Sequence[str]) -> Any:
    """A ``str`` enum of ``values`` as an option's type: typer lists them in ``--help``
    (``<sorensen|eq9>``) and refuses any other value with one line naming the option."""
    return Enum(name, {v: v for v in values}, type=str)


def plain(value: Any) -> Any:
    """An option's value as the library takes it: a choice's string (None and others as they are)."""
    return value.value if isinstance(value, Enum) else value


Metric = choices("Metric", names.METRICS)
Index = choices("Index", names.INDEXES)

def config_from_options(config: Optional[Path], set_: Optional[List[str]]) -> "GraphSlamConfig":
    """Config file (partial files merge over the defaults) plus ``--set a.b=value`` overrides."""
    from graphslam.config import load_config, parse_overrides

    return load_config(config, parse_overrides(set_))


INDEX_HELP = (
    "kNN search: auto (the approximate IVF index from 5,000 references, exact below), exact (every reference "
    "scored) or ivf (docs/radio_map.md)."
)


IVF_CLUSTERS_HELP = "IVF: k-means clusters (default ~2 sqrt(N))."


IVF_PROBES_HELP = "IVF: clusters searched per query (default 8)."


METRIC_HELP = (
    "Fingerprint distance: sorensen (Sørensen on powed RSS, Torres-Sospedra 2015: the better on every data set "
    "measured, docs/radio_map.md) or eq9 (the paper's RMS dB difference)."
)


K_HELP = "Neighbours (k)."


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
