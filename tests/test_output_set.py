"""`graphslam survey --out`: the folder is always one consistent set of files.

Re-running into a used folder leaves no earlier run's own file (radio_map_surveyed.parquet) and
rebuilds the files other commands added (fit-aps' ap_models.json, plot's radio_map.png) for the
new map; nothing track writes lands there; a folder holding anything else, the input folder, or
a folder inside it is refused before any work; a failure while writing or during the final
rename leaves the previous set exactly as it was and nothing staged behind.
"""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import pytest
from test_align import two_walks

import graphslam.io.atomic as atomic
from graphslam.cli import main
from graphslam.core.types import PoseTrack, Session
from graphslam.io.mcap_writer import write_session


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("rec")
    for s in two_walks():
        write_session(s, d / f"{s.session_id}.mcap")
    return d


def survey(rec: Path, out: Path, *extra: str) -> None:
    main(["survey", str(rec), "--out", str(out), "--no-progress", "--set", "wifi.d_min_m=0.5", *extra])


def fails(capsys: pytest.CaptureFixture[str], *args: object) -> str:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    lines = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(lines) == 1, lines
    return lines[0]


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def no_leftovers(parent: Path) -> bool:
    return not [p.name for p in parent.iterdir() if p.name.startswith(".")]


def test_rerun_replaces_the_whole_set_and_track_refits_stale_models(
    recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    out = tmp_path / "out"
    survey(recordings, out, "--surveyed")
    main(["fit-aps", "--radio-map", str(out / "radio_map.parquet"), "--min-readings", "5"])
    first = snapshot(out)
    assert {"radio_map_surveyed.parquet", "ap_models.json"} <= set(first)

    survey(recordings, out, "--set", "wifi.d_max_m=25")  # another run: no --surveyed
    second = snapshot(out)
    assert set(second) == {  # the survey's own file it did not write this time is gone; fit-aps' is rebuilt
        "trajectories.csv", "aligned.mcap", "radio_map.parquet", "wifi_edges.parquet", "config.yaml", "report.json",
        "survey.png", "survey_state.npz", "recordings_cache.npz", "ap_models.json",
    }
    assert second["config.yaml"] != first["config.yaml"] and b"d_max_m: 25" in second["config.yaml"]
    assert no_leftovers(tmp_path)
    from graphslam.io.apmodel_io import read_ap_models, read_fit_config
    from graphslam.io.radiomap_io import read_radio_map

    assert second["ap_models.json"] != first["ap_models.json"]
    read_ap_models(out / "ap_models.json", radio_map=read_radio_map(out / "radio_map.parquet"))  # the new map's
    assert read_fit_config(out / "ap_models.json").min_readings == 5  # refitted as fit-aps was told
    derived = json.loads(second["report.json"])["derived_files"]
    assert derived == {"ap_models.json": {"written_by": "fit-aps", "status": "rebuilt"}}

    # ap_models.json of the first run's map put back beside the second run's map: never used silently
    (out / "ap_models.json").write_bytes(first["ap_models.json"])
    assert first["radio_map.parquet"] != second["radio_map.parquet"]
    a = two_walks().sessions[0]  # a short walk to track: only which models are used matters here
    walk = write_session(Session(a.session_id, PoseTrack(a.steps.t_ns[:20], a.steps.xy[:20], a.steps.heading[:20]),
                                 a.scans[:10]), tmp_path / "short.mcap")
    msg = fails(capsys, "track", walk, "--radio-map", out / "radio_map.parquet", "--out",
                tmp_path / "t.csv", "--ap-models", out / "ap_models.json")
    assert "fitted to another radio map" in msg
    caplog.clear()
    main(["track", str(walk), "--radio-map", str(out / "radio_map.parquet"), "--out",
          str(tmp_path / "t.csv")])
    assert "fitted to another radio map" in caplog.text and "fitting them now" in caplog.text


def test_refused_before_any_work(recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    survey(recordings, out)
    before = snapshot(out)
    (out / "notes.txt").write_text("mine")
    msg = fails(capsys, "survey", recordings, "--out", out, "--no-progress")
    assert "'notes.txt'" in msg and "replaced as a whole" in msg
    (out / "notes.txt").unlink()
    (out / "radio_map.parquet").unlink()
    (out / "radio_map.parquet").mkdir()  # an output name, but a folder: not ours to delete
    assert "'radio_map.parquet'" in fails(capsys, "survey", recordings, "--out", out, "--no-progress")
    (out / "radio_map.parquet").rmdir()
    assert set(snapshot(out)) == set(before) - {"radio_map.parquet"}

    assert "is the input folder" in fails(capsys, "survey", recordings, "--out", recordings)
    assert "inside the input folder" in fails(capsys, "survey", recordings, "--out", recordings / "out")
    assert "holds the input" in fails(capsys, "survey", recordings, "--out", recordings.parent)
    if importlib.util.find_spec("rerun") is not None:  # without the rerun extra, that is the one line
        assert "--out" in fails(capsys, "survey", recordings, "--out", out, "--rerun", out / "s.rrd")
    assert sorted(p.name for p in recordings.iterdir()) == ["a.mcap", "b.mcap"]


@pytest.mark.parametrize("where", ["writing", "the radio map beside the other files", "final exchange", "final rename"])
def test_a_failure_leaves_the_previous_set(
    recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, where: str
) -> None:
    out = tmp_path / "out"
    survey(recordings, out)
    before = snapshot(out)
    if where == "writing":
        import graphslam.app.survey as app_survey

        def broken(*a: object, **k: object) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(app_survey, "write_aligned", broken)
        msg = fails(capsys, "survey", recordings, "--out", out, "--no-progress", "--set", "wifi.d_max_m=25")
        assert "cannot write the outputs (No space left on device)" in msg
    elif where == "the radio map beside the other files":  # built in a worker thread while they are written
        import graphslam.core.survey.radio_maps as radio_maps

        def failing(*a: object, **k: object) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(radio_maps, "crowdsourced_radio_map", failing)
        msg = fails(capsys, "survey", recordings, "--out", out, "--no-progress", "--set", "wifi.d_max_m=25")
        assert "cannot write the outputs (No space left on device)" in msg
    elif where == "final exchange":  # the one-step swap (Linux renameat2)
        def exchange(a: Path, b: Path) -> bool:
            raise OSError(5, "Input/output error")

        monkeypatch.setattr(atomic, "exchange", exchange)
        msg = fails(capsys, "survey", recordings, "--out", out, "--no-progress", "--set", "wifi.d_max_m=25")
        assert "cannot replace the output folder" in msg and "Input/output error" in msg
    else:  # the two renames where there is no exchange
        monkeypatch.setenv("GRAPHSLAM_NO_EXCHANGE", "1")
        real_rename = os.rename

        def rename(src: object, dst: object) -> None:
            if Path(str(src)).name.startswith(".out.stage-"):  # the swap of the new set into place
                raise OSError(5, "Input/output error")
            real_rename(src, dst)

        monkeypatch.setattr(atomic.os, "rename", rename)
        msg = fails(capsys, "survey", recordings, "--out", out, "--no-progress", "--set", "wifi.d_max_m=25")
        assert "cannot replace the output folder" in msg and "Input/output error" in msg
    assert snapshot(out) == before
    assert json.loads(before["report.json"])["aligned_sessions"] == 2
    assert no_leftovers(tmp_path)


def test_nothing_another_command_wrote_blocks_or_is_lost_in_an_update(
    recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The README's order: survey, fit-aps, plot, track, then an in-place `survey --update`."""
    from graphslam.app.pictures import plot_options
    from graphslam.io.apmodel_io import read_ap_models
    from graphslam.io.radiomap_io import read_radio_map

    out = tmp_path / "out"
    survey(recordings, out)
    main(["fit-aps", "--radio-map", str(out / "radio_map.parquet"), "--min-readings", "5"])
    main(["plot", str(out), "--top-aps", "2", "--recordings", str(recordings)])
    a = two_walks().sessions[0]
    walk = write_session(Session(a.session_id, PoseTrack(a.steps.t_ns[:20], a.steps.xy[:20], a.steps.heading[:20]),
                                 a.scans[:10]), tmp_path / "short.mcap")
    before = snapshot(out)
    main(["-q", "track", str(walk), "--radio-map", str(out / "radio_map.parquet"), "--filter", "ekf", "--no-picture",
          "-o", str(tmp_path / "t.csv")])
    assert snapshot(out) == before  # track writes nothing into the survey's folder
    (out / "track_calibration.json").write_text("{}")  # what an earlier graphslam's track left there
    capsys.readouterr()
    survey(recordings, out, "--update", str(out), "--set", "wifi.d_max_m=25")  # in place: not refused
    after = snapshot(out)
    assert set(before) | {"track_calibration.json"} == set(after)  # nothing deleted
    assert after["track_calibration.json"] == b"{}"  # kept as it was
    read_ap_models(out / "ap_models.json", radio_map=read_radio_map(out / "radio_map.parquet"))  # rebuilt for this map
    assert after["radio_map.png"] != before["radio_map.png"]  # redrawn from the new map ...
    assert plot_options(out / "radio_map.png")["top_aps"] == 2  # ... as plot drew it
    derived = json.loads(after["report.json"])["derived_files"]
    assert {k: v["status"] for k, v in derived.items()} == {
        "ap_models.json": "rebuilt", "radio_map.png": "rebuilt", "track_calibration.json": "kept",
    }
