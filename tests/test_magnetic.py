"""The magnetic field in the survey (core/survey/magnetic.py): sequences along the walked path, window
matches, the threshold from surrogates, loop-verified links, units, factors, the magnetic map and its file."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import T0, pose_body, write_raw_mcap

from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import load_config
from graphslam.core.survey import magnetic as M
from graphslam.core.survey import solver as S
from graphslam.core.types import HeadingTrack, MagneticTrack, PoseTrack, Scan, Session, Survey
from graphslam.errors import InputError, RadioMapError
from graphslam.io.magnetic_map_io import read_magnetic_map, write_magnetic_map
from graphslam.io.mcap_reader import read_session, read_survey
from graphslam.io.mcap_writer import write_session

STEP_M = 0.7
EARTH = math.radians(20.0)  # east/north from the synthetic site frame


class Field:
    """A synthetic building: the Earth's field plus bumps of 1-3 m (µT), a function of the site position."""

    def __init__(self, seed: int = 0, n: int = 140) -> None:
        rng = np.random.default_rng(seed)
        self.c = np.column_stack([rng.uniform(-5, 105, n), rng.uniform(-3, 3, n)])
        self.r = rng.uniform(1.0, 3.0, n)
        self.a = rng.normal(0.0, 6.0, (n, 3))

    def at(self, xy: np.ndarray) -> np.ndarray:
        d2 = ((xy[:, None, :] - self.c[None]) ** 2).sum(-1)
        bump = np.exp(-d2 / (2 * self.r[None] ** 2)) @ self.a
        return np.array([0.0, 22.0, -40.0]) + bump  # east, north, up


APS = np.column_stack([np.arange(0.0, 101.0, 12.0), np.full(9, 4.0)])


def walk(sid: str, x0: float, x1: float, field: Field, *, t0: int, dr_turn: float, offset=(0.0, 0.0, 0.0),
         rng: np.random.Generator, magnetic: bool = True, y0: float = 0.0) -> Session:
    """A walk along the corridor y = ``y0`` from x0 to x1 (either way): dead reckoning turned by ``dr_turn`` and
    started at its origin, the phone's heading and field in east/north, scans every 3 steps."""
    n = int(abs(x1 - x0) / STEP_M) + 1
    x = np.linspace(x0, x1, n)
    true = np.column_stack([x, y0 + 0.05 * np.sin(x / 7.0)])
    h_true = np.full(n, 0.0 if x1 > x0 else math.pi)
    c, s = math.cos(dr_turn), math.sin(dr_turn)
    d = true - true[0]
    dr = np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])
    t = t0 + np.arange(n, dtype=np.int64) * 600_000_000
    steps = PoseTrack(t, dr, h_true + dr_turn)
    heading = HeadingTrack(t[1:], np.angle(np.exp(1j * (h_true[1:] + EARTH))))
    b = field.at(true[1:])
    # the phone references its orientation to the field: the horizontal part points north
    enu = np.column_stack([rng.normal(0, 0.1, n - 1), np.hypot(b[:, 0], b[:, 1]), b[:, 2]]) + np.array(offset)
    enu += rng.normal(0.0, 0.3, enu.shape)
    scans = []
    for i in range(0, n, 3):
        dist = np.linalg.norm(APS - true[i], axis=1)
        rss = -40.0 - 25.0 * np.log10(np.maximum(dist, 1.0)) + rng.normal(0, 2.0, len(APS))
        scans.append(Scan(int(t[i]) + 1, {f"02:00:00:00:00:{k:02x}": float(v) for k, v in enumerate(rss) if v > -95}))
    return Session(sid, steps, tuple(scans), ground_truth=PoseTrack(t, true, h_true), heading=heading,
                   magnetic=MagneticTrack(t[1:], enu) if magnetic else None)


