"""Decentralised TDMA slot scheduling: Paper 003, III-B, Algorithm 1.

Every tag keeps a neighbour table (from the sync phase; entries not heard for a few
cycles are dropped by a garbage collector), a *sent* list (slots it proposed and holds) and a
*received* list (slot -> neighbour that holds it); its free slots are those in neither.
Control packets carry three values: sender id, action code, slot id. Actions:

- **proposal** (code = sender): "I take slot s". A listener records it in its received list
  (Alg. 1 lines 10-11) unless s is already attributed in its lists (its own, or another
  neighbour's): it has discovered a conflict and queues a **rejection** of s whose action code
  is the conflicting (later) proposer's id.
- **rejection** (code = conflicting id c): if c is the listener itself, it drops s and queues a
  **cancellation** of s (lines 15-18); otherwise, if its received list gives s to c, it erases
  that entry (lines 19-20). A listener that never recorded c's proposal (not c's neighbour)
  ignores it.
- **cancellation**: listeners that gave s to the sender erase the entry.

This resolves hidden nodes: a tag that hears two tags which cannot hear each other rejects the
second proposal for a slot, so two tags two hops apart never share a slot.

The phase has three parts (our structure; the paper gives the actions, not the timing):

1. **initial** (``initial_fraction``): a tag claims one slot, its rank among the tags of its
   neighbour table (the paper's initial sequence by ascending ids), or, if that one is
   taken or refused, a random free one (a hidden group holds a run of slots: probing them in
   order left a tag without a slot 3 times in 100 seven-tag runs);
2. **fill**: further random free slots while the tag holds fewer than
   ``n_slots // (tags in its table + 1)`` (the schedule fills and every neighbour keeps room);
3. **quiet** (``quiet_fraction``): nothing new is claimed (a late claim would get no time to be
   rejected) except by a tag that holds none; every tag re-announces its claims, least
   announced first, so that a relay that missed one hears it and rejects a conflict;
4. **last** (``last_fraction``): only rejections and cancellations, so that a conflict seen in
   the quiet part is still resolved.

Packets are lost (collisions at a relay that hears many tags, loss) and a hidden-node
conflict is only seen by a relay that received both claims, so claims are repeated: a new
claim goes out ``min_announce`` times before the next one, and at the end a tag keeps only the
slots it announced ``min_announce`` times in the quiet part (if that leaves none, its best
announced slot: every tag keeps one). A slot refused to a tag is not claimed again in the
phase. A rejection is repeated (``REJECT_RETRIES``) until the conflicting tag's cancellation is
heard: the cancellation is the acknowledgement. Broadcasting is random (``broadcast_prob`` per
tick, as in the sync phase; ``urgent_prob`` with a rejection or cancellation to send: the tag
between two groups has many). The repetitions, the three parts and the refused-slot memory are
ours: with the single proposal and rejection of the paper's description, 65 two-hop conflicts
remained in one 3-minute run of the seven-tag experiment.

Anchors are UWB devices too: they take part in the phase as listeners that queue
rejections (and hear cancellations), never proposing. Without that a tag pair hidden from
each other but ranging to the same anchor could share a slot and collide at the anchor. This
is our addition; the paper's anchors are not described in the protocol.
"""

from __future__ import annotations

import heapq
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.errors import ConfigError
from graphslam.sim.uwb.clock import Clocks
from graphslam.sim.uwb.radio import Medium, UwbRadioParams

PROPOSE, REJECT, CANCEL = 0, 1, 2
INITIAL, FILL, QUIET, LAST = 0, 1, 2, 3  # the parts of the phase
ACTIONS = ("proposal", "rejection", "cancellation")

Packet = tuple[int, int, int, int]  # (sender, action, code, slot)
REJECT_RETRIES = 4  # a rejection is repeated until the cancellation is heard, at most this often


