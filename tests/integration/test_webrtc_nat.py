"""Control over WebRTC across real NATs: the four network cases of the issue.

Each test builds a network lab (tests/netlab.py): the root namespace plays the internet,
with the platform (iouv.serve, on the lab's public address) and coturn (its STUN and TURN
server, whose URLs and shared secret the platform hands out); a car's agent on its
simulator runs as a process in the "vehicle" site, and Debian's Chromium, driven by
Playwright (tests/netlab_browser.py), is the user in the "user" site. Each site sits
behind its own NAT router. The user signs in, opens the session's page, and the page
does what it does for anyone: authenticates on the platform's relay socket, offers a
WebRTC connection there, and moves control to the data channels once they open.

1. Both sites behind endpoint-independent ("eim") NAT: STUN's server-reflexive
   addresses are enough, the connection ends direct and coturn carries none of the
   drive. (Both peers still allocate a relay while gathering, as TURN is configured;
   Chromium may first nominate a relayed pair that worked before the NATs' holes were
   punched, and the agent must follow it to the direct one: see
   ``agents.rtc._resume_nominated_checks``.)
2. Both behind symmetric NAT: hole punching fails, the connection goes through TURN.
3. Symmetric NAT and the TURN server unreachable: WebRTC cannot connect, the page keeps
   control on the relay on its own, and the user still drives.
4. The user's uplink cut while they drive on WebRTC: the vehicle's link-loss fail-safe
   fires (its agent, still online, reports it to the platform), and once the link is
   back the user drives again.

"The car moves" is read from the telemetry the page receives; which transport carried
each command and each positive ack is recorded in the page (``window.netlab``).

Needs root and network namespaces (skipped otherwise, with the reason); installs
iptables, coturn and Chromium when they are missing.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from django.utils import timezone

from fleet.models import Vehicle
from services.models import Session, SessionEvent
from services.sessions.signing import platform_public_key_pem
from tests import factories as f
from tests.browser import chromium_missing_reason
from tests.deployment import session_requested
from tests.netlab import NetLab, Turn, ensure_packages, leftovers, nat, netlab_available
from tests.netlab_browser import BrowserProcess
from tests.servers import platform_process
from tests.vehicles import car_served

ROOT = Path(__file__).resolve().parents[2]
TURN_SECRET = "nat-test-secret"
PASSWORD = "pw-for-tests"  # tests.factories.user's
#: The service's link-loss timeout. Long enough that a loaded machine never trips the
#: fail-safe by itself (the page sends a keepalive every 100 ms), short for case 4.
LINK_LOSS_MS = 2000
# Bounds, generous for a loaded 2-core machine (seen on a quiet one in brackets).
START_S = 45.0  # the agent registered, the task accepted (~3 s)
CONNECT_S = 30.0  # the page on a WebRTC path after it opened (~2 s)
FALLBACK_S = 40.0  # the page gave WebRTC up, on the relay (~14 s: 3 + 10 s of the page)
DRIVE_S = 20.0  # acks and a moved car while ArrowUp is held (~1 s)
FAILSAFE_S = 20.0  # the platform logged the fail-safe after the cut (~2.5 s)
RECOVER_S = 45.0  # the page hears the vehicle again after the link is back (~3 s)

_available, _why = netlab_available()
pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    pytest.mark.skipif(not _available, reason=_why or "network lab unavailable"),
]


@pytest.fixture(scope="module", autouse=True)
def _packages_and_final_check(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Installs what the lab and the user need; after the module, nothing of any lab
    this process made may remain."""
    ensure_packages("iptables", "coturn", log_path=tmp_path_factory.mktemp("apt") / "apt.log")
    if chromium_missing_reason() is not None:
        subprocess.run([str(ROOT / "bin" / "install-chromium")], check=True, timeout=600)
    reason = chromium_missing_reason()
    assert reason is None, reason
    yield
    assert not leftovers(), leftovers()


def wait_until(predicate: Callable[[], Any], *, within: float, what: str) -> Any:
    """Poll ``predicate`` (every 0.1 s) until it returns something truthy; that value.
    AssertionError naming ``what`` after ``within`` seconds."""
    deadline = time.monotonic() + within
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {within} s waiting for {what}")
        time.sleep(0.1)


def _tail(path: Path, chars: int = 3000) -> str:
    with contextlib.suppress(OSError):
        return path.read_text(errors="replace")[-chars:]
    return ""


