"""The UWB network of Paper 003, section III, as a discrete-event simulation.

Devices: mobile tags (walkers) and fixed anchors. Time runs in cycles of fixed length in every
device's logical clock (the paper's Fig. 1):

1. synchronisation (``clock.sync_phase``): gradient clock sync, eq. 1-3;
2. scheduling (``tdma.schedule_phase``): Alg. 1 over the neighbour tables;
3. execution: ``n_slots`` slots; in each of its slots a tag ranges (double-sided TWR, eq. 4-6)
   with every anchor and tag it heard this cycle, one exchange after the other (poll, response,
   final ``reply_s`` apart, exchanges ``exchange_s`` apart), at most ``max_responders``.

Topology comes from the building: links and NLOS from ``radio.link_matrix`` (walls limit the
reach and make a range NLOS), evaluated per phase and per slot at the devices' true
positions. A tag with a link that was not there during both the sync and the scheduling phase
(someone came into range, a walker stepped through a door) stays silent until the next cycle, both ends of the new link, neither
ranging nor answering polls (the paper: a new tag waits for the next round of scheduling);
without that rule a newcomer transmits in slots its new neighbours' schedules never accounted
for, and on clocks they are not synchronised with. Phases of different
types do not interact on the air (the phases of devices that hear each other are aligned to
microseconds by the sync; at the very first cycle to milliseconds).

Output: every completed range as the ``/uwb/range`` stream of the initiator (time = the poll's
true time on the shared clock, responder, measured 3-D range) plus what the benchmark needs:
collisions per phase, slots per tag per cycle, clock offsets to the neighbours' average after
sync, schedule tables, and the slots each tag executed (for the filter's prediction-only
steps). Ground truth (true range, NLOS flag) is kept beside the measurement, for evaluation.
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from graphslam.core.progress import Task
from graphslam.core.uwb.ekf import UwbEpoch
from graphslam.errors import ConfigError, SimulationError
from graphslam.sim.uwb.clock import ClockParams, Clocks, SyncParams, sync_phase
from graphslam.sim.uwb.radio import Frame, Medium, UwbRadioParams, ds_twr_range, link_matrix, nlos_excess
from graphslam.sim.uwb.tdma import TdmaParams, schedule_phase

log = logging.getLogger(__name__)

_SEND, _SETTLE = 0, 1  # event kinds of slot execution (a send at a frame's end goes first: no overlap)


@dataclass(frozen=True)
class SlotParams:
    """Slot execution (s)."""

    slot_s: float = 0.04
    guard_s: float = 1e-3  # from the slot's start to the first poll
    # one DS-TWR exchange: poll, response, final reply_s apart. Devices three hops apart may share
    # a slot; their frames stay apart while their clocks differ by less than reply_s - airtime
    # (350 us: the 20 ppm crystals drift ~30 us each over a cycle; 0.3 ms replies collided twice
    # in one 8-minute crowd run)
    exchange_s: float = 1.5e-3
    reply_s: float = 0.5e-3
    max_responders: int = 12

    def __post_init__(self) -> None:
        if not (self.exchange_s >= 2 * self.reply_s + 0.2e-3 and self.reply_s > 0):
            raise ConfigError("SlotParams: an exchange must fit two replies and a frame")
        if self.guard_s + self.max_responders * self.exchange_s > self.slot_s:
            raise ConfigError("SlotParams: max_responders exchanges do not fit in a slot")


@dataclass(frozen=True)
class NetworkParams:
    radio: UwbRadioParams = field(default_factory=UwbRadioParams)
    clock: ClockParams = field(default_factory=ClockParams)
    sync: SyncParams = field(default_factory=SyncParams)
    tdma: TdmaParams = field(default_factory=TdmaParams)
    slot: SlotParams = field(default_factory=SlotParams)
    gc_cycles: int = 3  # neighbour-table entries not heard for this many cycles are dropped
    tag_height_m: float = 1.0

    @property
    def cycle_s(self) -> float:
        return self.sync.duration_s + self.tdma.duration_s + self.tdma.n_slots * self.slot.slot_s


@dataclass(frozen=True, eq=False)
class Devices:
    """Who is in the network. Tags 0..T-1 move (``positions(t)`` -> (T, 2) site-frame m, ``active(t)``
    -> (T,) bool: a walker not yet started or gone is switched off); anchors T..T+A-1 are fixed
    at ``anchor_xyz`` (A, 3)."""

    tag_ids: tuple[str, ...]
    anchor_ids: tuple[str, ...]
    anchor_xyz: NDArray[np.float64]
    positions: Callable[[float], NDArray]
    active: Callable[[float], NDArray]
    walls: NDArray[np.float64]

    @property
    def n_tags(self) -> int:
        return len(self.tag_ids)

    @property
    def n(self) -> int:
        return len(self.tag_ids) + len(self.anchor_ids)

    def xy(self, t: float) -> NDArray:
        return np.vstack([np.reshape(self.positions(t), (-1, 2)), self.anchor_xyz[:, :2]])

    def on(self, t: float) -> NDArray:
        return np.concatenate([np.asarray(self.active(t), bool), np.ones(len(self.anchor_ids), bool)])

    def heights(self, tag_height_m: float) -> NDArray:
        return np.concatenate([np.full(self.n_tags, tag_height_m), self.anchor_xyz[:, 2]])


@dataclass(frozen=True)
class CycleRecord:
    index: int
    t_s: float  # true time of the cycle's start (the earliest device)
    active_tags: tuple[int, ...]
    sync_messages: int
    sync_collisions: int
    offset_to_neighbours_s: dict[int, float]  # tag -> |L_i - mean of the linked devices' L_j| after sync
    synced_tags: int
    tdma_packets: dict[str, int]
    tdma_collisions: int
    slots: dict[int, tuple[int, ...]]  # tag -> slots held
    schedule_conflicts: int  # tag pairs within two hops holding a common slot
    suspended_tags: tuple[int, ...]
    ranging_frames: int
    ranging_collisions: int  # frames of an exchange lost to a collision at their intended receiver
    exchanges: int
    ranges_ok: int


@dataclass(frozen=True, eq=False)
class RangeLog:
    """Every completed range (arrays of length R) and every executed slot."""

    tag: NDArray[np.int64]
    t_s: NDArray[np.float64]
    responder: NDArray[np.int64]  # device index (>= n_tags: an anchor)
    range_m: NDArray[np.float64]
    true_m: NDArray[np.float64]
    nlos: NDArray[np.bool_]
    slot_tag: NDArray[np.int64]  # one row per executed slot
    slot_t_s: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class NetworkRun:
    devices: Devices
    params: NetworkParams
    cycles: tuple[CycleRecord, ...]
    ranges: RangeLog
    t0_s: float
    t1_s: float

    def responder_name(self, j: int) -> str:
        d = self.devices
        return d.tag_ids[j] if j < d.n_tags else d.anchor_ids[j - d.n_tags]

    def epochs(self, t0_ns: int = 0) -> list[UwbEpoch]:
        """One ``UwbEpoch`` per executed slot (an empty one where no range completed: the
        filter's prediction-only step), times on the shared clock ``t0_ns + t``."""
        r, d = self.ranges, self.devices
        nt = d.n_tags
        out = []
        for tag in range(nt):
            st = np.sort(r.slot_t_s[r.slot_tag == tag])
            sel = np.flatnonzero(r.tag == tag)
            which = np.searchsorted(st, r.t_s[sel], side="right") - 1
            for k, t in enumerate(st.tolist()):
                m = sel[which == k]
                a, p = m[r.responder[m] >= nt], m[r.responder[m] < nt]
                out.append(UwbEpoch(
                    d.tag_ids[tag], t0_ns + int(round(t * 1e9)),
                    tuple(self.responder_name(int(j)) for j in r.responder[a]), r.range_m[a].copy(),
                    tuple(self.responder_name(int(j)) for j in r.responder[p]), r.range_m[p].copy(),
                ))
        return out


def _two_hop_conflicts(slots: dict[int, tuple[int, ...]], linked: NDArray) -> int:
    tags = sorted(slots)
    two_hop = linked | ((linked.astype(np.int32) @ linked.astype(np.int32)) > 0)
    bad = 0
    for a_i, a in enumerate(tags):
        for b in tags[a_i + 1:]:
            if two_hop[a, b] and set(slots[a]) & set(slots[b]):
                bad += 1
    return bad


def simulate_network(
    devices: Devices, t0_s: float, t1_s: float, params: NetworkParams, rng: np.random.Generator
) -> NetworkRun:
    """Run cycles from true time ``t0_s`` until ``t1_s``."""
    if t1_s <= t0_s:
        raise SimulationError("UWB network: the end time must be after the start time")
    n, nt = devices.n, devices.n_tags
    clocks = Clocks.draw(n, params.clock, rng)
    # every device's logical clock reads 0 at t0 (switched on together) up to its power-up offset
    clocks.hw_offset -= clocks.rate * t0_s
    heights = devices.heights(params.tag_height_m)
    tables: dict[int, dict[int, int]] = {i: {} for i in range(n)}  # device -> {neighbour: last cycle heard}
    tags_all = np.arange(nt)
    anchors = np.arange(nt, n)
    cyc_s = params.cycle_s
    sp, tp = params.slot, params.tdma
    records: list[CycleRecord] = []
    r_tag, r_t, r_resp, r_rng, r_true, r_nlos = [], [], [], [], [], []
    s_tag, s_t = [], []
    k = 0
    # cycles expected (the logical clocks drift by ppm: a cycle more or less)
    task = Task("simulate UWB network", total=max(1, math.ceil((t1_s - t0_s) / cyc_s)), unit="cycles")
    with task:
        while True:
            start_L = k * cyc_s
            t_start = float(np.min(clocks.true_time(np.arange(n), start_L)))
            if t_start >= t1_s:
                break
            on = devices.on(t_start + 0.5 * params.sync.duration_s)
            tags = tags_all[on[:nt]]
            if not len(tags):
                records.append(CycleRecord(k, t_start, (), 0, 0, {}, 0, {}, 0, {}, 0, (), 0, 0, 0, 0))
                k += 1
                task.advance(info=f"{len(r_t):,} ranges")
                continue
            part = np.concatenate([tags, anchors])
            # 1. synchronisation
            t_mid = t_start + 0.5 * params.sync.duration_s
            linked, _ = link_matrix(devices.xy(t_mid), devices.walls, params.radio, on)
            sync = sync_phase(clocks, part, start_L, linked, params.sync, params.clock, params.radio, rng)
            t_end_sync = float(np.mean(clocks.true_time(part, start_L + params.sync.duration_s)))
            L = clocks.logical(np.arange(n), t_end_sync)
            offsets = {}
            for i in tags.tolist():
                nb = np.flatnonzero(linked[i])
                if len(nb):
                    offsets[i] = float(abs(L[i] - L[nb].mean()))
            for r, s in sync.heard:
                tables[r][s] = k
            # garbage collector: forget neighbours not heard for gc_cycles
            for i in range(n):
                for j in [j for j, last in tables[i].items() if k - last >= params.gc_cycles]:
                    del tables[i][j]
            tag_tables = {i: {j for j in tables[i] if j < nt} for i in tags.tolist()}
            # 2. scheduling
            sched_L = start_L + params.sync.duration_s
            t_sched = float(np.mean(clocks.true_time(part, sched_L + 0.5 * tp.duration_s)))
            linked_s, _ = link_matrix(devices.xy(t_sched), devices.walls, params.radio, on)
            sched = schedule_phase(clocks, tags, anchors, tag_tables, sched_L, linked_s, tp, params.radio, rng)
            heard_now: dict[int, set[int]] = {i: set() for i in range(n)}
            for r, s in sync.heard | sched.heard:
                tables[r][s] = k
                heard_now[r].add(s)
            conflicts = _two_hop_conflicts(sched.slots, linked_s)
            # 3. execution
            exec_L = sched_L + tp.duration_s
            suspended: set[int] = set()
            n_frames = n_coll = n_exch = n_ok = 0
            for slot in range(tp.n_slots):
                slot_L = exec_L + slot * sp.slot_s
                t_slot = float(np.mean(clocks.true_time(part, slot_L)))
                if t_slot >= t1_s:
                    break
                on_now = devices.on(t_slot)
                xy = devices.xy(t_slot)
                linked_x, walls_x = link_matrix(xy, devices.walls, params.radio, on_now)
                new = linked_x & ~(linked & linked_s)  # a link must have been there to sync and to schedule
                suspended |= set(np.flatnonzero(new.any(axis=1) & (np.arange(n) < nt)).tolist())
                owners = [i for i in tags.tolist() if slot in sched.slots[i] and i not in suspended and on_now[i]]
                if not owners:
                    continue
                medium = Medium(linked_x, params.radio, rng)
                # frames in time order: a frame is settled when it ends; a response is sent only if
                # the poll arrived, the final only if the response did (a responder out of reach
                # stays silent)
                events: list[tuple[float, int, int, int, int, int]] = []  # (time, kind, stage, exchange, sender, receiver)
                exch: list[tuple[int, int, float]] = []
                for i in owners:
                    responders = sorted(heard_now[i], key=lambda j: (j < nt, j))[: sp.max_responders]
                    s_tag.append(i)
                    s_t.append(float(clocks.true_time(i, slot_L)))
                    for e, j in enumerate(responders):
                        t_poll = float(clocks.true_time(i, slot_L + sp.guard_s + e * sp.exchange_s))
                        events.append((t_poll, _SEND, 0, len(exch), i, j))
                        exch.append((i, j, t_poll))
                n_exch += len(exch)
                heapq.heapify(events)
                frames: dict[tuple[int, int], Frame] = {}
                while events:
                    t_ev, kind, stage, e, sender, receiver = heapq.heappop(events)
                    if kind == _SEND:
                        f = medium.send(t_ev, sender, None)
                        frames[(e, stage)] = f
                        heapq.heappush(events, (f.end, _SETTLE, stage, e, sender, receiver))
                        continue
                    f = frames.pop((e, stage))
                    n_frames += 1
                    st = medium.status(f, receiver)
                    n_coll += st == "collision"
                    if st != "ok":
                        continue
                    i, j, t_poll = exch[e]
                    if stage == 0 and receiver in suspended:
                        continue  # a device whose links changed stays silent, as responder too
                    if stage < 2:  # the reply goes out reply_s after reception, on the replier's clock
                        heapq.heappush(events, (f.start + sp.reply_s / clocks.rate[receiver], _SEND, stage + 1, e, receiver, sender))
                        continue
                    d3 = float(np.sqrt(np.sum((xy[i] - xy[j]) ** 2) + (heights[i] - heights[j]) ** 2))
                    excess, nlos = nlos_excess(np.array([walls_x[i, j]]), params.radio, rng)
                    meas = ds_twr_range(np.array([d3]), excess, clocks.rate[i], clocks.rate[j], sp.reply_s, params.radio, rng)
                    r_tag.append(i)
                    r_t.append(t_poll)
                    r_resp.append(j)
                    r_rng.append(float(meas[0]))
                    r_true.append(d3)
                    r_nlos.append(bool(nlos[0]))
                    n_ok += 1
            records.append(CycleRecord(
                k, t_start, tuple(tags.tolist()), sync.messages, sync.collisions, offsets, len(sync.synced_at_s),
                sched.packets, sched.collisions, sched.slots, conflicts, tuple(sorted(suspended)), n_frames, n_coll,
                n_exch, n_ok,
            ))
            k += 1
            task.advance(info=f"{len(r_t):,} ranges")
    log.info("UWB network: %d cycles, %d ranges", len(records), len(r_t))
    ranges = RangeLog(
        np.array(r_tag, np.int64), np.array(r_t, float), np.array(r_resp, np.int64), np.array(r_rng, float),
        np.array(r_true, float), np.array(r_nlos, bool), np.array(s_tag, np.int64), np.array(s_t, float),
    )
    return NetworkRun(devices, params, tuple(records), ranges, t0_s, t1_s)