def corridor(seed: int = 0, magnetic: bool = True) -> Survey:
    """Five walks of one corridor: repetitions both ways, each with its own dead-reckoning frame and offset."""
    f, rng = Field(seed), np.random.default_rng(seed + 1)
    spans = [(0, 80), (85, 5), (10, 90), (90, 15), (3, 70)]
    return Survey(tuple(
        walk(f"w{k}", a, b, f, t0=T0 + k * 10**12, dr_turn=0.7 * k - 1.0, offset=(0.0, 0.5 * k, -0.8 * k), rng=rng,
             magnetic=magnetic)
        for k, (a, b) in enumerate(spans)
    ))


def _links(survey: Survey, p: M.MagneticParams = M.MagneticParams()) -> M.MagneticLinks:
    """Links with every walk's rotation from its heading, anchored by the true places (matches within 3 m)."""
    offsets = np.concatenate([[0], np.cumsum([len(s.steps) for s in survey])])
    rot = np.array([float(np.angle(np.exp(1j * (s.heading.yaw[0] - s.steps.heading[1])))) for s in survey])
    true = np.concatenate([s.ground_truth.xy for s in survey])
    walk_of = np.repeat(np.arange(len(survey)), np.diff(offsets))
    i = np.arange(0, len(true), 4)
    d = np.linalg.norm(true[i, None] - true[None], axis=2)
    ii, jj = np.nonzero((d < 3.0) & (walk_of[i, None] != walk_of[None]))
    return M.magnetic_links(survey, offsets, rot, i[ii], jj, p)


def test_features_are_resampled_along_the_path_and_standing_still_is_one_place() -> None:
    s = corridor().sessions[0]
    # stand still for five steps mid-walk: the path does not grow, the sequence does not either
    xy = np.asarray(s.steps.xy)
    xy = np.concatenate([xy[:20], np.repeat(xy[20:21], 5, axis=0), xy[20:]])
    t = T0 + np.arange(len(xy), dtype=np.int64) * 600_000_000
    enu = np.concatenate([s.magnetic.enu[:19], np.repeat(s.magnetic.enu[19:20], 5, axis=0), s.magnetic.enu[19:]])
    still = Session("still", PoseTrack(t, xy, np.zeros(len(xy))), magnetic=MagneticTrack(t[1:], enu))
    seq = M.walk_sequences(Survey((s, still)), np.array([0, len(s.steps), len(s.steps) + len(xy)]), 0.5)
    n0, n1 = np.diff(seq.offsets)
    assert n0 == n1 == int(np.linalg.norm(np.diff(s.steps.xy, axis=0), axis=1).sum() / 0.5) + 1
    # away from where it stood, the same sequence (there, its messages while standing are the field there)
    at = np.linalg.norm(np.diff(s.steps.xy[:21], axis=0), axis=1).sum()
    away = np.abs(seq.path_m[:n0] - at) > 1.0
    np.testing.assert_allclose(seq.features[:n0][away], seq.features[n0:][away], atol=1e-9)
    b = s.magnetic.enu[5]  # the message of step 6: the field averaged since step 5, placed mid-way
    f = M.step_features(Survey((s,)))[0][6]
    np.testing.assert_allclose(f, [np.linalg.norm(b), math.hypot(b[0], b[1]), b[2]])
    assert np.all(np.diff(seq.path_m[:n0]) == pytest.approx(0.5))


