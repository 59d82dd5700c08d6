"""UWB ranging (Paper 003, collaborative localisation with a minimal set of anchors).

- ``ranging``: two-way ranging (eq. 4-6), trilateration, planar ranges to raised anchors;
- ``motion``: where a walker is between two steps (the stride model ranges are attached with);
- ``ekf``: the paper's collaborative EKF (section IV-C) for many tags at once;
- ``factors``: survey range factors, native GTSAM (anchor and peer ranges, robust loss);
- ``initialise``: placing walks from ranges (windowed rigid fits, never ground truth);
- ``nlos``: one-sided NLOS rejection by a UWB-only solve;
- ``survey``: the one hook ``graphslam.core.survey.align`` calls (``uwb_terms``).

The network layer (clock sync, TDMA, slot execution) is simulated in ``graphslam.sim.uwb``.
"""
