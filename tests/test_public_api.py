"""The package's public API (graphslam/__init__.py): what it promises and that it stays cheap."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_import_is_lazy_and_names_resolve_to_their_definitions():
    # `import graphslam` must not pull in GTSAM / pyarrow (CLI start-up, service workers); the
    # first use of a name imports its module, and the object is the library's own.
    code = (
        "import sys, graphslam as gs\n"
        "heavy = [m for m in ('gtsam', 'pyarrow', 'rerun', 'scipy') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "from graphslam.core.survey.align import align\n"
        "from graphslam.core.tracking.smoother import smooth\n"
        "assert gs.align is align and gs.smooth is smooth\n"
        "assert issubclass(gs.EstimationError, gs.GraphSlamError)\n"
        "missing = [n for n in gs.__all__ if not hasattr(gs, n)]\n"
        "assert not missing, missing\n"
        "print(gs.__version__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip()


def test_unknown_name_is_an_attribute_error():
    import graphslam

    with pytest.raises(AttributeError, match="no attribute 'alighn'"):
        graphslam.alighn  # noqa: B018
