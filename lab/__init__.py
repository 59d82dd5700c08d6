"""The lab: experiments, diagnostics and benchmarks on simulated and public data. Not installed
(``pip install .`` ships ``graphslam`` only); run from the repository root, e.g. ``python -m
lab.bench accuracy paper``. Lab code imports the public API only (``import graphslam``)."""
