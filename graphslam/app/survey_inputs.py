"""What one survey is given besides its configuration, as one object: ``SurveyInputs``.

``graphslam survey``, ``survey-batch`` (``graphslam.app.batch``), ``bench real``
(``graphslam.app.bench_real``) and library callers build one and hand it to
``graphslam.app.survey.run_survey(inputs, config)``; a new kind of input is a field here, read and
checked (before the work) in ``run_survey``. A module of its own, free of numpy, so that
``survey-batch`` can import it before any of the work's libraries.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

CONTROL_POINTS_FILE = "control_points.csv"  # in a floor folder: that floor's control points (survey-batch, bench real)
REFERENCE_MAP_FILE = "reference_map.csv"  # in a floor folder: a surveyed radio map of that floor (survey-batch, bench real)
FLOOR_PLAN_FILE = "floor_image.png"  # in a floor folder: its plan, under survey.png (survey-batch; the ILC layout)

ControlPoints = Mapping[str, tuple[float, float]]  # landmark id -> site (x, y), metres


@dataclass(frozen=True, eq=False)
class SurveyInputs:
    """A survey's inputs (what it reads) and outputs (where it writes); paths as ``Path``.

    Read:

    - ``recordings``: ``.mcap`` files or folders of them (a folder: the files directly in it);
    - ``control_points``: a ``landmark_id,x,y`` CSV file (``graphslam.io.control_points``) or its
      content, landmark id -> site (x, y) in metres; the landmarks of these ids, where a walk marks
      them on /landmarks, tie the main map to the site frame (at least one must be marked);
    - ``reference_map``: a surveyed radio map of the floor in the site frame (a CSV
      ``fingerprint_id,x,y,bssid,rssi_dbm`` or a site-frame ``radio_map.parquet``,
      ``graphslam.io.reference_map``), held fixed: the walks that match it are placed on it;
    - ``floor_plan``: an image drawn under survey.png and in Rerun; ``floor_size``: its (W, H) in
      metres (None: ``floor_info.json`` beside the image);
    - ``previous``: a previous output folder of this floor (``survey --update``): walks solved
      there start from their solution and only the new walks' neighbourhood is re-solved.

    Written:

    - ``out``: the output folder, replaced as one set (None: no files, the result only);
    - ``rerun``: also log the survey to this ``.rrd`` file;
    - ``picture``: survey.png into ``out``; ``surveyed``: also radio_map_surveyed.parquet
      (fingerprints at their ground-truth poses, for evaluation).
    """

    recordings: tuple[Path, ...]
    out: Path | None = None
    control_points: Path | ControlPoints | None = None
    reference_map: Path | None = None
    floor_plan: Path | None = None
    floor_size: tuple[float, float] | None = None
    previous: Path | None = None
    rerun: Path | None = None
    picture: bool = True
    surveyed: bool = False

    def __post_init__(self) -> None:
        # one path or several, as str or Path: held as a tuple of Path
        rec = self.recordings
        paths = (rec,) if isinstance(rec, (str, Path)) else tuple(rec)
        object.__setattr__(self, "recordings", tuple(Path(p) for p in paths))
        for name in ("out", "reference_map", "floor_plan", "previous", "rerun"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, Path(v))
        cp = self.control_points
        if isinstance(cp, str):
            object.__setattr__(self, "control_points", Path(cp))
        elif cp is not None and not isinstance(cp, Path):
            object.__setattr__(self, "control_points", dict(cp))  # a copy: the inputs do not change under the run
        if self.floor_size is not None:
            object.__setattr__(self, "floor_size", tuple(self.floor_size))

    @classmethod
    def from_paths(cls, recordings: str | Path | Sequence[str | Path], out: str | Path | None = None,
                   **options: Any) -> SurveyInputs:
        """``SurveyInputs(recordings, out, **options)``: one path or several, ``str`` or ``Path``."""
        return cls(recordings, out, **options)  # type: ignore[arg-type]

    @classmethod
    def for_floor(cls, folder: str | Path, out: str | Path | None = None, *, update: bool = False,
                  **options: Any) -> SurveyInputs:
        """A floor folder's recordings as ``survey-batch`` surveys them: with the folder's
        ``control_points.csv`` and ``reference_map.csv`` when it holds them, and its ``floor_image.png``
        under the picture when ``floor_info.json`` (its size) is beside it; ``update``: seeded by the
        previous output in ``out`` when there is one (``survey --update``; none: a full survey)."""
        from graphslam.io.floor_plan import FLOOR_INFO_FILE
        from graphslam.io.survey_state import STATE_FILE

        folder = Path(folder)
        cp, ref, plan = folder / CONTROL_POINTS_FILE, folder / REFERENCE_MAP_FILE, folder / FLOOR_PLAN_FILE
        previous = Path(out) if update and out is not None and (Path(out) / STATE_FILE).is_file() else None
        found = {"control_points": cp if cp.is_file() else None, "reference_map": ref if ref.is_file() else None,
                 "floor_plan": plan if plan.is_file() and (folder / FLOOR_INFO_FILE).is_file() else None}
        return cls((folder,), out, **{**found, "previous": previous, **options})
