"""What the core sub-packages share: SE(2) geometry, the odometry (IMU-between) factors and array helpers.

The core sub-packages depend in one direction: ``common`` (and ``types``, ``progress``,
``summary``) <- ``radiomap`` <- ``uwb`` <- ``survey``; ``tracking`` sits beside ``survey`` on
``radiomap``. Nothing here imports a sub-package (``tests/test_layers.py`` checks it).
"""
