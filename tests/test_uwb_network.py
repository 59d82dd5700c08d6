"""The UWB network simulation (Paper 003, section III): gradient clock sync converges, Alg. 1's
rejection / cancellation / hidden-node cases, DS-TWR noise, and a short seven-tag run whose
recordings are tracked by ``graphslam track-uwb``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from graphslam.sim.uwb.clock import ClockParams, Clocks, SyncParams, sync_phase
from graphslam.sim.uwb.radio import UwbRadioParams, ds_twr_range
from graphslam.sim.uwb.tdma import CANCEL, PROPOSE, REJECT, TdmaNode, TdmaParams, schedule_phase

RADIO = UwbRadioParams()


def _spread(clocks: Clocks, devices: np.ndarray, t: float) -> float:
    L = clocks.logical(devices, t)
    return float(np.max(np.abs(L - L.mean())))


def test_gradient_sync_brings_a_group_to_microseconds() -> None:
    rng = np.random.default_rng(0)
    n = 6
    clocks = Clocks.draw(n, ClockParams(initial_offset_s=5e-3), rng)
    linked = ~np.eye(n, dtype=bool)
    dev = np.arange(n)
    assert _spread(clocks, dev, 0.0) > 1e-3
    res = sync_phase(clocks, dev, 0.01, linked, SyncParams(), ClockParams(), RADIO, rng)
    assert _spread(clocks, dev, 0.25) < 30e-6  # the delay jitter (3 us) and 20 ppm drift remain
    assert res.messages > 0 and len(res.heard) == n * (n - 1)


def test_merge_rule_joins_two_groups_that_drifted_apart() -> None:
    """Two groups of three, 3 ms apart, meet over one link: averaging alone would close the gap
    by a fraction per round; with the merge rule both follow the one ahead within the phase."""
    rng = np.random.default_rng(1)
    clocks = Clocks(np.ones(6), np.array([0, 0, 0, 3e-3, 3e-3, 3e-3]))
    linked = np.zeros((6, 6), bool)
    for g in ((0, 1, 2), (3, 4, 5)):
        for a in g:
            for b in g:
                linked[a, b] = a != b
    linked[2, 3] = linked[3, 2] = True  # the bridge
    res = sync_phase(clocks, np.arange(6), 0.01, linked, SyncParams(), ClockParams(delay_jitter_s=0.0), RADIO, rng)
    assert res.jumps >= 3
    assert _spread(clocks, np.arange(6), 0.3) < 30e-6


def _deliver(packet: tuple, *nodes: TdmaNode) -> None:
    for n in nodes:
        n.on_packet(packet)


def test_alg1_rejection_and_cancellation() -> None:
    a, b, c = (TdmaNode(i, {0, 1, 2} - {i}, 25) for i in range(3))  # all neighbours
    p = a.next_packet()
    assert p == (0, PROPOSE, 0, 0)  # initial sequence: rank 0 -> slot 0
    _deliver(p, b, c)
    assert b.received == {0: 0} and c.received == {0: 0}
    # b claims the same slot anyway (it missed a's packet): a owns it and rejects b (code = b's id)
    b.received.clear()
    b.sent.add(0)
    b.announced[0] = 1
    a.on_packet((1, PROPOSE, 1, 0))
    c.on_packet((1, PROPOSE, 1, 0))  # c gave slot 0 to a: it rejects b too
    rej = a.next_packet()
    assert rej == (0, REJECT, 1, 0)
    _deliver(rej, b, c)
    assert 0 not in b.sent and 0 in b.refused  # lines 15-18: b was the source
    cancel = b.next_packet()
    assert cancel == (1, CANCEL, 1, 0)
    _deliver(cancel, a, c)
    assert (0, 1) not in a.rejecting and (0, 1) not in c.rejecting  # the cancellation acknowledges
    assert a.sent == {0} and c.received == {0: 0}


def test_alg1_rejection_erases_a_third_party_entry() -> None:
    """Lines 19-20: a listener that gave the slot to the conflicting tag erases that entry."""
    x = TdmaNode(5, {1, 2}, 25)
    x.on_packet((2, PROPOSE, 2, 7))
    assert x.received == {7: 2}
    x.on_packet((1, REJECT, 9, 7))  # a rejection of someone else: not its entry, kept
    assert x.received == {7: 2}
    x.on_packet((1, REJECT, 2, 7))
    assert 7 not in x.received


def test_alg1_hidden_node() -> None:
    """a - b - c: a and c cannot hear each other and claim the same slot; b sees the conflict
    and rejects the later claim; a (not c's neighbour) ignores the rejection and keeps it."""
    a, b, c = TdmaNode(0, {1}, 25), TdmaNode(1, {0, 2}, 25), TdmaNode(2, {1}, 25)
    pa = a.next_packet()
    _deliver(pa, b)
    c.sent.add(pa[3])
    c.announced[pa[3]] = 1
    b.on_packet((2, PROPOSE, 2, pa[3]))
    rej = b.next_packet()
    assert rej == (1, REJECT, 2, pa[3])
    _deliver(rej, a, c)
    assert a.sent == {pa[3]} and pa[3] not in c.sent
    nxt = c.next_packet()  # c cancels, then claims a different slot
    assert nxt[1] == CANCEL
    again = c.next_packet()
    assert again[1] == PROPOSE and again[3] != pa[3]
    # an anchor between two hidden tags does the same (it never claims a slot itself)
    anchor = TdmaNode(9, set(), 25, is_anchor=True)
    anchor.on_packet((0, PROPOSE, 0, 4))
    anchor.on_packet((2, PROPOSE, 2, 4))
    assert anchor.next_packet() == (9, REJECT, 2, 4) and not anchor.sent


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_schedule_phase_resolves_hidden_nodes_on_the_air(seed: int) -> None:
    """Three groups in a row (tags 0-2, 3-5, 6-8; tag 4 hears groups 1 and 3 too): after one phase
    on the simulated medium no two tags within two hops share a slot and every tag holds one."""
    rng = np.random.default_rng(seed)
    n = 9
    linked = np.zeros((n, n), bool)
    for g in ((0, 1, 2), (3, 4, 5), (6, 7, 8)):
        for a in g:
            for b in g:
                linked[a, b] = a != b
    for a in (2, 4, 6):
        for b in (2, 4, 6):
            linked[a, b] = a != b
    clocks = Clocks(np.ones(n), np.zeros(n))
    tags = np.arange(n)
    tables = {i: set(np.flatnonzero(linked[i]).tolist()) for i in range(n)}
    res = schedule_phase(clocks, tags, np.zeros(0, np.int64), tables, 0.0, linked, TdmaParams(), RADIO, rng)
    two_hop = linked | ((linked.astype(int) @ linked.astype(int)) > 0)
    for a in range(n):
        assert res.slots[a], f"tag {a} has no slot"
        for b in range(a + 1, n):
            if two_hop[a, b]:
                assert not set(res.slots[a]) & set(res.slots[b]), (a, b, res.slots[a], res.slots[b])
    assert res.packets["rejection"] > 0  # the hidden-node conflicts of the initial sequence did happen


def test_ds_twr_range_noise() -> None:
    rng = np.random.default_rng(2)
    d = np.full(20000, 12.0)
    rates = 1 + rng.normal(0, 20e-6, (2, 20000))
    r = ds_twr_range(d, np.zeros_like(d), rates[0], rates[1], 0.3e-3, RADIO, rng)
    assert abs((r - d).mean()) < 2e-3 and 0.045 < (r - d).std() < 0.055  # the documented 5 cm


def test_short_seven_tag_run_and_its_recordings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from graphslam.cli import main
    from graphslam.sim.uwb.scenarios import simulate_zones

    run = simulate_zones(0, end_s=30.0)
    cyc = [c for c in run.network.cycles if c.active_tags]
    assert len(cyc) >= 15
    assert sum(c.ranging_collisions for c in cyc) == 0
    assert all(len(c.slots[t]) >= 1 for c in cyc for t in c.active_tags)
    assert max(max(c.offset_to_neighbours_s.values()) for c in cyc[1:]) < 100e-6
    run.write(tmp_path / "rec")
    capsys.readouterr()
    main(["track-uwb", str(tmp_path / "rec"), "--out", str(tmp_path / "track.csv")])
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    with open(tmp_path / "track.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["update"] for r in rows} <= {"trilateration", "anchor", "neighbour", "none"}
    errs = []
    for r in rows:
        tag = run.tag_ids.index(r["uwb_id"])
        t = (int(r["t_ns"]) - 1_780_304_400_000_000_000) / 1e9
        truth = run.paths.at(tag, np.array([t]))[0]
        if run.site.zone_of(truth[None])[0] == 0:
            errs.append(np.hypot(float(r["x"]) - truth[0], float(r["y"]) - truth[1]))
    assert len(errs) > 100 and np.mean(errs) < 0.10  # zone A, four anchors: the paper's 10 cm
    # the recordings carry the true paths: the error figures printed are those of every row against them
    every = [np.hypot(float(r["x"]) - p[0], float(r["y"]) - p[1]) for r in rows for p in
             [run.paths.at(run.tag_ids.index(r["uwb_id"]), np.array([(int(r["t_ns"]) - 1_780_304_400_000_000_000) / 1e9]))[0]]]
    ev = printed["errors"]
    assert ev["evaluated"] and ev["frame"] == printed["frame"] == "site" and ev["truth"]["n"] == len(rows)
    assert ev["truth"]["mean_m"] == pytest.approx(np.mean(every), abs=2e-3)
    # ... and the picture beside the CSV: the tracks, the truth (dashed), the anchors (orange squares)
    png = tmp_path / "track.png"
    assert printed["picture"] == str(png)
    with Image.open(png) as im:
        text, img = dict(im.text), np.asarray(im.convert("RGB")).astype(int)
    assert text["frame"] == "site" and "error vs truth mean" in text["Title"]
    from graphslam.viz.track_picture import ANCHOR

    assert (np.abs(img - np.array(ANCHOR)).max(axis=2) <= 10).sum() > 9 * 100  # 9 anchors, ~15x15 px each
    main(["track-uwb", str(tmp_path / "rec"), "--out", str(tmp_path / "t2.csv"), "--no-picture"])
    assert not (tmp_path / "t2.png").exists()
