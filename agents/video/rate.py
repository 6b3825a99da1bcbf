"""Bitrate adaptation for the shared video encoder: whose estimate counts, the target
bitrate it gives, and the resolution and frame rate that target can carry.

The vehicle encodes once for every viewer (:class:`agents.video.encoder.SharedEncoder`), so
there is one target for all of them. It follows the **pilot's** receiver estimate: the
pilot flies by this picture, and spectators (directly, or through the SFU's one copy)
get what the pilot gets. Without a pilot the SFU's estimate applies; without either,
the configured bitrate.

The estimates are the receivers' REMB (RTCP "receiver estimated maximum bitrate",
``goog-remb``): what Chromium sends to aiortc, which offers ``abs-send-time`` and
``goog-remb`` but not transport-wide congestion control, and what aiortc's own receiver
sends. A receiver's estimate (libwebrtc's AIMD, and aiortc's copy of it) starts from
what it first received, never rises above 1.5 times the rate it receives, and only
falls when it sees the queue grow (over-use: then to 0.85 times what arrives). So an
estimate that is low but rising says nothing about the link (a page that started
slowly, a still picture that compresses to little: Chromium's first REMBs are about
100 kbit/s while 400 kbit/s arrive); a **falling** one means congestion. A receiver's
estimate caps the target from its first fall on, and follows it back up until it is at
the configured bitrate again.

The delay-based REMB reacts in one to three seconds; a link cut to a fifth loses most
packets long before. So the receivers' loss reports (the fraction lost in each RTCP
receiver report) cap the target too, as libwebrtc's loss-based estimate does: above 10 %
lost, to what got through; below 2 %, the cap grows 8 % a second until it no longer
binds.

:class:`RateController` is plain logic on an injectable clock: the senders feed it
estimates, and it answers the target bitrate
and the :class:`Rung` of the :data:`LADDER`, with hysteresis (down at once, up one step
at a time, only with a margin and after a hold) so the picture does not oscillate.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Final, Literal, TypeAlias

__all__ = [
    "LADDER",
    "MIN_BITRATE",
    "RateController",
    "RetransmitBudget",
    "Role",
    "Rung",
    "fit_size",
]

#: Who a sender serves: the session's pilot (direct), the SFU's one copy for the
#: spectators, or a spectator connected directly (embedded mode, no SFU).
Role: TypeAlias = Literal["pilot", "sfu", "viewer"]

#: The target never goes below this (bit/s): below it VP8 at the smallest step is mush.
MIN_BITRATE: Final = 100_000


@dataclass(frozen=True)
class Rung:
    """One step of the ladder: the largest picture (fitted inside ``width`` x ``height``,
    aspect kept, never enlarged) and frame rate sent while the target is at least
    ``min_bitrate``. None means the camera's own size or rate."""

    width: int | None
    height: int | None
    fps: float | None
    min_bitrate: int


#: From the camera's own picture down to a slow small one. A step's ``min_bitrate`` is
#: where VP8 (libvpx realtime) still gives a clean picture at that size and rate; below
#: it, fewer pixels look better than blockier ones, and fewer frames keep each legible.
LADDER: Final[tuple[Rung, ...]] = (
    Rung(None, None, None, 700_000),  # the camera's own: 640x480@30 for the demo's
    Rung(480, 360, 20, 350_000),
    Rung(320, 240, 15, 160_000),
    Rung(320, 240, 10, 0),
)


def fit_size(width: int, height: int, rung: Rung) -> tuple[int, int]:
    """The size a ``width`` x ``height`` picture is sent at on ``rung``: fitted inside the
    rung's box with its aspect kept, never enlarged, even dimensions (VP8's 4:2:0)."""
    scale = 1.0
    if rung.width is not None:
        scale = min(scale, rung.width / width)
    if rung.height is not None:
        scale = min(scale, rung.height / height)
    if scale >= 1.0:
        return width, height
    return max(2, round(width * scale / 2) * 2), max(2, round(height * scale / 2) * 2)


@dataclass
class _Estimate:
    role: Role
    bitrate: int | None = None  # the latest REMB
    cap: int | None = None  # since its last fall, until back at the ceiling
    loss_cap: int | None = None  # since heavy loss, until back at the ceiling
    loss_cut_at: float = -1e9  # when loss last lowered loss_cap
    loss_grown_at: float = -1e9  # when it last grew
    probe: float = 1.0  # how far above its REMB the cap reaches, see RateController
    quiet_since: float = -1e9  # the last fall, loss cut or probe step


