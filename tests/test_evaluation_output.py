"""What the commands say about accuracy, and what other tools read of their output: locate's
error figures, evaluate on recordings of another survey (one line, exit 2), and `export` in the
TUM / KITTI formats checked as evo reads them (evo itself is not a test dependency: it pulls in
pandas and seaborn; the readers below check what evo's file_interface and trajectory checks do)."""

from __future__ import annotations

import csv
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

from graphslam.cli import main
from graphslam.core.common.geometry import interpolate_xy
from graphslam.io.csv_io import read_trajectory_file
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def surveyed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The paper scenario's 5 walks (+ 2 held out in data/test), surveyed into out/ (component 0: ``_main_walks``)."""
    d = tmp_path_factory.mktemp("export")
    simulate("paper", seed=0, test_walks=2).write(d / "data")
    main(["-q", "survey", str(d / "data"), "--out", str(d / "out"), "--no-picture"])
    return d / "data", d / "out"


def _rows(path: Path, delim: str) -> list[list[str]]:
    """evo's csv_read_matrix: lines starting with '#' skipped, the rest split on one delimiter."""
    with open(path) as f:
        return list(csv.reader((ln for ln in f if not ln.startswith("#")), delimiter=delim))


def read_tum_as_evo(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps s, xyz, quaternions wxyz) with evo's checks: 8 entries per row (no trailing or double
    space), floats, unit quaternions, valid rotations, strictly ascending stamps."""
    raw = _rows(path, " ")
    assert raw and all(len(r) == 8 for r in raw), "TUM trajectory files must have 8 entries per row"
    mat = np.array(raw).astype(float)
    stamps, xyz, quat = mat[:, 0], mat[:, 1:4], np.roll(mat[:, 4:], 1, axis=1)
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0)
    assert np.all(np.diff(stamps) > 0)  # evo: sorted and no duplicates
    return stamps, xyz, quat


def read_kitti_as_evo(path: Path) -> np.ndarray:
    """(N, 4, 4) poses with evo's checks: 12 entries per row, valid SE(3) (R R^T = I, det R = 1)."""
    raw = _rows(path, " ")
    assert raw and all(len(r) == 12 for r in raw), "KITTI pose files must have 12 entries per row"
    m = np.array(raw).astype(float).reshape(-1, 3, 4)
    poses = np.concatenate([m, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (len(m), 1, 4))], axis=1)
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-7) and np.allclose(np.linalg.det(R), 1.0)
    return poses


def _main_walks(out: Path) -> int:
    """Walks of component 0 (report.json), what the exports hold and the truth files follow."""
    return json.loads((out / "report.json").read_text())["components"][0]["n_walks"]


def _export(out: Path, target: Path, *args: str, capsys: pytest.CaptureFixture[str]) -> dict:
    main(["export", str(out), "-o", str(target), *args])
    return json.loads(capsys.readouterr().out)


def test_export_tum_kitti_csv_hold_the_survey_as_evo_reads_it(surveyed, tmp_path, capsys) -> None:
    data, out = surveyed
    traj = read_trajectory_file(out / "trajectories.csv").of_component(0)
    frame = json.loads((out / "report.json").read_text())["frame"]
    res = _export(out, tmp_path / "tum", "--format", "tum", capsys=capsys)
    assert res == {"out": str(tmp_path / "tum"), "walks": len(traj), "files": len(traj), "truth_files": 0, "frame": frame}
    for sid, tr in traj.items():
        stamps, xyz, quat = read_tum_as_evo(tmp_path / "tum" / f"{sid}.tum")
        np.testing.assert_allclose(stamps, tr.t_ns / 1e9, rtol=0, atol=1e-6)  # seconds
        np.testing.assert_allclose(xyz[:, :2], tr.xy, atol=1e-5)
        assert np.all(xyz[:, 2] == 0) and np.all(quat[:, 1:3] == 0)  # planar: a rotation about z
        yaw = 2 * np.arctan2(quat[:, 3], quat[:, 0])
        np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - tr.heading))), 0, atol=1e-6)
    _export(out, tmp_path / "kitti", "--format", "kitti", capsys=capsys)
    _export(out, tmp_path / "csv", "--format", "csv", capsys=capsys)
    for sid, tr in traj.items():
        poses = read_kitti_as_evo(tmp_path / "kitti" / f"{sid}.kitti")
        np.testing.assert_allclose(poses[:, :2, 3], tr.xy, atol=1e-5)
        np.testing.assert_allclose(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]), np.angle(np.exp(1j * tr.heading)), atol=1e-6)
        rows = list(csv.DictReader(io.StringIO((tmp_path / "csv" / f"{sid}.csv").read_text())))
        assert [int(r["t_ns"]) for r in rows] == tr.t_ns.tolist()
        np.testing.assert_allclose([[float(r["x"]), float(r["y"])] for r in rows], tr.xy, atol=1e-5)