def test_links_place_walks_where_the_field_repeats_both_ways_and_a_contradicting_link_is_dropped() -> None:
    survey = corridor()
    links = _links(survey)
    assert len(links) >= 6  # five walks of one corridor: most pairs link
    true = np.concatenate([s.ground_truth.xy for s in survey])
    gap = np.linalg.norm(true[links.pair_nodes[:, 0]] - true[links.pair_nodes[:, 1]], axis=1)
    assert np.median(gap) < 0.5 and gap.max() < 2.0  # the pairs are one place
    # reversed walks link as well as forward ones
    reversed_pairs = {(a, b) for a, b in zip(links.a, links.b) if (a % 2) != (b % 2)}
    assert reversed_pairs
    # the translation: T_b - T_a of the walks' (turned) dead reckonings, as the truth has it
    for k in range(len(links)):
        a, b = int(links.a[k]), int(links.b[k])
        ta, tb = survey.sessions[a].ground_truth.xy[0], survey.sessions[b].ground_truth.xy[0]
        expected = np.array([[math.cos(EARTH), -math.sin(EARTH)], [math.sin(EARTH), math.cos(EARTH)]]) @ (tb - ta)
        assert np.linalg.norm(links.translation[k] - expected) < 1.5
    # units: the walks placed relative to each other on the links' pairs; a link that contradicts the
    # others (its translation bent by 9 m) is dropped, the rest hold the corridor together
    node_xy = np.concatenate([np.asarray(s.steps.xy) for s in survey])
    node_walk = np.repeat(np.arange(len(survey)), [len(s.steps) for s in survey])
    rot = np.array([float(np.angle(np.exp(1j * (s.heading.yaw[0] - s.steps.heading[1])))) for s in survey])
    from graphslam.core.survey.placement import GrowthParams

    units = M.link_units(links, len(survey), rot, np.full(len(survey), 0.1), node_xy, node_walk, 2.0, GrowthParams())
    assert units.n_units == 1 and len(units.links) == len(links)
    bent_pairs = links.pair_nodes.copy()
    k0 = links.pair_link == 0
    bent_pairs[k0, 1] = np.clip(bent_pairs[k0, 1] + 14, 0, len(node_xy) - 1)  # 14 steps (~10 m) along the walk
    bent = M.MagneticLinks(links.a, links.b, links.translation, links.windows, links.candidates, links.score,
                           links.pair_link, bent_pairs)
    units = M.link_units(bent, len(survey), rot, np.full(len(survey), 0.1), node_xy, node_walk, 2.0, GrowthParams())
    assert units.n_units == 1 and len(units.links) == len(links) - 1
    true_xy = np.concatenate([s.ground_truth.xy for s in survey])
    placed = np.concatenate([M._apply(units.transforms, np.full(len(s.steps), w), np.asarray(s.steps.xy))
                             for w, s in enumerate(survey)])
    from graphslam.core.common.geometry import fit_se2, se2_apply

    assert np.linalg.norm(se2_apply(fit_se2(placed, true_xy), placed) - true_xy, axis=1).mean() < 0.5


def test_the_greedy_choice_on_bit_sets_is_the_choice_on_window_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    # every pair of walks by one path, then by the other: the same links, windows and node pairs
    survey = corridor()
    monkeypatch.setattr(M, "GREEDY_BITS_ABOVE", 0)
    bits = _links(survey)
    monkeypatch.setattr(M, "GREEDY_BITS_ABOVE", 10**9)
    starts = _links(survey)
    assert len(bits) >= 6 and (bits.windows >= 3).all()
    for f in ("a", "b", "translation", "windows", "candidates", "score", "pair_link", "pair_nodes"):
        np.testing.assert_array_equal(getattr(bits, f), getattr(starts, f))
    # a choice where the greedy order matters: match 0 overlaps 1 on the first walk, 2 overlaps 1 on the second
    ga, gb, L = [0, 5, 20], [0, 30, 25], 10
    for b in (M._overlap_bits(np.array(ga), np.array(gb), L), None):
        assert M._independent([0, 1, 2], ga, gb, L, b) == [0, 2]
        assert M._independent([1, 0, 2], ga, gb, L, b) == [1]


