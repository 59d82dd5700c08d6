"""Device clocks and the gradient clock synchronisation phase (Paper 003, III-A, eq. 1-3).

Each device i has a hardware clock H_i(t) = h_i t + theta_i (eq. 1; rate h_i = 1 + drift,
offset theta_i from power-up), never adjusted, and a logical clock
L_i(t) = l_i H_i(t) + theta'_i (eq. 2) with l_i = 1 (the paper: hardware clocks are good
enough over a cycle) so only the logical offset theta'_i is maintained.

Synchronisation phase (fixed length in every device's logical time, at the start of each
cycle): time is cut into ticks; at each tick a device broadcasts a ``syn msg`` carrying its
logical time with probability ``broadcast_prob`` (at a random instant within the tick) and
listens otherwise. A receiver j of a message of i computes the offset (eq. 3)

    Delta_ji = L_i(t_send) + delta_hat - L_j(t_receive),

delta_hat the estimated communication delay (send + access + propagation + receive; the
paper measures its average with broadcast scripts), and keeps the latest Delta per
neighbour. Every ``round_ticks`` ticks it moves its clock towards the neighbours' average:
theta'_j += sum_i Delta_ji / (n + 1), the average over its n neighbours and itself (a tag
with a single neighbour would otherwise swap clocks with it forever), and forgets the
Deltas. Once the neighbours' average is within ``threshold_s`` of its own clock a device
stops adjusting until the next cycle; the phase itself ends on time (timeout). Messages are
lost to collisions and to loss like any frame (``radio.Medium``).

Merge rule (ours): a device that hears a neighbour more than ``jump_s`` ahead adopts that clock
at once. When two groups that drifted apart for minutes (~30 us/s between two crystals) meet,
averaging over the one link between them closes the gap by a fraction 1/(n+1) per round, and
the far members of the two groups stay hundreds of microseconds apart for cycles: enough for a
response of one group to overlap a poll of the other three hops away (measured on the
seven-tag runs). With the rule the merged group follows the clock that is ahead within a few
message hops, and averaging takes over again.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from graphslam.errors import ConfigError
from graphslam.sim.uwb.radio import Medium, UwbRadioParams


@dataclass(frozen=True)
class ClockParams:
    """Hardware clocks and message delay (s)."""

    rate_ppm: float = 20.0  # std of the hardware rate error (crystal oscillators: +-20 ppm)
    initial_offset_s: float = 5e-3  # hardware offsets U(0, this): devices switched on together
    delay_mean_s: float = 120e-6  # communication delay of a syn msg
    delay_jitter_s: float = 3e-6  # its std (the part the estimate cannot remove)

    def __post_init__(self) -> None:
        if min(self.rate_ppm, self.initial_offset_s, self.delay_jitter_s) < 0 or self.delay_mean_s <= 0:
            raise ConfigError("ClockParams: rates, offsets and delays must be >= 0 (delay_mean_s > 0)")


@dataclass(frozen=True)
class SyncParams:
    """The synchronisation phase (s)."""

    duration_s: float = 0.2
    tick_s: float = 2e-3
    broadcast_prob: float = 0.1  # per tick; listening is the more likely action
    round_ticks: int = 10
    threshold_s: float = 10e-6
    jump_s: float = 50e-6  # a neighbour further ahead than this: adopt its clock at once (a merge)

    def __post_init__(self) -> None:
        if not (self.duration_s > self.tick_s > 0 and 0 < self.broadcast_prob < 0.5 and self.round_ticks >= 1):
            raise ConfigError("SyncParams: need duration > tick > 0, 0 < broadcast_prob < 0.5, round_ticks >= 1")


class Clocks:
    """Hardware and logical clocks of N devices (eq. 1-2), true time t in s."""

    def __init__(self, rate: NDArray, hw_offset: NDArray) -> None:
        self.rate = np.asarray(rate, float).copy()
        self.hw_offset = np.asarray(hw_offset, float).copy()
        self.offset = np.zeros(len(self.rate))  # theta', the logical correction

    @classmethod
    def draw(cls, n: int, params: ClockParams, rng: np.random.Generator) -> "Clocks":
        return cls(1.0 + rng.normal(0.0, params.rate_ppm * 1e-6, n), rng.uniform(0.0, params.initial_offset_s, n))

    def __len__(self) -> int:
        return len(self.rate)

    def hardware(self, i: int | NDArray, t: float | NDArray) -> NDArray:
        return self.rate[i] * t + self.hw_offset[i]

    def logical(self, i: int | NDArray, t: float | NDArray) -> NDArray:
        return self.hardware(i, t) + self.offset[i]

    def true_time(self, i: int | NDArray, logical: float | NDArray) -> NDArray:
        """The true time at which device ``i``'s logical clock reads ``logical``."""
        return (logical - self.hw_offset[i] - self.offset[i]) / self.rate[i]


