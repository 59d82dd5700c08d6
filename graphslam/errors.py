"""One exception hierarchy for the whole package.

Library code raises these; only the CLI (``graphslam.cli``) catches them, prints
one line and exits non-zero.
"""

from __future__ import annotations

from pathlib import Path


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
