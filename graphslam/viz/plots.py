"""Static figures (matplotlib, headless): the paper's fig. 7 histogram and fig. 8 CDF."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.survey.evaluate import HIST_BIN_M, Evaluation
from graphslam.io.atomic import atomic_open


def _figure():  # type: ignore[no-untyped-def]
    from graphslam.errors import require_extra

    matplotlib = require_extra("matplotlib", "plots")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def landmark_histogram(ev: Evaluation, path: str | Path, title: str = "Landmark errors") -> Path:
    """Histogram of landmark errors (as the paper's fig. 7)."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    h = ev.landmarks.histogram
    ax.bar([b for b, _ in h], [c for _, c in h], width=HIST_BIN_M, align="edge", edgecolor="black")
    lm = ev.landmarks
    ax.set_xlabel("error (m)")
    ax.set_ylabel("marks")
    ax.set_title(f"{title}: n={lm.n}, mean {lm.mean_m:.2f} m, max {lm.max_m:.2f} m")
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)


def error_cdf(errors: Mapping[str, NDArray], path: str | Path, title: str = "Positioning error CDF") -> Path:
    """Empirical CDFs of positioning errors, one curve per label (as the paper's fig. 8)."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for label, e in errors.items():
        e = np.sort(np.asarray(e, float))
        ax.step(e, np.arange(1, len(e) + 1) / len(e), where="post", label=f"{label} (P<10 m = {np.mean(e < 10):.2f})")
    ax.axvline(10.0, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("positioning error (m)")
    ax.set_ylabel("CDF")
    ax.set_xlim(left=0)
    ax.set_ylim(0, 1.01)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title(title)
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)
