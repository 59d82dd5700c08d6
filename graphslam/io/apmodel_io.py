"""AP path-loss models beside a radio map: JSON, written atomically."""

from __future__ import annotations

import json
from pathlib import Path

from graphslam.core.tracking.apmodel import ApModels
from graphslam.errors import InputError
from graphslam.io.atomic import atomic_write_json


def write_ap_models(models: ApModels, path: str | Path) -> Path:
    """JSON, written atomically (the file is complete or absent)."""
    atomic_write_json(path, models.as_dict())
    return Path(path)


def read_ap_models(path: str | Path) -> ApModels:
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read AP models: {e}") from None
    try:
        return ApModels.from_dict(d)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"malformed AP models ({e})") from None
