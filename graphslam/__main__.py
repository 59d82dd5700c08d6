from graphslam.cli import entry

entry()