@dataclass(frozen=True)
class TdmaParams:
    """The scheduling phase (s) and the frame of slots."""

    duration_s: float = 0.5
    tick_s: float = 2e-3
    broadcast_prob: float = 0.15
    urgent_prob: float = 0.4  # a device with a rejection or cancellation to send broadcasts more often
    n_slots: int = 25  # the paper's choice for seven tags
    initial_fraction: float = 0.25  # first part: one claim per tag
    quiet_fraction: float = 0.3  # then: claims are only re-announced (verification)
    last_fraction: float = 0.15  # and last: only rejections and cancellations
    min_announce: int = 3  # a claim counts once it went out this often before, and again in, the quiet part

    def __post_init__(self) -> None:
        if not (self.duration_s > self.tick_s > 0 and 0 < self.broadcast_prob < 1 and self.n_slots >= 1):
            raise ConfigError("TdmaParams: need duration > tick > 0, 0 < broadcast_prob < 1, n_slots >= 1")
        parts = (self.initial_fraction, self.quiet_fraction, self.last_fraction)
        if min(parts) < 0 or sum(parts) >= 1:
            raise ConfigError("TdmaParams: initial, quiet and last fractions must be >= 0 and sum to < 1")
        if self.min_announce < 1:
            raise ConfigError("TdmaParams: min_announce must be >= 1")


