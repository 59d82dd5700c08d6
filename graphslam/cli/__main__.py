"""``python -m graphslam.cli``: as the ``graphslam`` script."""

from graphslam.cli import entry

entry()
