"""The paper's alignment (Paper 004, section III): fingerprints on step nodes, WiFi-vicinity edges,
initial placement, native GTSAM factors, chain compression, Levenberg-Marquardt, evaluation."""