@dataclass
class World:
    """One lab with everything running: coturn, the platform, the car's agent, and a
    session deployed on the car for ``user``; ``browser()`` starts the user's Chromium
    in the user site."""

    lab: NetLab
    turn: Turn
    base: str
    vehicle: Vehicle
    session: Session
    logs: Path
    stack: contextlib.ExitStack
    browsers: list[BrowserProcess] = field(default_factory=list)

    def browser(self) -> BrowserProcess:
        """Chromium in the user site, up (not yet on any page)."""
        log_path = self.logs / f"browser-{len(self.browsers)}.log"
        with open(log_path, "w") as log:
            proc = self.lab.popen(
                "user",
                BrowserProcess.argv(),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
                cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
            )
        browser = BrowserProcess(proc, log_path)
        self.browsers.append(browser)
        self.stack.callback(browser.close)
        browser.started()
        return browser

    def open_session_page(self, browser: BrowserProcess) -> None:
        """Sign in as the session's user and open its page (the controller)."""
        browser.call(
            "open",
            within=60,
            base=self.base,
            username=self.session.user.username,
            password=PASSWORD,
            path=f"/sessions/{self.session.pk}/",
        )
        browser.wait("c && c.role === 'controller'", 30)

    def session_row(self) -> Session:
        return Session.objects.get(pk=self.session.pk)

    def events(self, kind: str) -> list[SessionEvent]:
        return list(SessionEvent.objects.filter(session=self.session, kind=kind).order_by("seq"))

    def agent_log(self, chars: int = 3000) -> str:
        return _tail(self.logs / "agent.log", chars)


@pytest.fixture
def world(lab: NetLab, tmp_path: Path) -> Iterator[World]:
    logs = tmp_path / "logs"
    logs.mkdir()
    with contextlib.ExitStack() as stack:
        turn = stack.enter_context(lab.coturn(TURN_SECRET))
        env = {
            "IOUV_STUN_URLS": ",".join(turn.stun_urls),
            "IOUV_TURN_URLS": ",".join(turn.turn_urls),
            "IOUV_TURN_SECRET": TURN_SECRET,
            # Plain http on an address that is not loopback: no redirect to https, and
            # cookies the browser keeps over http.
            "SECURE_SSL_REDIRECT": "0",
            "SECURE_COOKIES": "0",
        }
        base = stack.enter_context(platform_process(host=lab.public_ip, extra_env=env))
        car, credential, service = car_served(
            "car-nat",
            service="drive-car-nat",
            features=["camera_arm"],
            link_loss_timeout_ms=LINK_LOSS_MS,
        )
        user = f.user("alice")
        configs = tmp_path / "agents"
        configs.mkdir()
        config = {
            "platform_url": base.replace("http://", "ws://"),
            "platform_public_key": platform_public_key_pem(),
            "vehicle_id": str(car.pk),
            "vehicle_name": car.name,
            "credential": credential,
            "adapter": "car",
            "adapter_options": {"camera_arm": True, "origin": [f.HOME[0], f.HOME[1]]},
        }
        (configs / "car-nat.json").write_text(json.dumps(config))
        with open(logs / "agent.log", "w") as log:
            agent = lab.popen(
                "vehicle",
                [sys.executable, "-m", "agents", "sim", "fleet", "--configs", str(configs)],
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
            )
        # Registered after the platform is gone would be noise: the agent stops first.
        stack.callback(_stop, agent)

        def registered() -> bool:
            if agent.poll() is not None:
                raise AssertionError(f"the agent exited:\n{_tail(logs / 'agent.log')}")
            return Vehicle.objects.get(pk=car.pk).status == Vehicle.Status.IDLE

        wait_until(registered, within=START_S, what="the car's agent to register")
        session = session_requested(user=user, service=service, target=f.HOME).session
        wait_until(
            lambda: SessionEvent.objects.filter(session=session, kind="task_accepted").exists(),
            within=START_S,
            what="the car's agent to accept the task",
        )
        session = Session.objects.select_related("user").get(pk=session.pk)
        yield World(lab, turn, base, car, session, logs, stack)


