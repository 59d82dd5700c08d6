"""One exception hierarchy for the whole package.

Library code raises these; only the CLI (``graphslam.cli``) catches them, prints
one line and exits non-zero.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType


class GraphSlamError(Exception):
    """Base class of every error graphslam raises on purpose."""


class InputError(GraphSlamError):
    """A recording (or other input file) is unreadable or breaks the data contract.

    The message always names the file and, where known, the topic and field.
    """

    def __init__(
        self,
        path: str | Path,
        problem: str,
        *,
        topic: str | None = None,
        field: str | None = None,
    ) -> None:
        self.path = str(path)
        self.topic = topic
        self.field = field
        self.problem = problem
        where = self.path
        if topic:
            where += f" [topic {topic}]"
        if field:
            where += f" [field {field}]"
        super().__init__(f"{where}: {problem}")


class ConfigError(GraphSlamError):
    """A configuration file or option is invalid (unknown key, wrong type, bad value)."""


class SolverError(GraphSlamError):
    """The factor graph could not be built or optimised (e.g. nothing to align)."""


class RadioMapError(GraphSlamError):
    """A radio map file is unreadable, or a query cannot be answered with it."""


class QueryError(GraphSlamError):
    """A localisation query is malformed (empty, no known access point, ...)."""


class SimulationError(GraphSlamError):
    """The simulator cannot produce the requested survey (inconsistent floor plan or walk)."""


class VisualizationError(GraphSlamError):
    """A Rerun recording could not be written or a viewer could not be started."""


class EstimationError(GraphSlamError):
    """A filter or an access-point fit cannot run (inconsistent model, covariance lost, no usable data)."""


class OutputError(GraphSlamError):
    """An output file or folder cannot be written (permissions, not a folder, disk full)."""


class ServiceError(GraphSlamError):
    """The HTTP service cannot start: e.g. its address is taken or not this machine's."""


class MissingExtraError(GraphSlamError):
    """A feature needs an optional dependency that is not installed (``pip install "graphslam[EXTRA]"``)."""


# the optional dependencies by extra (pyproject.toml's [project.optional-dependencies])
EXTRAS = {"rerun": "rerun", "distributed": "batch", "dask": "batch", "matplotlib": "plots"}


def require_extra(module: str, purpose: str) -> ModuleType:
    """``module`` imported, or ``MissingExtraError`` naming the extra to install: one line, exit 2."""
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        raise MissingExtraError(
            f"{purpose} needs {top}, an optional dependency: pip install \"graphslam[{EXTRAS[top]}]\""
        ) from None