def test_each_place_keeps_the_factors_of_its_best_links_and_a_pair_stays_when_either_end_keeps_it() -> None:
    # five walks of one 40-m corridor, every step 1 m; every walk linked to every other, a pair every 4 m
    n_walk, n_step = 5, 41
    xy = np.tile(np.column_stack([np.arange(n_step, dtype=float), np.zeros(n_step)]), (n_walk, 1))
    walk = np.repeat(np.arange(n_walk), n_step)
    a, b = np.triu_indices(n_walk, 1)
    score = np.linspace(0.95, 0.99, len(a))  # the last links score best
    steps = np.arange(0, n_step, 4)
    pair_link = np.repeat(np.arange(len(a)), len(steps))
    nodes = np.column_stack([a[pair_link] * n_step + np.tile(steps, len(a)), b[pair_link] * n_step + np.tile(steps, len(a))])
    links = M.MagneticLinks(a, b, np.zeros((len(a), 2)), np.full(len(a), 2), np.full(len(a), 2), score, pair_link, nodes)
    keep = M.factor_pairs(links, xy, walk, 4.0, 2)
    kept = set(map(tuple, np.column_stack([a, b])[np.unique(pair_link[keep])].tolist()))
    # each walk's place keeps its two best partners; a pair kept by either end stays
    best = {w: sorted((k for k in range(len(a)) if w in (a[k], b[k])), key=lambda k: -score[k])[:2] for w in range(n_walk)}
    assert kept == {(int(a[k]), int(b[k])) for ks in best.values() for k in ks}
    per_place = np.bincount(np.concatenate([nodes[keep, 0], nodes[keep, 1]]), minlength=len(xy))
    assert per_place.max() <= 2 * 2 and len(kept) < len(a)
    # every place of a kept link keeps its pair (the places are the walk's own, path from its start)
    assert keep.sum() == len(kept) * len(steps)
    assert M.factor_pairs(links, xy, walk, 4.0, n_walk).all()


def test_the_threshold_comes_from_surrogates_and_unrelated_walks_do_not_link() -> None:
    survey = corridor()
    # each walk in a building of its own: the fields never repeat between walks
    other = Survey(tuple(
        walk(f"x{k}", a, b, Field(50 + k), t0=T0 + k * 10**12, dr_turn=0.3 * k, rng=np.random.default_rng(k))
        for k, (a, b) in enumerate([(0, 80), (85, 5), (10, 90), (90, 15)])
    ))
    linked, unrelated = _links(survey), _links(other)
    assert 0.5 < linked.threshold < 1.0 and linked.matches > 0
    assert len(unrelated) == 0


def test_surrogates_keep_each_walks_spectrum_and_nothing_else() -> None:
    survey = corridor()
    offsets = np.concatenate([[0], np.cumsum([len(s.steps) for s in survey])])
    seq = M.walk_sequences(survey, offsets, 0.5)
    sur = M.surrogates(seq, np.random.default_rng(0))
    a, b = seq.offsets[0], seq.offsets[1]
    x, y = seq.features[a:b], sur[a:b]
    np.testing.assert_allclose(y.mean(0), x.mean(0), atol=1e-9)
    np.testing.assert_allclose(np.abs(np.fft.rfft(y - y.mean(0), axis=0)), np.abs(np.fft.rfft(x - x.mean(0), axis=0)),
                               rtol=1e-6, atol=1e-6)
    assert np.corrcoef(x[:, 0], y[:, 0])[0, 1] < 0.6


def test_range_factors_take_a_sigma_and_dead_zone_per_edge() -> None:
    rng = np.random.default_rng(4)
    xa, xb = rng.normal(size=(20, 3)) * 4, rng.normal(size=(20, 3)) * 4
    sigma, d0 = rng.uniform(0.3, 3.0, 20), rng.uniform(0.0, 2.0, 20)
    r, Ja, Jb = S.range_residuals(xa, xb, sigma, d0)
    for k in range(20):
        rk, _, jk = S.range_residuals(xa[k:k + 1], xb[k:k + 1], float(sigma[k]), float(d0[k]))
        assert r[k] == pytest.approx(rk[0]) and np.allclose(Jb[k], jk[0])
        assert np.allclose(S.range_hessian(xa[k:k + 1], xb[k:k + 1], rk, jk, float(sigma[k]))[0],
                           S.range_hessian(xa, xb, r, Jb, sigma)[k])


def _survey(tmp_path: Path, survey: Survey, name: str, **cfg: object) -> tuple[dict, Path]:
    folder = tmp_path / f"{name}_in"
    folder.mkdir()
    for s in survey:
        write_session(s, folder / f"{s.session_id}.mcap")
    out = tmp_path / name
    res = run_survey(SurveyInputs.from_paths([folder], out=out, picture=False), load_config(None, cfg or None))
    return res.report, out


