#!/usr/bin/env python3
"""The shape of the recorded magnetic field (``/phone/magnetic``), real or simulated, side by side.

Per folder of recordings, one JSON line: the east component's spread (the orientation's azimuth
error: the horizontal part points north by construction), the medians of the horizontal magnitude
and the vertical component, their std along a walk (median over walks), the rms of 10 m stretches
(features |B|, |B_h|, B_up resampled every 0.5 m of the dead-reckoned path, each stretch's mean
removed; percentiles over stretches every 2 m) and the along-path autocorrelation of |B_h| and B_up
(each walk's mean removed). No ground truth. How the simulator's defaults were chosen
(docs/simulator.md, "Magnetic field"):

    python lab/simulator/magnetic_field_shape.py ../shared/data/ipin2023/b100_f-2 SIMULATED_FOLDER
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from graphslam import read_survey

SAMPLE_M, WINDOW_M, STRIDE_M = 0.5, 10.0, 2.0
LAGS_M = (0.5, 1.0, 2.0, 3.0, 4.0)


def _along_path(sess) -> np.ndarray | None:  # type: ignore[no-untyped-def]
    """(Q, 3) |B|, |B_h|, B_up every SAMPLE_M of the dead-reckoned path (a message at its step)."""
    m = sess.magnetic
    if m is None or len(m) < 10:
        return None
    t = sess.steps.t_ns
    k = np.clip(np.searchsorted(t, m.t_ns), 0, len(t) - 1)
    xy = np.asarray(sess.steps.xy)[k]
    d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    keep = np.concatenate([[True], np.diff(d) > 1e-6])  # standing still: one place
    d, b = d[keep], m.enu[keep]
    f = np.column_stack([np.linalg.norm(b, axis=1), np.hypot(b[:, 0], b[:, 1]), b[:, 2]])
    q = np.arange(0.0, d[-1], SAMPLE_M)
    return np.column_stack([np.interp(q, d, f[:, c]) for c in range(3)]) if len(q) > 1 else None


def shape(folder: str) -> dict:
    survey = read_survey([folder])
    east, h_med, u_med, h_std, u_std, rms = [], [], [], [], [], []
    acf = np.zeros((2, len(LAGS_M) + 1))
    n_acf = np.zeros(len(LAGS_M) + 1)
    L, st = int(WINDOW_M / SAMPLE_M), int(STRIDE_M / SAMPLE_M)
    for sess in survey:
        if sess.magnetic is None:
            continue
        b = sess.magnetic.enu
        east.append(b[:, 0])
        h_med.append(np.median(np.hypot(b[:, 0], b[:, 1])))
        u_med.append(np.median(b[:, 2]))
        f = _along_path(sess)
        if f is None:
            continue
        h_std.append(f[:, 1].std())
        u_std.append(f[:, 2].std())
        for i in range(0, len(f) - L + 1, st):
            w = f[i : i + L] - f[i : i + L].mean(axis=0)
            rms.append(float(np.sqrt((w * w).mean())))
        c = f[:, 1:] - f[:, 1:].mean(axis=0)
        for j, lag in enumerate((0.0, *LAGS_M)):
            k = int(round(lag / SAMPLE_M))
            if len(c) - k > 5:
                acf[:, j] += (c[: len(c) - k] * c[k:]).mean(axis=0)
                n_acf[j] += 1
    e = np.concatenate(east)
    acf = acf / n_acf
    acf = acf / acf[:, :1]
    return {
        "folder": folder,
        "walks": len(h_med),
        "east_std_ut": round(float(e.std()), 2),
        "horizontal_median_ut": round(float(np.median(h_med)), 1),
        "up_median_ut": round(float(np.median(u_med)), 1),
        "walk_std_horizontal_ut": round(float(np.median(h_std)), 2),
        "walk_std_up_ut": round(float(np.median(u_std)), 2),
        "stretch_rms_ut_p10_p50_p90": [round(float(v), 2) for v in np.percentile(rms, [10, 50, 90])],
        "stretch_rms_p90_over_p10": round(float(np.percentile(rms, 90) / np.percentile(rms, 10)), 2),
        "autocorr_lags_m": list(LAGS_M),
        "autocorr_horizontal": [round(float(v), 2) for v in acf[0, 1:]],
        "autocorr_up": [round(float(v), 2) for v in acf[1, 1:]],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+")
    for folder in ap.parse_args().folders:
        print(json.dumps(shape(folder)), flush=True)


if __name__ == "__main__":
    main()
