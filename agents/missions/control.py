"""The agent's autonomous missions: :class:`MissionControl` runs the mission of the
task the agent accepted, at most one at a time, idempotent per mission id.

The mission comes typed and checked in the signed task (``VehicleTask.mission``, the
union of the registered specs): a malformed one never gets here, the agent refuses its
whole task. The registry names the runner that flies each kind.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from typing import Any, Final

from agents.missions.kit import ArtifactSink, MissionHub, MissionRunner, Reporter
from agents.missions.registry import mission_of
from agents.protocol import VehicleTask
from agents.vehicles.base import Adapter

#: Finished missions whose result a re-sent task hears again.
REMEMBERED: Final = 256


class MissionControl:
    """The agent's autonomous missions: at most one :class:`MissionRunner`, idempotent
    per mission id. The agent calls :meth:`task_accepted` for every task it accepts
    and :meth:`task_ended` when the hub ends one (before its safe action).

    ``sensors`` are the agent's open sensors by configuration section, handed to every
    runner (see :class:`agents.missions.registry.Sensor`), and ``artifacts`` where they
    keep the files they make (agents.artifacts).
    """

    def __init__(
        self,
        *,
        hub: MissionHub,
        adapter: Adapter,
        report: Reporter,
        sensors: Mapping[str, Any] | None = None,
        artifacts: ArtifactSink | None = None,
    ) -> None:
        self.hub = hub
        self.artifacts = artifacts
        self.adapter = adapter
        self.report = report
        self.sensors: Mapping[str, Any] = sensors or {}
        self.runner: MissionRunner[Any] | None = None
        # Remembered across runners, by mission id: the results of the last REMEMBERED
        # finished missions; payloads released and release attempts for the agent's
        # whole life (a few ids: never forgotten, so never released twice).
        self.results: OrderedDict[str, tuple[str, dict[str, Any]]] = OrderedDict()
        self.released: dict[str, dict[str, Any]] = {}
        self.release_attempted: set[str] = set()

    def task_accepted(self, task: VehicleTask) -> None:
        """Start, keep or replace the runner for ``task.mission`` (None: nothing).

        * a payload already released for this mission id: ``payload_released`` is
          reported again (same position), nothing is flown or released;
        * the running mission has this id: nothing (no restart, no duplicate);
        * a finished mission had this id: its result is reported again;
        * a payload release was attempted for it but never confirmed:
          ``mission_failed``, nothing flies;
        * otherwise a new runner replaces the current one (which stops at once).
        """
        mission = task.mission
        if mission is None:
            return
        self._remember_finished()
        runner = self.runner
        if mission.id in self.released:
            self.report("payload_released", task.session_id, dict(self.released[mission.id]))
            return
        if runner is not None and runner.mission.id == mission.id and not runner.done:
            return
        if mission.id in self.results:
            event, data = self.results[mission.id]
            self.report(event, task.session_id, dict(data))
            return
        if mission.id in self.release_attempted:
            # Sent once and never confirmed (its runner was stopped mid-command): the
            # payload may be gone, so it is not flown for again.
            reason = "the payload release was attempted already and not confirmed"
            self.report(
                "mission_failed", task.session_id, {"mission": mission.id, "reason": reason}
            )
            return
        previous = None
        if runner is not None:
            runner.cancel()
            previous = runner.task
        runner_type = mission_of(mission).runner()
        self.runner = runner_type(
            mission,
            session_id=task.session_id,
            hub=self.hub,
            adapter=self.adapter,
            report=self.report,
            sensors=self.sensors,
            artifacts=self.artifacts,
            released=self.released,
            release_attempted=self.release_attempted,
        )
        self.runner.start(previous)

    def task_ended(self, task: VehicleTask) -> None:
        """The session ended: its mission stops at once (the hub's safe action follows)."""
        runner = self.runner
        if runner is not None and runner.session_id == task.session_id and not runner.done:
            runner.cancel()

    def _remember_finished(self) -> None:
        runner = self.runner
        if runner is None or not runner.done or runner.result is None:
            return
        self.results[runner.mission.id] = runner.result
        self.results.move_to_end(runner.mission.id)
        while len(self.results) > REMEMBERED:
            self.results.popitem(last=False)

    async def close(self) -> None:
        """Stop the runner (agent shutdown)."""
        if self.runner is not None:
            self.runner.cancel()
            await self.runner.wait()
