"""Benchmarks on simulated and public data (``python -m lab.bench --help``): accuracy and speed of
the survey on the simulator, scale, ``survey --update`` and ``survey-batch``, the paper's fig. 8,
the filter papers' cart, tracking on simulated walks, UJIIndoorLoc, UWB."""
