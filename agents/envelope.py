"""The safety envelope: the vehicle's actual state against its task's limits, all along.

:class:`~agents.safety.CommandGate` refuses a command that *would* take the vehicle past
the ceiling, the geofence or the speed limit. That is not enough: a latched throttle, a
gust, an autopilot's own return-to-launch climb or a car that keeps rolling after its
next command was refused all cross a limit with no command to refuse. So while a task
is current, :class:`EnvelopeWatch` reads :meth:`Adapter.state` ``CHECK_HZ`` times a
second and, when the vehicle is outside a limit, asks the adapter to bring it back
(:meth:`Adapter.envelope_recover`, with a :class:`~agents.vehicles.base.Breach`).

Per limit (``altitude``: metres above home against ``max_altitude_m``; ``geofence``:
metres from ``geofence_center`` against ``geofence_radius_m``; ``speed``: ground speed
against ``max_speed_mps``), :func:`band_for` gives three distances:

* **tolerance**: a breach is a value more than this past the limit (sensor noise and an
  autopilot settling on a limit set exactly at it are not breaches), or past the limit
  for ``DWELL_S`` (the speed: by more than half the tolerance, for an autopilot flying
  at a commanded speed equal to the limit reads a few cm/s over it all along);
* **margin**: the recovery aims this far inside the limit (``Breach.target``; never
  further out than the vehicle is);
* the breach ends (``restored``) once the value has stayed at least half the margin
  inside the limit for ``RESTORE_S`` (and, for a vehicle that says how it brakes, so has
  where it would come to rest).

**On its way out.** A vehicle that reports its velocity
(:attr:`~agents.vehicles.base.VehicleState.velocity`) and says how it brakes
(:meth:`Adapter.braking`) is also a breach while still inside, as soon as braking now
would no longer stop it within the tolerance (``Breach.rest``, the ``rest`` of the
``envelope_breach`` event): a return's climb or another ground station's command is
then caught before it crosses, not a braking distance after.

While breached the recovery is repeated when the value crosses the limit again, or
stays past it ``REPEAT_S`` after the last recovery without getting better; the
platform hears of each breach once (:class:`Envelope` decides, :class:`EnvelopeWatch`
acts and tells).

How far past a limit a vehicle can get depends on how fast it moves towards it and how
quickly it answers; each vehicle's figures are in ``docs/vehicles/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

from agents.geo import distance_m, offset
from agents.protocol import Limits
from agents.vehicles.base import Braking, Breach, VehicleState

log = logging.getLogger(__name__)

ALTITUDE, GEOFENCE, SPEED = "altitude", "geofence", "speed"

#: Checks per second: a vehicle climbing at 5 m/s moves 0.5 m between two.
CHECK_HZ = 10.0
#: Past the limit, but within the tolerance, for this long: a breach all the same.
DWELL_S = 2.0
#: A breach ends after the value stayed inside (by half the margin) this long.
RESTORE_S = 1.0
#: Still past the limit this long after a recovery, and no better: recover again.
REPEAT_S = 1.0
#: Never two recoveries of one limit closer together than this.
MIN_REPEAT_S = 0.25
#: From a check to the vehicle acting on its recovery (s): the check's own period.
ACT_S = 1.0 / CHECK_HZ

#: limit -> (tolerance: fraction of the limit, at most; margin: fraction, at most).
_BANDS: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    ALTITUDE: ((0.05, 0.5), (0.2, 2.0)),  # metres
    GEOFENCE: ((0.05, 1.0), (0.2, 5.0)),  # metres
    SPEED: ((0.05, 0.5), (0.2, 1.0)),  # m/s
}


#: Past the limit by more than this share of the tolerance for DWELL_S: a breach. The
#: speed's floor: ArduCopter flying at the 5 m/s it was asked for reports 5.05 m/s.
_DWELL_FLOOR: dict[str, float] = {ALTITUDE: 0.0, GEOFENCE: 0.0, SPEED: 0.5}


@dataclass(frozen=True)
class Band:
    """How a limit is watched; see the module docstring."""

    limit_value: float
    tolerance: float
    margin: float
    #: How far past the limit a value counts for the dwell rule.
    dwell_floor: float = 0.0

    @property
    def target(self) -> float:
        """Where a recovery aims: ``margin`` inside the limit."""
        return self.limit_value - self.margin

    @property
    def restore_below(self) -> float:
        """Inside by half the margin: the breach may end."""
        return self.limit_value - self.margin / 2


def band_for(limit: str, limit_value: float) -> Band:
    """The tolerance and margin of ``limit`` at ``limit_value``: 5 % and 20 % of it, at
    most 0.5 m / 2 m for the ceiling, 1 m / 5 m for the geofence, 0.5 / 1 m/s for the
    speed (so a 6 m ceiling is watched with 0.3 m and 1.2 m, a 60 m one with 0.5 m and
    2 m)."""
    (tol_share, tol_max), (margin_share, margin_max) = _BANDS[limit]
    tolerance = min(tol_max, tol_share * limit_value)
    return Band(
        limit_value=limit_value,
        tolerance=tolerance,
        margin=min(margin_max, margin_share * limit_value),
        dwell_floor=_DWELL_FLOOR[limit] * tolerance,
    )


@dataclass(frozen=True)
class Step:
    """What :meth:`Envelope.update` decided for one limit: ``kind`` is ``"breach"`` (a
    new breach: recover and report), ``"again"`` (recover again, already reported) or
    ``"restored"`` (back inside: report); ``duration_s`` is how long the breach lasted
    (restored only)."""

    kind: str
    breach: Breach
    duration_s: float = 0.0


@dataclass
class _Track:
    band: Band
    centre: tuple[float, float] | None = None
    breached: bool = False
    since: float = 0.0
    over_since: float | None = None
    inside_since: float | None = None
    acted_at: float = 0.0
    acted_value: float = 0.0
    dipped: bool = False


class Envelope:
    """The breach logic for one task's limits, without I/O or clock of its own: feed it
    states with :meth:`update`. Limits the task leaves unset, and values the vehicle
    cannot tell (None), are not watched."""

    def __init__(self, limits: Limits) -> None:
        self.tracks: dict[str, _Track] = {}
        if limits.max_altitude_m is not None:
            self.tracks[ALTITUDE] = _Track(band_for(ALTITUDE, limits.max_altitude_m))
        if limits.geofence_center is not None and limits.geofence_radius_m is not None:
            self.tracks[GEOFENCE] = _Track(
                band_for(GEOFENCE, limits.geofence_radius_m), centre=limits.geofence_center
            )
        if limits.max_speed_mps is not None:
            self.tracks[SPEED] = _Track(band_for(SPEED, limits.max_speed_mps))

    @property
    def breached(self) -> list[str]:
        """The limits breached now."""
        return [name for name, track in self.tracks.items() if track.breached]

    def _value(self, name: str, track: _Track, state: VehicleState) -> float | None:
        if name == ALTITUDE:
            return state.alt
        if name == SPEED:
            return state.speed_mps
        position = state.position
        if position is None or track.centre is None:
            return None
        return distance_m(track.centre, position)

    def _rest(
        self, name: str, track: _Track, state: VehicleState, braking: Braking | None
    ) -> float | None:
        """Where the vehicle comes to rest if it brakes now (the value of limit
        ``name``), when it is heading out and says how it brakes; else None."""
        velocity = state.velocity
        if braking is None or velocity is None:
            return None
        north, east, up = velocity
        if name == ALTITUDE:
            vertical = braking.vertical
            if vertical is None or state.alt is None or up <= 0:
                return None
            return state.alt + vertical.distance(up) + up * ACT_S
        horizontal, position = braking.horizontal, state.position
        speed = math.hypot(north, east)
        if name != GEOFENCE or horizontal is None or position is None or track.centre is None:
            return None
        if speed <= 0:
            return None
        ahead = (horizontal.distance(speed) + speed * ACT_S) / speed
        return distance_m(track.centre, offset(position, north * ahead, east * ahead))

    def update(self, state: VehicleState, now: float, braking: Braking | None = None) -> list[Step]:
        """Compare ``state`` (at monotonic time ``now``) with the limits; with the
        vehicle's ``braking`` and its velocity, also where it would come to rest."""
        steps: list[Step] = []
        for name, track in self.tracks.items():
            value = self._value(name, track, state)
            if value is not None:
                rest = self._rest(name, track, state, braking)
                step = self._update_one(name, track, value, now, rest)
                if step is not None:
                    steps.append(step)
        return steps

    def _breach(self, name: str, track: _Track, value: float, rest: float | None = None) -> Breach:
        band = track.band
        return Breach(
            limit=name,
            value=value,
            limit_value=band.limit_value,
            # Never further out than it is: caught on its way out, it stops there.
            target=min(band.target, value),
            centre=track.centre,
            rest=rest,
        )

    def _update_one(
        self, name: str, track: _Track, value: float, now: float, rest: float | None = None
    ) -> Step | None:
        band = track.band
        over = value > band.limit_value
        if not track.breached:
            if value <= band.limit_value + band.dwell_floor:
                track.over_since = None
            elif track.over_since is None:
                track.over_since = now
            dwelt = track.over_since is not None and now - track.over_since >= DWELL_S
            beyond = band.limit_value + band.tolerance
            heading_out = rest is not None and rest > beyond and value <= beyond
            if value > beyond or dwelt or heading_out:
                track.breached, track.since = True, now
                track.inside_since = None
                self._acted(track, value, now)
                return Step(
                    "breach", self._breach(name, track, value, rest if heading_out else None)
                )
            return None
        # Inside, and not on its way out again (braking now it would still rest inside).
        if max(value, rest or value) <= band.restore_below:
            if track.inside_since is None:
                track.inside_since = now
            if now - track.inside_since >= RESTORE_S:
                track.breached = False
                track.over_since = None
                return Step("restored", self._breach(name, track, value), now - track.since)
        else:
            track.inside_since = None
        if not over:
            track.dipped = True
            return None
        if now - track.acted_at < MIN_REPEAT_S:
            return None
        # Crossed again (a user, a gust), or no better a while after the last recovery.
        no_better = value > track.acted_value - band.margin / 4
        if track.dipped or (now - track.acted_at >= REPEAT_S and no_better):
            self._acted(track, value, now)
            return Step("again", self._breach(name, track, value))
        return None

    @staticmethod
    def _acted(track: _Track, value: float, now: float) -> None:
        track.acted_at, track.acted_value, track.dipped = now, value, False