@dataclass
class SyncResult:
    heard: set[tuple[int, int]] = field(default_factory=set)  # (receiver, sender) pairs
    messages: int = 0
    collisions: int = 0
    losses: int = 0
    jumps: int = 0
    synced_at_s: dict[int, float] = field(default_factory=dict)  # device -> logical time into the phase when it stopped


def sync_phase(
    clocks: Clocks,
    devices: NDArray[np.int64],
    start_logical: float,
    linked: NDArray,
    params: SyncParams,
    clock_params: ClockParams,
    radio: UwbRadioParams,
    rng: np.random.Generator,
) -> SyncResult:
    """Run one synchronisation phase for ``devices`` (their phase starts when their own logical
    clock reads ``start_logical``); adjusts ``clocks.offset`` in place."""
    res = SyncResult()
    medium = Medium(linked, radio, rng)
    n_ticks = int(round(params.duration_s / params.tick_s))
    delay_hat = clock_params.delay_mean_s  # the estimate: the measured average delay
    deltas: dict[int, dict[int, float]] = {int(i): {} for i in devices}
    synced: set[int] = set()
    events = [(float(clocks.true_time(i, start_logical)), int(i), 0) for i in devices]
    heapq.heapify(events)

    def settle(until: float) -> None:
        for f, receivers in medium.resolve(until):
            sent_logical = f.payload
            for r in receivers:
                if r not in deltas:
                    continue  # not in this phase (e.g. a device switched off)
                res.heard.add((r, f.sender))
                t_recv = f.start + clock_params.delay_mean_s + rng.normal(0.0, clock_params.delay_jitter_s)
                d = sent_logical + delay_hat - float(clocks.logical(r, t_recv))
                if d > params.jump_s:  # merge rule: a group whose clock is ahead absorbs this one
                    clocks.offset[r] += d
                    deltas[r].clear()
                    synced.discard(r)
                    res.jumps += 1
                deltas[r][f.sender] = 0.0 if d > params.jump_s else d

    while events:
        t, i, k = heapq.heappop(events)
        settle(t)
        if k > 0 and k % params.round_ticks == 0 and i not in synced and deltas[i]:
            d = np.fromiter(deltas[i].values(), float)
            if abs(d.mean()) < params.threshold_s:
                synced.add(i)
                res.synced_at_s[i] = k * params.tick_s
            else:
                clocks.offset[i] += d.sum() / (len(d) + 1)
            deltas[i].clear()
        if rng.random() < params.broadcast_prob:
            at = start_logical + (k + rng.uniform(0.0, 1.0 - radio.airtime_s / params.tick_s)) * params.tick_s
            t_send = float(clocks.true_time(i, at))
            medium.send(t_send, i, float(clocks.logical(i, t_send)))
            res.messages += 1
        if k + 1 < n_ticks:
            heapq.heappush(events, (float(clocks.true_time(i, start_logical + (k + 1) * params.tick_s)), i, k + 1))
    settle(float("inf"))
    res.collisions, res.losses = medium.collisions, medium.losses
    return res