def test_a_survey_with_the_field_holds_the_corridor_together_and_says_how(tmp_path: Path) -> None:
    report, out = _survey(tmp_path, corridor(), "with")
    mag = report["magnetic"]
    assert mag["walks_with_field"] == 5 and mag["links"] >= 4 and mag["pairs"] > 0
    assert mag["pair_distance_m"]["median"] < 1.0
    main = report["components"][0]
    assert main["n_walks"] == 5 and main["links"]["magnetic"] >= 4 and main["links"]["wifi"] > 0
    assert all(c["links"]["magnetic"] == 0 for c in report["components"][1:])
    mm = read_magnetic_map(out / "magnetic_map.parquet")
    assert mm.frame == report["frame"] == "earth" and mm.n_walks == 5 and len(mm) == sum(
        len(s.steps) for s in corridor())
    # each walk's device offset (0, 0.5 k, -0.8 k µT on |B_h|, B_up) removed: the walks agree where they overlap
    off = np.array([mm.offsets[f"w{k}"] for k in range(5)])
    for col, per_walk in ((1, 0.5), (2, -0.8)):  # up to the common level, which stays in the map
        err = off[:, col] - per_walk * np.arange(5)
        assert np.abs(err - err.mean()).mean() < 0.3, off[:, col]
    # the evaluation's landmark-free check: the aligned steps lie on the corridor's truth after one fit
    assert report["radio_map"]["walks"] == 5


def test_without_the_field_or_with_it_off_the_survey_is_the_wifi_one(tmp_path: Path) -> None:
    r_off, out_off = _survey(tmp_path, corridor(), "off", magnetic={"enabled": False})
    r_none, out_none = _survey(tmp_path, corridor(magnetic=False), "none")
    assert "magnetic" not in r_off and "magnetic" not in r_none
    assert not (out_off / "magnetic_map.parquet").exists() and not (out_none / "magnetic_map.parquet").exists()
    assert (out_off / "trajectories.csv").read_bytes() == (out_none / "trajectories.csv").read_bytes()
    assert all(c["links"]["magnetic"] == 0 for c in r_off["components"])


def test_a_walk_without_the_field_is_surveyed_without_magnetic_links(tmp_path: Path) -> None:
    walks = list(corridor().sessions)
    walks[2] = Session(walks[2].session_id, walks[2].steps, walks[2].scans, ground_truth=walks[2].ground_truth,
                       heading=walks[2].heading)
    report, out = _survey(tmp_path, Survey(tuple(walks)), "partial")
    assert report["magnetic"]["walks_with_field"] == 4
    mm = read_magnetic_map(out / "magnetic_map.parquet")
    assert "w2" not in set(mm.session_ids.tolist())
    assert report["sessions"] == 5 and not report["unaligned"]


def test_magnetic_messages_are_read_and_checked(tmp_path: Path) -> None:
    s = corridor().sessions[0]
    p = write_session(s, tmp_path / "ok.mcap")
    back = read_session(p)
    np.testing.assert_array_equal(back.magnetic.t_ns, s.magnetic.t_ns)
    np.testing.assert_allclose(back.magnetic.enu, s.magnetic.enu)

    def stamp(t: int) -> dict:
        return {"sec": t // 10**9, "nsec": t % 10**9}

    poses = [("/fmip/pose", pose_body(T0 + k * 10**9, 0.7 * k, 0.0, 0.0), T0 + k * 10**9) for k in range(4)]
    for name, bodies, field in (
        ("nan", [{"timestamp": stamp(T0 + 10**9), "east": 0.1, "north": float("nan"), "up": -40.0}], "north"),
        ("missing", [{"timestamp": stamp(T0 + 10**9), "east": 0.1, "north": 20.0}], "up"),
        ("text", [{"timestamp": stamp(T0 + 10**9), "east": "0.1", "north": 20.0, "up": -40.0}], "east"),
        ("back", [{"timestamp": stamp(T0 + 2 * 10**9), "east": 0.0, "north": 20.0, "up": -40.0},
                  {"timestamp": stamp(T0 + 10**9), "east": 0.0, "north": 20.0, "up": -40.0}], "timestamp"),
    ):
        bad = write_raw_mcap(tmp_path / f"{name}.mcap", poses + [("/phone/magnetic", b, T0) for b in bodies])
        with pytest.raises(InputError) as e:
            read_session(bad)
        assert "/phone/magnetic" in str(e.value) and field in str(e.value), str(e.value)


def test_the_magnetic_map_file_round_trips_and_refuses_a_changed_byte(tmp_path: Path) -> None:
    _, out = _survey(tmp_path, corridor(), "file")
    path = out / "magnetic_map.parquet"
    mm = read_magnetic_map(path)
    copy = write_magnetic_map(mm, tmp_path / "copy.parquet")
    again = read_magnetic_map(copy)
    np.testing.assert_array_equal(again.features, mm.features)
    assert again.offsets == mm.offsets and again.frame == mm.frame
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[b"graphslam.magnetic_map"])
    for change, field in ((lambda m: m | {"frame": "site"}, "content_sha256"),
                          (lambda m: m | {"format_version": 99}, "format_version")):
        t2 = table.replace_schema_metadata({b"graphslam.magnetic_map": json.dumps(change(meta)).encode()})
        pq.write_table(t2, tmp_path / "bad.parquet")
        with pytest.raises(RadioMapError, match=field):
            read_magnetic_map(tmp_path / "bad.parquet")


