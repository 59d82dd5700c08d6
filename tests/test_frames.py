"""One frame name per survey: every file and answer made from a survey names the frame its
report.json names (``earth`` with the phones' headings, ``site`` with control points or UWB
anchors): the radio map's metadata, trajectories.csv, aligned.mcap, the CSVs and JSON lines of
``locate`` and ``track`` (their error figures too), ap_models.json, the pictures (their ``frame``
text chunk and title), the service's answers and heatmaps. Real commands on simulated recordings."""

from __future__ import annotations

import csv
import io
import json
import re
from pathlib import Path

import httpx
import pyarrow.parquet as pq
import pytest
from conftest import run_cli
from mcap.reader import make_reader
from PIL import Image

from graphslam.names import FRAMES

ALL = ("headings", "control_points", "uwb")


def _other_frames_named(text: str, frame: str) -> list[str]:
    """The other frame names a text calls "<name> frame" (a picture's title, a note)."""
    return [f for f in FRAMES if f != frame and re.search(rf"\b{f} frame", text)]


def _png(path: Path) -> dict[str, str]:
    with Image.open(path) as im:
        return dict(im.text)


def _csv_frames(path: Path, column: str = "frame") -> set[str]:
    with open(path, newline="", encoding="utf-8") as fh:
        return {row[column] for row in csv.DictReader(fh)}


@pytest.fixture(scope="module")
def surveys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Path, Path]]:
    """kind -> (recordings, held-out walks, survey folder): paper with headings; paper with four of
    its landmarks named control points; the UWB crowd with four anchors."""
    from graphslam.io.mcap_reader import read_survey
    from graphslam.sim import simulate
    from graphslam.sim.uwb.scenarios import CrowdUwb, simulate_crowd

    root = tmp_path_factory.mktemp("frames")
    paper = simulate("paper", seed=0, test_walks=1)
    paper.write(root / "paper")
    marks: dict[str, tuple[float, float]] = {}
    for s in read_survey(sorted((root / "paper").glob("*.mcap"))):
        for m in s.landmarks:
            marks.setdefault(m.landmark_id, (m.x, m.y))
    cp = root / "control_points.csv"
    cp.write_text("landmark_id,x,y\n" + "".join(f"{k},{x},{y}\n" for k, (x, y) in list(marks.items())[:4]))
    crowd = simulate_crowd(1, CrowdUwb(n_walkers=4, duration_min=(2.0, 2.5)))
    crowd.write(root / "uwb")
    out = {}
    for kind, rec, extra in (("headings", root / "paper", []), ("control_points", root / "paper", ["--control-points", str(cp)]),
                             ("uwb", root / "uwb", [])):
        folder = root / f"out_{kind}"
        assert run_cli(["-q", "survey", *sorted(map(str, rec.glob("*.mcap"))), "--out", str(folder), *extra]) == 0
        held_out = root / "paper" / "test" if kind != "uwb" else next(iter(sorted(rec.glob("*.mcap"))))
        out[kind] = (rec, held_out, folder)
    return out


@pytest.mark.parametrize("kind", ALL)
def test_every_survey_output_names_the_reports_frame(surveys: dict, kind: str) -> None:
    rec, _, d = surveys[kind]
    report = json.loads((d / "report.json").read_text())
    frame = report["frame"]
    assert frame == ("earth" if kind == "headings" else "site")
    assert report["frame_description"].startswith(f"{frame}:")
    # the radio map's metadata (what locate, serve, track and fit-aps read it by)
    meta = json.loads(pq.read_schema(d / "radio_map.parquet").metadata[b"graphslam.radio_map"])
    assert meta["frame"] == frame
    # the magnetic map beside it (the simulated walks carry the field; the UWB crowd's may not)
    mag = d / "magnetic_map.parquet"
    assert mag.is_file() or kind == "uwb"
    if mag.is_file():
        assert json.loads(pq.read_schema(mag).metadata[b"graphslam.magnetic_map"])["frame"] == frame
    # trajectories.csv: component 0 in the report's frame, on every row
    assert _csv_frames(d / "trajectories.csv") == {frame}
    with open(d / "aligned.mcap", "rb") as fh:
        ids = {json.loads(m.data)["frame_id"] for _, _, m in make_reader(fh).iter_messages()}
    assert ids == {frame}
    # survey.png: its frame chunk, its title naming this frame and no other
    text = _png(d / "survey.png")
    assert text["frame"] == frame and f"{frame} frame" in text["Title"], text
    assert not _other_frames_named(text["Title"], frame), text["Title"]
    # plot's radio_map.png (and survey.png redrawn from the folder)
    assert run_cli(["-q", "plot", str(d), "--recordings", str(rec)]) == 0
    for name in ("radio_map.png", "survey.png") + (("magnetic_map.png",) if mag.is_file() else ()):
        text = _png(d / name)
        assert text["frame"] == frame and f"{frame} frame" in text["Title"], (name, text)
        assert not _other_frames_named(text["Title"], frame), (name, text["Title"])
    # fit-aps: the models are in the map's frame
    assert run_cli(["-q", "fit-aps", "--radio-map", str(d / "radio_map.parquet")]) == 0
    assert json.loads((d / "ap_models.json").read_text())["frame"] == frame


@pytest.mark.parametrize("kind", ALL)
def test_locate_and_track_answer_in_the_reports_frame(
    surveys: dict, kind: str, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _, held_out, d = surveys[kind]
    frame = json.loads((d / "report.json").read_text())["frame"]
    rm = str(d / "radio_map.parquet")
    capsys.readouterr()
    assert run_cli(["-q", "locate", "--radio-map", rm, str(held_out), "-o", str(tmp_path / "pos.csv")]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["frame"] == frame and line["errors"]["frame"] == frame, line
    assert _csv_frames(tmp_path / "pos.csv") == {frame}
    text = _png(tmp_path / "pos.png")
    assert text["frame"] == frame and not _other_frames_named(text["Title"], frame), text
    assert run_cli(["-q", "track", str(held_out), "--radio-map", rm, "-o", str(tmp_path / "track.csv"),
                    "--filter", "ekf", "--no-self-calibrate"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["frame"] == frame and line["errors"]["frame"] == frame, line
    # the error figures say how the answers met the truth, in words that do not rename the frame
    assert not _other_frames_named(line["errors"]["site_from_map"], frame)
    assert _csv_frames(tmp_path / "track.csv") == {frame}
    text = _png(tmp_path / "track.png")
    assert text["frame"] == frame and not _other_frames_named(text["Title"], frame), text


@pytest.mark.parametrize("kind", ALL)
def test_the_service_answers_in_the_reports_frame(surveys: dict, kind: str) -> None:
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.service.app import create_app
    from graphslam.service.server import start_background_server

    _, _, d = surveys[kind]
    frame = json.loads((d / "report.json").read_text())["frame"]
    rm = read_radio_map(d / "radio_map.parquet")
    bssid = rm.bssids[0]
    with start_background_server(create_app(rm)) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        r = c.post("/v1/locate", json={"readings": {bssid: -60.0}})
        assert r.status_code == 200 and r.json()["frame"] == frame
        assert c.get("/v1/radio-map").json()["frame"] == frame
        png = c.get(f"/v1/heatmap/{bssid}.png")
        assert png.status_code == 200
        with Image.open(io.BytesIO(png.content)) as im:
            assert im.text["frame"] == frame
