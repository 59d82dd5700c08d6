"""The library functions behind the commands that touch files (survey pipeline, benchmarks, locate,
track, demo): the only callers of ``graphslam.core`` that read or write files."""