def test_plot_and_rerun_show_the_magnetic_map_and_its_factors(tmp_path: Path) -> None:
    rerun = pytest.importorskip("rerun.chunk", reason="the rerun extra is not installed")
    from PIL import Image

    from graphslam.app.pictures import plot_survey_folder

    folder = tmp_path / "in"
    folder.mkdir()
    for s in corridor():
        write_session(s, folder / f"{s.session_id}.mcap")
    out, rrd = tmp_path / "out", tmp_path / "survey.rrd"
    run_survey(SurveyInputs.from_paths([folder], out=out, rerun=rrd, picture=False), load_config())
    paths = {str(p) for p in rerun.RrdReader(rrd).store().schema().entity_paths()}
    assert {"/world/aligned/magnetic_map/magnitude", "/world/aligned/magnetic_map/vertical",
            "/world/aligned/magnetic_pairs"} <= paths
    files = plot_survey_folder(out)
    with Image.open(files["magnetic_map"]) as im:
        assert im.size == (1600, 760)
        px = np.asarray(im.convert("RGB"), float)
    assert px.std(axis=(0, 1)).max() > 20  # a heatmap, not a blank page
    # a later survey into the folder redraws it for the new map (report.json says so)
    report = run_survey(SurveyInputs.from_paths([folder], out=out, picture=False), load_config()).report
    assert report["derived_files"]["magnetic_map.png"]["status"] == "rebuilt"


def test_an_update_keeps_the_fields_links_and_places_new_walks_by_theirs(tmp_path: Path) -> None:
    walks = corridor().sessions
    folder = tmp_path / "in"
    folder.mkdir()
    files = [write_session(s, folder / f"{s.session_id}.mcap") for s in walks]
    out = tmp_path / "out"
    first = run_survey(SurveyInputs.from_paths(files[:3], out=out, picture=False), load_config()).report
    assert first["magnetic"]["links"] >= 2
    res = run_survey(SurveyInputs.from_paths(files, out=out, previous=out, picture=False), load_config())
    r = res.report
    assert r["update"]["mode"] == "incremental", r["update"]
    assert r["components"][0]["n_walks"] == 5
    # the previous links between w0..w2 are kept, the new walks' links found
    links = res.alignment.magnetic
    pairs = {(int(a), int(b)) for a, b in zip(links.a, links.b)}
    assert {(0, 1), (0, 2), (1, 2)} & pairs and any(b >= 3 for _, b in pairs)
    # the new walks where the truth has them, relative to the old ones (one fit of everything)
    from graphslam.core.common.geometry import fit_se2, se2_apply

    est = np.concatenate([res.alignment.tracks[s.session_id].xy for s in walks])
    true = np.concatenate([s.ground_truth.xy for s in walks])
    assert np.linalg.norm(se2_apply(fit_se2(est, true), est) - true, axis=1).mean() < 1.0