def test_export_in_the_site_frame_with_the_truth_beside(surveyed, tmp_path, capsys) -> None:
    data, out = surveyed
    errors = {}
    for frame in ("map", "site"):
        res = _export(out, tmp_path / frame, "--frame", frame, "-r", str(data), capsys=capsys)
        n = _main_walks(out)
        assert n >= 4 and res["truth_files"] == res["walks"] == n
        assert res["frame"] == ("site" if frame == "site" else "earth")
        e = []
        for est in sorted((tmp_path / frame).glob("*[0-9].tum")):
            t, xyz, _ = read_tum_as_evo(est)
            tt, txyz, _ = read_tum_as_evo(est.with_name(est.stem + ".truth.tum"))
            truth = np.column_stack([np.interp(t, tt, txyz[:, 0]), np.interp(t, tt, txyz[:, 1])])
            e.append(np.linalg.norm(xyz[:, :2] - truth, axis=1))
        errors[frame] = np.concatenate(e)
    # the estimate and its truth are in one frame either way: the same errors, and small (the survey's fit)
    np.testing.assert_allclose(errors["map"], errors["site"], atol=1e-4)
    assert errors["site"].mean() < 2.0
    report = json.loads((out / "report.json").read_text())
    no_fit = tmp_path / "no_fit"
    no_fit.mkdir()
    for f in ("trajectories.csv",):
        (no_fit / f).write_bytes((out / f).read_bytes())
    (no_fit / "report.json").write_text(json.dumps({k: v for k, v in report.items() if k != "evaluation"}))
    with pytest.raises(SystemExit) as e:
        main(["export", str(no_fit), "-o", str(tmp_path / "x"), "--frame", "site"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "no site frame for component 0" in err[0]


def test_locate_prints_its_errors_against_the_truth(surveyed, tmp_path, capsys) -> None:
    data, out = surveyed
    main(["-q", "locate", str(data / "test"), "--radio-map", str(out / "radio_map.parquet"), "-o", str(tmp_path / "p.csv"),
          "--no-picture"])
    res = json.loads(capsys.readouterr().out)
    ev = res["errors"]
    assert ev["evaluated"] and ev["frame"] == res["frame"] == "earth" and "landmark fit" in ev["site_from_map"]
    assert ev["truth"]["n"] == res["located"] and 0 < ev["truth"]["median_m"] <= ev["truth"]["p90_m"] <= ev["truth"]["max_m"]
    assert ev["landmarks"]["n"] > 0  # the held-out walks mark landmarks too
    # the figure is what the CSV's answers, placed by the report's fit, are off the truth
    from graphslam.core.common.geometry import se2_apply
    from graphslam.io.mcap_reader import read_survey

    T = np.array(json.loads((out / "report.json").read_text())["evaluation"]["site_from_aligned"])
    truth = {s.session_id: s.ground_truth for s in read_survey([data / "test"])}
    rows = list(csv.DictReader((tmp_path / "p.csv").open()))
    e = [np.linalg.norm(se2_apply(T, np.array([[float(r["x"]), float(r["y"])]]))
                        - interpolate_xy(truth[r["session_id"]], np.array([float(r["t_ns"])]))) for r in rows]
    assert ev["truth"]["mean_m"] == pytest.approx(float(np.mean(e)), abs=2e-3)  # the CSV's 4 decimals


def test_evaluate_on_another_survey_s_recordings_is_one_line_and_exit_2(surveyed, tmp_path, capsys) -> None:
    data, out = surveyed
    other = tmp_path / "other"
    simulate("corridor", seed=3).write(other)
    n = _main_walks(out)
    for recordings, text in ((other, f"none of its {n} walks of component 0"), (data / "test", f"none of its {n} walks")):
        with pytest.raises(SystemExit) as e:
            main(["evaluate", str(out / "trajectories.csv"), str(recordings)])
        cap = capsys.readouterr()
        lines = cap.err.strip().splitlines()
        assert e.value.code == 2 and len(lines) == 1 and text in lines[0] and cap.out == "", lines
    main(["evaluate", str(out / "trajectories.csv"), str(data), "-o", str(tmp_path / "ev.json")])  # its own recordings: figures
    printed = capsys.readouterr().out
    got = json.loads(printed)
    assert got["landmarks"]["n"] > 0
    # printed to the millimetre (as locate's and track's figures), not 16 digits; the file keeps them all
    assert not re.search(r"\d\.\d{4,}", printed), printed
    full = json.loads((tmp_path / "ev.json").read_text())
    assert got["landmarks"]["mean_m"] == round(full["landmarks"]["mean_m"], 3)