def _stop(proc: subprocess.Popen[Any]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# -- what the page says -------------------------------------------------------------------

#: The candidate pair Chromium's connection uses: types and the remote address.
SELECTED_PAIR = """(async () => {
  const stats = await c.pc.getStats();
  let pair = null;
  stats.forEach((r) => {
    if (r.type === "transport" && r.selectedCandidatePairId) {
      pair = stats.get(r.selectedCandidatePairId);
    }
  });
  if (!pair) return null;
  const local = stats.get(pair.localCandidateId);
  const remote = stats.get(pair.remoteCandidateId);
  return { local: local.candidateType, remote: remote.candidateType,
           remote_address: remote.address || remote.ip, remote_port: remote.port };
})()"""


#: Bytes of data (DTLS: SCTP and media, not ICE's checks) Chromium sent and received on
#: candidate pairs through a TURN relay, and on the others.
PAIR_BYTES = """(async () => {
  const stats = await c.pc.getStats();
  const bytes = { relay: 0, direct: 0 };
  stats.forEach((r) => {
    if (r.type !== "candidate-pair") return;
    const local = stats.get(r.localCandidateId);
    const remote = stats.get(r.remoteCandidateId);
    const relayed = local.candidateType === "relay" || remote.candidateType === "relay";
    bytes[relayed ? "relay" : "direct"] += (r.bytesSent || 0) + (r.bytesReceived || 0);
  });
  return bytes;
})()"""


def location(browser: BrowserProcess) -> dict[str, float]:
    """The car's position, from the telemetry the page receives."""
    return browser.wait("window.netlab.telemetry.location", 20)


def drive_forward(browser: BrowserProcess, transport: str) -> dict[str, Any]:
    """Hold ArrowUp (the car's forward) until at least three more commands were acked
    on ``transport`` and the telemetry shows the car a few centimetres further; then
    let go. Returns the page's records (``window.netlab``)."""
    start = location(browser)
    acks = browser.eval(f"window.netlab.acks.{transport}")
    moved = (
        f"(() => {{ const p = window.netlab.telemetry.location;"
        f" return p && Math.hypot(p.lat - {start['lat']}, p.lon - {start['lon']}) > 5e-7; }})()"
    )
    browser.call("key", action="down", key="ArrowUp")
    try:
        browser.wait(f"window.netlab.acks.{transport} >= {acks + 3} && {moved}", DRIVE_S)
    finally:
        browser.call("key", action="up", key="ArrowUp")
    # Let go: the page sends "stop" (on the urgent channel when on WebRTC).
    browser.wait(f"(window.netlab.sent.{transport}.stop || 0) >= 1", DRIVE_S)
    record = browser.eval("window.netlab")
    end = record["telemetry"]["location"]
    metres = math.hypot(end["lat"] - start["lat"], (end["lon"] - start["lon"]) * 0.76) * 111_320
    assert metres > 0.05, (start, end)
    return record


# -- the cases -----------------------------------------------------------------------------


@nat("eim", "eim")
def test_behind_eim_nats_the_user_drives_on_a_direct_connection(world: World) -> None:
    browser = world.browser()
    world.open_session_page(browser)
    # Both sides gathered a TURN candidate too; the page may first hear "webrtc_turn"
    # when Chromium nominated the relayed pair first, then the better pair once the
    # NATs' holes were punched.
    browser.wait("c.channels && c.path === 'webrtc_direct'", CONNECT_S)
    # Through both NATs, STUN's mappings: Chromium talks to the vehicle's router.
    pair = browser.eval(SELECTED_PAIR)
    assert pair is not None and pair["local"] != "relay" and pair["remote"] != "relay", pair
    assert pair["remote_address"] == world.lab.site("vehicle").wan_ip, pair

    before = browser.eval(PAIR_BYTES)
    record = drive_forward(browser, "datachannel")
    after = browser.eval(PAIR_BYTES)
    # Control went on the data channels only, nothing on the relay socket, and coturn
    # carried little of it. (It did allocate: each peer gathers a relayed candidate
    # when TURN is configured, before ICE knows that it will not need it.) On a
    # saturated machine Chromium has moved to the relayed pair for a moment (1.3 kB
    # against 11.5 kB direct, seen once) when a consent check on the direct pair came
    # late; it came back, and most of the driving went direct.
    assert record["sent"]["websocket"] == {}, record
    assert record["acks"]["websocket"] == 0, record
    direct, relayed = after["direct"] - before["direct"], after["relay"] - before["relay"]
    assert direct > 0 and relayed <= direct / 4, (before, after)

    wait_until(
        lambda: world.session_row().control_path == "webrtc_direct",
        within=10,
        what="the platform to record the direct path",
    )
    assert world.events("control_path")[-1].data["path"] == "webrtc_direct"
    assert browser.eval("c.path") == "webrtc_direct"


@nat("symmetric", "symmetric")
def test_behind_symmetric_nats_the_user_drives_through_turn(world: World) -> None:
    browser = world.browser()
    world.open_session_page(browser)
    browser.wait("c.channels && c.path === 'webrtc_turn'", CONNECT_S)
    pair = browser.eval(SELECTED_PAIR)
    assert pair is not None and "relay" in (pair["local"], pair["remote"]), pair

    before = browser.eval(PAIR_BYTES)
    record = drive_forward(browser, "datachannel")
    after = browser.eval(PAIR_BYTES)
    assert record["sent"]["websocket"] == {}, record
    assert record["acks"]["websocket"] == 0, record
    assert after["relay"] > before["relay"], (before, after)
    assert after["direct"] == before["direct"], (before, after)

    wait_until(
        lambda: world.session_row().control_path == "webrtc_turn",
        within=10,
        what="the platform to record the TURN path",
    )
    assert world.turn.allocations() >= 1, world.turn.log()[-3000:]
    assert browser.eval("c.path") == "webrtc_turn"


@nat("symmetric", "symmetric")
def test_with_turn_unreachable_the_user_stays_on_the_relay_and_drives(world: World) -> None:
    turn = world.turn
    for site in ("vehicle", "user"):
        for proto in ("udp", "tcp"):
            world.lab.block(site, turn.host, turn.port, proto)
    browser = world.browser()
    world.open_session_page(browser)
    # The page tries WebRTC, gives it up after its 10 s, and keeps control on the relay
    # without the user doing anything (a retry is scheduled for much later).
    browser.wait("c.rtcRetry !== undefined && !c.pc && !c.channels", FALLBACK_S)
    assert browser.eval("c.path") == "relay"

    record = drive_forward(browser, "websocket")
    assert record["sent"]["datachannel"] == {}, record
    assert record["acks"]["datachannel"] == 0, record

    assert world.session_row().control_path == "relay"
    assert [e.data["path"] for e in world.events("control_path")] == ["relay"]
    assert turn.allocations() == 0, turn.log()[-3000:]


@nat("eim", "eim")
def test_a_cut_user_link_trips_the_failsafe_and_the_user_drives_again(world: World) -> None:
    browser = world.browser()
    world.open_session_page(browser)
    browser.wait("c.channels && c.path === 'webrtc_direct'", CONNECT_S)
    drive_forward(browser, "datachannel")
    early = world.events("unintentional_end")
    assert not early, ([e.data for e in early], world.agent_log())

    # The user's site goes dark (a dead radio link): the page's keepalives stop reaching
    # the vehicle, whose watchdog makes it safe after the link-loss timeout. The vehicle
    # is still online, so its agent reports that to the platform.
    cut_at = timezone.now()
    world.lab.link_down("user")
    try:
        events = wait_until(
            lambda: world.events("unintentional_end"),
            within=FAILSAFE_S,
            what=f"the platform to log the fail-safe\n{world.agent_log()}",
        )
        wait_until(
            lambda: Vehicle.objects.get(pk=world.vehicle.pk).status == Vehicle.Status.FAILSAFE,
            within=10,
            what="the car's status to say fail-safe",
        )
    finally:
        world.lab.link_up("user")
    assert (events[0].data["cause"], events[0].data["action"]) == ("link_lost", "stop")
    # The watchdog fires once the link-loss timeout has passed since the page's last
    # keepalive (sent at most 100 ms before the cut), and not much later.
    after_s = (events[0].created_at - cut_at).total_seconds()
    assert LINK_LOSS_MS / 1000 - 0.2 <= after_s < FAILSAFE_S, after_s

    # The link is back: the page hears of the fail-safe, and the user drives again on
    # whatever path carries the page now.
    browser.wait("c.stats.failsafes >= 1 && c.role === 'controller'", RECOVER_S)
    path = browser.wait("c.path", RECOVER_S)
    assert path in ("webrtc_direct", "webrtc_turn", "relay"), path
    transport = "datachannel" if browser.eval("!!c.channels") else "websocket"
    drive_forward(browser, transport)

    # The platform saw the user come back: the same link heard again, or a new one.
    def back() -> bool:
        recovered = world.events("link_recovered")
        reconnected = [e for e in world.events("user_connected") if e.created_at > cut_at]
        return bool(recovered or reconnected)

    wait_until(back, within=10, what="the platform to hear the user again")
    wait_until(
        lambda: Vehicle.objects.get(pk=world.vehicle.pk).status == Vehicle.Status.IN_SERVICE,
        within=10,
        what="the car back in service",
    )
