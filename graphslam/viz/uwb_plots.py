"""UWB figures (matplotlib, headless): the site of Paper 003's Fig. 5 and its Fig. 8."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.io.atomic import atomic_open
from graphslam.viz.plots import _figure

# Fig. 8's colours: trilateration green, no measurement red; ours for the two range kinds
TYPE_COLOURS = {"none": "tab:red", "neighbour": "tab:orange", "anchor": "tab:blue", "trilateration": "tab:green"}


def _save(fig, path: str | Path) -> Path:  # type: ignore[no-untyped-def]
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    return Path(path)


def zones_map(
    walls: NDArray,
    zones: Sequence[tuple[float, float]],
    zone_names: Sequence[str],
    anchors: NDArray,
    true_paths: Sequence[NDArray],
    estimates: Sequence[NDArray],
    path: str | Path,
    title: str = "",
) -> Path:
    """Walls, zones, anchors (site frame m), true paths (grey) and estimates (one colour per tag)."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(10, 3.2), dpi=120)
    for x1, y1, x2, y2 in np.asarray(walls):
        ax.plot([x1, x2], [y1, y2], color="black", lw=1.5)
    for (x0, x1), name in zip(zones, zone_names):
        ax.text((x0 + x1) / 2, -0.6, name, ha="center", va="top", fontsize=8)
    for p in true_paths:
        ax.plot(p[:, 0], p[:, 1], color="0.75", lw=2.5, zorder=1)
    for k, e in enumerate(estimates):
        ax.plot(e[:, 0], e[:, 1], ".", ms=1.5, color=f"C{k % 10}", zorder=2)
    a = np.asarray(anchors)
    ax.plot(a[:, 0], a[:, 1], "^", color="black", ms=7, label="anchors", zorder=3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_title(title, fontsize=9)
    out = _save(fig, path)
    plt.close(fig)
    return out


def error_over_time(
    t_s: NDArray,
    err_m: NDArray,
    kind: NDArray,
    tag: NDArray,
    type_names: Sequence[str],
    tag_names: Sequence[str],
    path: str | Path,
    title: str = "",
) -> Path:
    """Paper 003's Fig. 8: tracking error at every slot, coloured by the slot's measurement type,
    one row per tag (log scale: centimetres and metres on one axis)."""
    plt = _figure()
    n = len(tag_names)
    fig, axes = plt.subplots(n, 1, figsize=(9, 1.25 * n + 0.6), dpi=120, sharex=True)
    axes = np.atleast_1d(axes)
    for i, ax in enumerate(axes):
        sel = tag == i
        for k, name in enumerate(type_names):
            m = sel & (kind == k)
            if m.any():
                ax.plot(t_s[m], np.maximum(err_m[m], 1e-3), ".", ms=2, color=TYPE_COLOURS.get(name, "k"), label=name)
        ax.set_yscale("log")
        ax.set_ylim(5e-3, 20)
        ax.axhline(0.1, color="grey", lw=0.6, ls="--")
        ax.set_ylabel(tag_names[i], fontsize=7)
        ax.tick_params(labelsize=7)
    handles = [plt.Line2D([], [], ls="", marker="o", color=TYPE_COLOURS[n_], label=n_) for n_ in type_names]
    axes[0].legend(handles=handles, ncol=4, fontsize=7, loc="upper left")
    axes[-1].set_xlabel("time (s); error (m), dashed: 10 cm")
    axes[0].set_title(title, fontsize=9)
    out = _save(fig, path)
    plt.close(fig)
    return out