class RateController:
    """The target bitrate and ladder step of one shared encoder (see the module).

    * ``max_bitrate``: the most it sends, and what it sends with no estimate (the
      agent's configured ``bitrate``);
    * ``up_margin``, ``up_hold_s``: a step up needs a target ``up_margin`` times the
      upper step's minimum, held ``up_hold_s`` after the last change of step;
    * ``clock``: seconds, monotonic (tests inject their own).

    Feed it :meth:`attach`/:meth:`forget` as senders come and go, :meth:`estimate` for
    each REMB; read :attr:`target_bitrate` and
    :attr:`rung` (call :meth:`tick` before reading, so that a held step up happens).
    """

    #: An estimate this much below the receiver's previous one is a fall (congestion);
    #: AIMD estimates otherwise only grow.
    FALL_FRACTION: Final = 0.02
    #: Loss above this lowers the loss cap to what got through ...
    LOSS_HIGH: Final = 0.1
    #: ... at most this often (the reports that follow tell of packets sent before
    #: the cut, still queued on the link) ...
    LOSS_HOLD_S: Final = 1.0
    #: ... and loss below this lets it grow by LOSS_GROWTH a second.
    LOSS_LOW: Final = 0.02
    LOSS_GROWTH: Final = 1.08
    #: After a fall a receiver's estimate grows slowly near the rate it last saw (AIMD's
    #: additive increase), and never above 1.5 times what it receives: a restored link
    #: could take a minute to be believed. So after this long without a fall or loss
    #: the cap reaches PROBE_STEP above the estimate, and again after as long: sending
    #: more is what lets the receiver see the room (its estimate leaves the slow mode
    #: when what arrives passes what it saw), and a link without room says so with loss
    #: or a fall within a second, which ends the probe.
    PROBE_AFTER_S: Final = 5.0
    PROBE_STEP: Final = 1.15

    #: Changes of target smaller than this fraction are not applied: each starts a
    #: new VP8 stream (a keyframe), worth it only for a real change.
    STEP_FRACTION: Final = 0.1

    def __init__(
        self,
        *,
        max_bitrate: int,
        min_bitrate: int = MIN_BITRATE,
        ladder: Sequence[Rung] = LADDER,
        up_margin: float = 1.2,
        up_hold_s: float = 3.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_bitrate < min_bitrate:
            raise ValueError(f"bitrate {max_bitrate} is below the minimum {min_bitrate}")
        if not ladder or ladder[-1].min_bitrate != 0:
            raise ValueError("a ladder needs steps, the last one for any bitrate (0)")
        self.max_bitrate = max_bitrate
        self.min_bitrate = min_bitrate
        self.ladder = tuple(ladder)
        self.up_margin = up_margin
        self.up_hold_s = up_hold_s
        self.clock = clock
        self.target_bitrate = max_bitrate
        self.step = self._step_for(max_bitrate)
        self._step_changed = clock()
        self._estimates: dict[Hashable, _Estimate] = {}

    @property
    def rung(self) -> Rung:
        """The current step of the ladder."""
        return self.ladder[self.step]

    def attach(self, key: Hashable, role: Role) -> None:
        """A sender serving ``role`` is there (it has no estimate yet)."""
        self._estimates[key] = _Estimate(role)

    def forget(self, key: Hashable) -> None:
        """The sender is gone; its estimate no longer counts."""
        if self._estimates.pop(key, None) is not None:
            self._update(self._governing())

    def estimate(self, key: Hashable, bitrate: int) -> None:
        """The receiver behind ``key`` estimates it can take ``bitrate`` bit/s (REMB)."""
        entry = self._estimates.get(key)
        if entry is None:
            return
        fell = entry.bitrate is not None and bitrate < entry.bitrate * (1 - self.FALL_FRACTION)
        entry.bitrate = bitrate
        if fell:
            entry.probe, entry.quiet_since = 1.0, self.clock()
        if fell or entry.cap is not None:
            entry.cap = bitrate if bitrate * entry.probe < self.max_bitrate else None
        self._update(self._governing())

    def loss(self, key: Hashable, fraction: float) -> None:
        """The receiver behind ``key`` reports ``fraction`` (0-1) of the packets lost
        since its previous report (RTCP RR)."""
        entry = self._estimates.get(key)
        if entry is None:
            return
        now = self.clock()
        if fraction > self.LOSS_HIGH:
            if now - entry.loss_cut_at < self.LOSS_HOLD_S:
                return
            through = round(self.target_bitrate * (1 - fraction))
            entry.loss_cap = through if entry.loss_cap is None else min(entry.loss_cap, through)
            entry.loss_cut_at = entry.loss_grown_at = now
            entry.probe, entry.quiet_since = 1.0, now
        elif fraction < self.LOSS_LOW and entry.loss_cap is not None:
            grown = entry.loss_cap * self.LOSS_GROWTH ** min(now - entry.loss_grown_at, 1.0)
            entry.loss_cap = round(grown) if grown < self.max_bitrate else None
            entry.loss_grown_at = now
        else:
            return
        self._update(self._governing())

    def governing_role(self) -> Role | None:
        """Whose estimate sets the target now: the pilot's, else the SFU's, else None
        (the configured bitrate)."""
        for role in ("pilot", "sfu"):
            if any(e.role == role for e in self._estimates.values()):
                return role
        return None

    def tick(self) -> None:
        """Take a probe or a held step up when due (the encoder calls this every
        frame)."""
        now = self.clock()
        probed = False
        for entry in self._estimates.values():
            if entry.cap is not None and now - entry.quiet_since >= self.PROBE_AFTER_S:
                entry.probe *= self.PROBE_STEP
                entry.quiet_since = now
                if entry.cap * entry.probe >= self.max_bitrate:
                    entry.cap, entry.probe = None, 1.0
                probed = True
        if probed:
            self._update(self._governing())
        elif self.step > 0:
            self._choose_step()

    # --- internals -----------------------------------------------------------------------

    def _governing(self) -> int | None:
        """The cap that sets the target: the pilot's, else the SFU's (the lowest of
        several); None when that receiver saw no congestion, or nobody governs."""
        role = self.governing_role()
        caps = [
            c
            for e in self._estimates.values()
            if e.role == role
            for c in (None if e.cap is None else round(e.cap * e.probe), e.loss_cap)
            if c is not None
        ]
        return min(caps) if caps else None

    def _update(self, cap: int | None) -> None:
        target = (
            self.max_bitrate if cap is None else max(self.min_bitrate, min(self.max_bitrate, cap))
        )
        # Only a real change, either way: each change of target starts a new VP8
        # stream with a keyframe (libvpx takes no new bitrate once open), and Chromium
        # sends a REMB every few tens of milliseconds, each a little different.
        if (
            target in (self.max_bitrate, self.min_bitrate)
            or target >= self.target_bitrate * (1 + self.STEP_FRACTION)
            or target <= self.target_bitrate * (1 - self.STEP_FRACTION)
        ):
            self.target_bitrate = target
        self._choose_step()

    def _step_for(self, bitrate: int) -> int:
        return next(i for i, r in enumerate(self.ladder) if bitrate >= r.min_bitrate)

    def _choose_step(self) -> None:
        now = self.clock()
        lowest_fit = self._step_for(self.target_bitrate)
        if lowest_fit > self.step:  # down at once, as far as needed
            self.step, self._step_changed = lowest_fit, now
        elif (
            self.step > 0
            and self._roomy(self.ladder[self.step - 1])
            and now - self._step_changed >= self.up_hold_s
        ):  # up one step at a time, with a margin, after a hold
            self.step, self._step_changed = self.step - 1, now

    def _roomy(self, rung: Rung) -> bool:
        """Whether the target leaves the margin above ``rung``'s minimum (or is the
        ceiling itself, which no estimate holds back)."""
        if self.target_bitrate == self.max_bitrate:
            return self.target_bitrate >= rung.min_bitrate
        return self.target_bitrate >= rung.min_bitrate * self.up_margin


class RetransmitBudget:
    """How many of the packets a receiver reports lost (RTCP NACK) one sender may send
    again: at most ``share`` of the target bitrate, counted in packets of
    ``packet_bytes`` (a token bucket holding up to one second's worth).

    aiortc resends every packet a NACK names, at once and as often as asked. On a link
    that is already full, the resent packets are lost too and asked for again: a storm
    that keeps the link full long after the encoder stepped down (seen: seven packets
    in eight dropped on a 300 kbit/s link). libwebrtc's senders cap retransmissions in
    the same way.
    """

    def __init__(
        self,
        *,
        share: float = 0.25,
        packet_bytes: int = 1100,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.share = share
        self.packet_bytes = packet_bytes
        self.clock = clock
        self._tokens = 0.0
        self._at: float | None = None
        #: Packets refused so far.
        self.refused = 0

    def allow(self, wanted: int, bitrate: int) -> int:
        """How many of ``wanted`` packets may be resent now, at ``bitrate`` bit/s."""
        now = self.clock()
        per_s = self.share * bitrate / (8 * self.packet_bytes)
        elapsed = 1.0 if self._at is None else now - self._at
        self._at = now
        self._tokens = min(max(per_s, 1.0), self._tokens + per_s * elapsed)
        allowed = min(wanted, int(self._tokens))
        self._tokens -= allowed
        self.refused += wanted - allowed
        return allowed