class TdmaNode:
    """Alg. 1 at one device. ``table``: the tags of its neighbour table (ids)."""

    def __init__(self, node_id: int, table: set[int] | frozenset[int], n_slots: int, *, is_anchor: bool = False,
                 min_announce: int = 1, rng: np.random.Generator | None = None) -> None:
        self.id = node_id
        self.n_slots = n_slots
        self.is_anchor = is_anchor
        self.min_announce = min_announce
        self.rng = rng or np.random.default_rng(0)
        self.sent: set[int] = set()
        self.announced: dict[int, int] = {}  # held slot -> times it went out
        self.refused: set[int] = set()  # slots rejected for me this phase
        self.late: set[int] = set()  # slots first claimed in the quiet part of the phase
        self.verified: dict[int, int] = {}  # held slot -> announcements in the quiet part
        self.received: dict[int, int] = {}
        self.pending: deque[tuple[int, int, int]] = deque()  # (action, code, slot): cancellations
        self.rejecting: dict[tuple[int, int], int] = {}  # (slot, conflicting id) -> rejections still to send
        ranked = sorted(set(table) | {node_id})
        self.initial = ranked.index(node_id)
        self.max_slots = max(1, n_slots // len(ranked))
        self.claimed: set[int] = set()  # every slot claimed this phase
        self._announce = 0

    @property
    def urgent(self) -> bool:
        return bool(self.pending or self.rejecting)

    def free_slots(self) -> list[int]:
        return [s for s in range(self.n_slots) if s not in self.sent and s not in self.received and s not in self.refused]

    def confirmed(self) -> tuple[int, ...]:
        """The slots this tag uses: held, claimed before the quiet part and announced in it at
        least ``min_announce`` times (if that leaves none: the held slot announced most)."""
        ok = sorted(s for s in self.sent if self.verified.get(s, 0) >= self.min_announce and s not in self.late)
        if ok or not self.sent:
            return tuple(ok)
        return (max(sorted(self.sent), key=lambda s: (s not in self.late, self.verified.get(s, 0))),)

    def _announce_slot(self, slot: int, quiet: bool = False) -> Packet:
        if quiet and slot not in self.sent:
            self.late.add(slot)
        if quiet:
            self.verified[slot] = self.verified.get(slot, 0) + 1
        self.sent.add(slot)
        self.announced[slot] = self.announced.get(slot, 0) + 1
        return (self.id, PROPOSE, self.id, slot)

    def _queue(self, item: tuple[int, int, int]) -> None:
        if item not in self.pending:
            self.pending.append(item)

    def next_packet(self, stage: int = FILL) -> Packet | None:
        """What to broadcast at this turn (None: nothing to say); ``stage``: INITIAL, FILL or QUIET."""
        if self.pending:
            action, code, slot = self.pending.popleft()
            return (self.id, action, code, slot)
        if self.rejecting:  # repeated until the conflicting tag's cancellation is heard (or retries run out)
            (slot, code), left = next(iter(self.rejecting.items()))
            del self.rejecting[(slot, code)]
            if left > 1:
                self.rejecting[(slot, code)] = left - 1  # to the back: other conflicts get their turn
            return (self.id, REJECT, code, slot)
        if self.is_anchor or stage == LAST:
            return None
        quiet = stage == QUIET
        free = self.free_slots()
        if not self.sent and free:  # the first claim (initial sequence), or a new one after a refusal
            # after a refusal a random free slot: a hidden group holds a run of them, not one
            slot = self.initial if (self.initial in free and self.initial not in self.claimed) else int(self.rng.choice(free))
            self.claimed.add(slot)
            return self._announce_slot(slot, quiet)
        young = sorted(s for s in self.sent if self.announced.get(s, 0) < self.min_announce)
        if young and not quiet:
            return self._announce_slot(young[0])
        if stage == FILL and len(self.sent) < self.max_slots and free:
            slot = int(self.rng.choice(free))
            self.claimed.add(slot)
            return self._announce_slot(slot)
        if self.sent:  # in turn; in the quiet part, the least verified first
            held = sorted(self.sent)
            self._announce += 1
            slot = min(held, key=lambda s: self.verified.get(s, 0)) if quiet else held[self._announce % len(held)]
            return self._announce_slot(slot, quiet)
        return None

    def on_packet(self, packet: Packet) -> None:
        sender, action, code, slot = packet
        if action == PROPOSE:
            owner = self.received.get(slot)
            if slot in self.sent or (owner is not None and owner != sender):
                self.rejecting[(slot, sender)] = REJECT_RETRIES  # conflict discovered (a neighbour or a hidden node)
            else:
                self.received[slot] = sender
        elif action == REJECT:
            if code == self.id:
                if slot in self.sent:  # lines 15-18: I am the source of the conflict
                    self.sent.discard(slot)
                    self.announced.pop(slot, None)
                    self.late.discard(slot)
                    self.verified.pop(slot, None)
                    self._queue((CANCEL, self.id, slot))
                self.refused.add(slot)
            elif self.received.get(slot) == code:  # lines 19-20
                del self.received[slot]
        elif action == CANCEL:
            self.rejecting.pop((slot, sender), None)
            if self.received.get(slot) == sender:
                del self.received[slot]


@dataclass
class ScheduleResult:
    slots: dict[int, tuple[int, ...]]  # tag -> slots it holds at the end of the phase
    heard: set[tuple[int, int]]  # (receiver, sender)
    packets: dict[str, int]  # per action
    collisions: int
    losses: int


def schedule_phase(
    clocks: Clocks,
    tags: NDArray[np.int64],
    anchors: NDArray[np.int64],
    tables: dict[int, set[int]],
    start_logical: float,
    linked: NDArray,
    params: TdmaParams,
    radio: UwbRadioParams,
    rng: np.random.Generator,
) -> ScheduleResult:
    """Run Alg. 1 for ``tags`` (and ``anchors`` as listeners) from their logical ``start_logical``."""
    nodes = {
        int(i): TdmaNode(int(i), tables.get(int(i), set()), params.n_slots, min_announce=params.min_announce, rng=rng)
        for i in tags
    }
    nodes.update({int(a): TdmaNode(int(a), set(), params.n_slots, is_anchor=True, rng=rng) for a in anchors})
    medium = Medium(linked, radio, rng)
    n_ticks = int(round(params.duration_s / params.tick_s))
    fill_from = int(n_ticks * params.initial_fraction)
    last_from = int(n_ticks * (1.0 - params.last_fraction))
    quiet_from = int(n_ticks * (1.0 - params.last_fraction - params.quiet_fraction))
    counts = {a: 0 for a in ACTIONS}
    heard: set[tuple[int, int]] = set()
    events = [(float(clocks.true_time(i, start_logical)), i, 0) for i in nodes]
    heapq.heapify(events)

    def settle(until: float) -> None:
        for f, receivers in medium.resolve(until):
            for r in receivers:
                if r in nodes:
                    heard.add((r, f.sender))
                    nodes[r].on_packet(f.payload)

    while events:
        t, i, k = heapq.heappop(events)
        settle(t)
        if rng.random() < (params.urgent_prob if nodes[i].urgent else params.broadcast_prob):
            stage = LAST if k >= last_from else QUIET if k >= quiet_from else FILL if k >= fill_from else INITIAL
            pkt = nodes[i].next_packet(stage)
            if pkt is not None:
                at = start_logical + (k + rng.uniform(0.0, 1.0 - radio.airtime_s / params.tick_s)) * params.tick_s
                medium.send(float(clocks.true_time(i, at)), i, pkt)
                counts[ACTIONS[pkt[1]]] += 1
        if k + 1 < n_ticks:
            heapq.heappush(events, (float(clocks.true_time(i, start_logical + (k + 1) * params.tick_s)), i, k + 1))
    settle(float("inf"))
    slots = {int(i): nodes[int(i)].confirmed() for i in tags}
    return ScheduleResult(slots, heard, counts, medium.collisions, medium.losses)
