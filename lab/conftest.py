"""What the lab's tests share: the repository and the real data's folder (tests skip without it)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data"))


def needs_data(sub: str) -> Any:
    return pytest.mark.skipif(not (DATA / sub).exists(), reason=f"real data {DATA / sub} not present")
