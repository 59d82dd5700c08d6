"""Figures of the filter papers' experiment (matplotlib, headless): path, |error| x/y, trace(P)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graphslam.io.atomic import atomic_open


def cart_figure(
    t_s: NDArray, truth_xy: NDArray, est_xy: NDArray, trace_p: NDArray, path: str | Path, title: str
) -> Path:
    """Three panels as the papers' figs. 9/7 (path), 10/8 (|error| in x and y) and 12/10 (trace P)."""
    from graphslam.viz.plots import _figure

    plt = _figure()

    fig, ax = plt.subplots(1, 3, figsize=(13, 4), dpi=110)
    ax[0].plot(truth_xy[:, 0], truth_xy[:, 1], "k--", lw=1, label="reference path")
    ax[0].plot(est_xy[:, 0], est_xy[:, 1], lw=0.8, label="estimate")
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("x (m)")
    ax[0].set_ylabel("y (m)")
    ax[0].legend(fontsize=7, loc="center")
    e = np.abs(est_xy - truth_xy)
    ax[1].plot(t_s, e[:, 0], lw=0.8, label=f"x (RMS {np.sqrt(np.mean(e[:, 0] ** 2)):.2f} m)")
    ax[1].plot(t_s, e[:, 1], lw=0.8, label=f"y (RMS {np.sqrt(np.mean(e[:, 1] ** 2)):.2f} m)")
    ax[1].set_xlabel("time (s)")
    ax[1].set_ylabel("absolute error (m)")
    ax[1].legend(fontsize=7)
    ax[2].semilogy(t_s, trace_p, lw=0.8)
    ax[2].set_xlabel("time (s)")
    ax[2].set_ylabel("trace(P)")
    for a in ax:
        a.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)