#: Runs the correction for a breach; returns what was done, in a few words.
Recover = Callable[[Breach], Awaitable[str]]
#: Tells the platform and the users: ``(event, data)``.
Notify = Callable[[str, dict[str, Any]], Awaitable[None]]


class EnvelopeWatch:
    """Watches one task's limits on the vehicle's state (an async context manager).

    ``state`` is the adapter's :meth:`~agents.vehicles.base.Adapter.state`, ``braking``
    its :meth:`~agents.vehicles.base.Adapter.braking`. On a breach the watch awaits
    ``recover(breach)`` (the hub runs it under its command lock) and then
    ``notify("envelope_breach", {"limit", "value", "limit_value", "action"})`` (and
    ``"rest"`` when caught on its way out);
    when the vehicle is back inside, ``notify("envelope_restored", {"limit", "value",
    "limit_value", "duration_ms"})``. A recovery repeated during one breach is logged,
    not notified. Neither callback may stop the watch: their errors are logged.
    """

    def __init__(
        self,
        *,
        limits: Limits,
        state: Callable[[], VehicleState],
        recover: Recover,
        notify: Notify,
        braking: Callable[[], Braking | None] | None = None,
        period_s: float = 1.0 / CHECK_HZ,
    ) -> None:
        self.envelope = Envelope(limits)
        self.state = state
        self.braking = braking or (lambda: None)
        self.recover = recover
        self.notify = notify
        self.period_s = period_s
        #: Breaches seen so far (each reported once).
        self.breaches = 0
        self._task: asyncio.Task[None] | None = None

    @property
    def watching(self) -> bool:
        """Whether the task has any limit the vehicle can be checked against."""
        return bool(self.envelope.tracks)

    def start(self) -> None:
        """Start checking (nothing to do for a task without limits)."""
        if self._task is None and self.watching:
            self._task = asyncio.create_task(self._run(), name="envelope-watch")

    async def stop(self) -> None:
        """Stop checking; a recovery under way is cancelled. Idempotent."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def __aenter__(self) -> Self:
        self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    async def _run(self) -> None:
        next_at = time.monotonic()
        while True:
            try:
                await self.check_once(time.monotonic())
            except Exception:  # a dead watch would silently drop the envelope
                log.exception("envelope check failed")
            # An even pace, without bursting to catch up after a slow recovery.
            next_at = max(next_at + self.period_s, time.monotonic())
            await asyncio.sleep(next_at - time.monotonic())

    async def check_once(self, now: float) -> None:
        """One check: compare the state with the limits and act on what changed."""
        for step in self.envelope.update(self.state(), now, self.braking()):
            breach = step.breach
            if step.kind == "restored":
                log.warning("envelope: back inside the %s limit", breach.limit)
                await self._notify(
                    "envelope_restored",
                    {
                        "limit": breach.limit,
                        "value": round(breach.value, 2),
                        "limit_value": breach.limit_value,
                        "duration_ms": round(step.duration_s * 1000),
                    },
                )
                continue
            action = await self._recover(breach)
            log.warning(
                "envelope: %s %.2f past the limit %g (%s): %s",
                breach.limit,
                breach.value,
                breach.limit_value,
                step.kind,
                action,
            )
            if step.kind == "breach":
                self.breaches += 1
                data: dict[str, Any] = {
                    "limit": breach.limit,
                    "value": round(breach.value, 2),
                    "limit_value": breach.limit_value,
                    "action": action,
                }
                if breach.rest is not None:
                    data["rest"] = round(breach.rest, 2)
                await self._notify("envelope_breach", data)

    async def _recover(self, breach: Breach) -> str:
        try:
            return await self.recover(breach)
        except Exception as exc:  # reported as the action: the platform must know
            log.exception("envelope recovery failed")
            return f"recovery failed: {exc}"

    async def _notify(self, event: str, data: dict[str, Any]) -> None:
        try:
            await self.notify(event, data)
        except Exception:
            log.exception("envelope: telling %s failed", event)
