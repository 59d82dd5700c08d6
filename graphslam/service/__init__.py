"""HTTP query service for radio maps (FastAPI): ``create_app``, ``serve``."""

from graphslam.service.app import create_app

__all__ = ["create_app"]
