"""The network lab (tests/netlab.py) behaves like the networks WebRTC meets in the field.

Two plain aiortc peers (tests/netlab_peer.py), one in the "vehicle" site and one in the
"user" site, each behind its own NAT router, signal through this test process and try to
connect with coturn (in the root namespace, the lab's "internet") as STUN/TURN server:

- behind endpoint-independent NATs STUN alone is enough, no relay is used;
- behind symmetric NATs STUN alone fails and TURN gets through;
- with the STUN/TURN server unreachable from both symmetric sites nothing connects;
- a cut uplink is noticed by the peers and, restored, carries a new connection.

The peers run with shortened aioice timeouts (``PEER_TIMEOUTS``) so that failure is
reported as the "failed" state within seconds instead of after aioice's internet
defaults (63.5 s per STUN transaction, 30 s of consent misses).

Needs root and network namespaces (skipped otherwise, with the reason); installs iptables
and coturn with apt-get when they are missing. Every lab is checked to leave nothing
behind (namespaces, interfaces, firewall rules, coturn, peer processes).
"""

from __future__ import annotations

import ipaddress
import os
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from services.sessions.ice import turn_credentials
from tests import netlab
from tests.netlab import NetLab, Turn, ensure_packages, leftovers, nat, netlab_available
from tests.netlab_peer import PeerProcess, connect_peers

ROOT = Path(__file__).resolve().parents[2]
TURN_SECRET = "netlab-test-secret"
# Fail fast: a STUN transaction gives up after 0.5+1+2+4 = 7.5 s; consent expires
# after 3 missed checks at ~1 s intervals.
PEER_TIMEOUTS: dict[str, Any] = {"stun_retries": 3, "consent_interval": 1.0, "consent_failures": 3}
CONNECT_S = 20.0  # bound on reaching "connected" (seen: ~0.5 s after signalling)
FAIL_S = 25.0  # bound on reaching "failed" (seen: ~7.5 s, one STUN transaction timeout)
LOSS_S = 10.0  # bound on noticing a cut link (seen: ~3.5 s, 3 consent misses)

_available, _why = netlab_available()
pytestmark = pytest.mark.skipif(not _available, reason=_why or "network lab unavailable")


def ice(
    turn: Turn, username: str | None = None, credential: str | None = None
) -> list[dict[str, Any]]:
    """RTCIceServer-shaped dicts: STUN always, TURN when given credentials."""
    servers: list[dict[str, Any]] = [{"urls": turn.stun_urls}]
    if username is not None:
        servers.append({"urls": turn.turn_urls, "username": username, "credential": credential})
    return servers


@pytest.fixture(scope="module", autouse=True)
def _packages_and_final_check(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Installs what the lab needs; after the module, nothing of any lab this process
    made may remain (namespaces, root interfaces or firewall rules, coturn)."""
    ensure_packages("iptables", "coturn", log_path=tmp_path_factory.mktemp("apt") / "apt.log")
    yield
    assert not leftovers(), leftovers()


@pytest.fixture
def turn(lab: NetLab) -> Iterator[Turn]:
    with lab.coturn(TURN_SECRET) as turn:
        yield turn


@pytest.fixture
def start_peer(lab: NetLab, turn: Turn, tmp_path: Path) -> Iterator[Callable[..., PeerProcess]]:
    """Starts a peer program in a site of the lab; stopped (and checked gone) on
    teardown, before coturn stops (a peer closing its TURN allocation talks to it)."""
    peers: list[PeerProcess] = []

    def start(site: str, role: str, ice_servers: list[dict[str, Any]]) -> PeerProcess:
        log = open(tmp_path / f"peer-{len(peers)}-{site}-{role}.log", "w")  # noqa: SIM115
        proc = lab.popen(
            site,
            PeerProcess.argv(role, ice_servers, **PEER_TIMEOUTS),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
        )
        log.close()  # the child has its own descriptor
        peer = PeerProcess(proc, name=f"{site}/{role}")
        peers.append(peer)
        return peer

    yield start
    for peer in peers:
        peer.close()
    assert all(peer.proc.poll() is not None for peer in peers)


def pair(
    start_peer: Callable[..., PeerProcess], ice_servers: list[dict[str, Any]]
) -> tuple[PeerProcess, PeerProcess, list[str], list[str]]:
    """A vehicle (offerer) and a user (answerer) peer, signalled; with the candidate
    types each gathered."""
    vehicle = start_peer("vehicle", "offer", ice_servers)
    user = start_peer("user", "answer", ice_servers)
    gathered_v, gathered_u = connect_peers(vehicle, user)
    return vehicle, user, gathered_v["candidates"], gathered_u["candidates"]


def credentials(name: str) -> tuple[str, str]:
    return turn_credentials(TURN_SECRET, name, ttl_s=600)


@nat("eim", "eim")
def test_eim_nat_connects_with_stun_only(lab, turn, start_peer):
    vehicle, user, cand_v, cand_u = pair(start_peer, ice(turn))
    # Each peer saw itself behind NAT: a server-reflexive candidate from coturn.
    assert "srflx" in cand_v and "srflx" in cand_u and "relay" not in cand_v + cand_u
    assert vehicle.state("connected", "failed", timeout=CONNECT_S) == "connected"
    assert user.state("connected", "failed", timeout=CONNECT_S) == "connected"
    for peer, other in ((vehicle, "user"), (user, "vehicle")):
        selected = peer.expect("selected", 5)
        assert "relay" not in (selected["local"], selected["remote"]), selected
        # Through the NATs: each talks to the other's router, not to its LAN address.
        assert selected["remote_addr"][0] == lab.site(other).wan_ip, selected
    assert vehicle.echo()["ok"]
    assert user.echo()["ok"]
    assert turn.allocations() == 0, turn.log()[-2000:]


@nat("symmetric", "symmetric")
def test_symmetric_nat_needs_turn(lab, turn, start_peer):
    # STUN only: the checks of every candidate pair time out, ICE fails.
    vehicle, user, cand_v, cand_u = pair(start_peer, ice(turn))
    assert "srflx" in cand_v and "srflx" in cand_u
    assert vehicle.state("connected", "failed", timeout=FAIL_S) == "failed"
    assert user.state("connected", "failed", timeout=FAIL_S) == "failed"
    assert turn.allocations() == 0

    # With TURN credentials: connected through a relay.
    vehicle, user, cand_v, cand_u = pair(start_peer, ice(turn, *credentials("sym")))
    assert "relay" in cand_v and "relay" in cand_u
    assert vehicle.state("connected", "failed", timeout=CONNECT_S) == "connected"
    assert user.state("connected", "failed", timeout=CONNECT_S) == "connected"
    selected = [vehicle.expect("selected", 5), user.expect("selected", 5)]
    assert any("relay" in (s["local"], s["remote"]) for s in selected), selected
    assert vehicle.echo()["ok"]
    assert turn.allocations() >= 1, turn.log()[-2000:]


@nat("symmetric", "symmetric")
def test_symmetric_nat_with_turn_blocked_does_not_connect(lab, turn, start_peer):
    for site in ("vehicle", "user"):
        lab.block(site, turn.host, turn.port, proto="udp")
    servers = ice(turn, *credentials("blocked"))
    vehicle, user, cand_v, cand_u = pair(start_peer, servers)
    # The server is unreachable: neither STUN nor TURN candidates, host ones only.
    assert set(cand_v) == set(cand_u) == {"host"}, (cand_v, cand_u)
    assert vehicle.state("connected", "failed", timeout=FAIL_S) == "failed"
    assert user.state("connected", "failed", timeout=FAIL_S) == "failed"
    assert turn.allocations() == 0

    # The block was the cause: lifted, the same peers' successors connect by relay.
    for site in ("vehicle", "user"):
        lab.unblock(site, turn.host, turn.port, proto="udp")
    vehicle, user, cand_v, cand_u = pair(start_peer, servers)
    assert "relay" in cand_v and "relay" in cand_u
    assert vehicle.state("connected", "failed", timeout=CONNECT_S) == "connected"
    assert vehicle.echo()["ok"]
    assert turn.allocations() >= 1


@nat("eim", "eim")
def test_link_cut_is_noticed_and_link_up_restores(lab, turn, start_peer):
    vehicle, user, _, _ = pair(start_peer, ice(turn))
    assert vehicle.state("connected", "failed", timeout=CONNECT_S) == "connected"
    assert user.state("connected", "failed", timeout=CONNECT_S) == "connected"
    assert vehicle.echo()["ok"]

    lab.link_down("vehicle")
    assert not vehicle.echo(timeout=2)["ok"]
    # Consent freshness expires on both sides (3 misses at ~1 s). aiortc has no
    # "disconnected": the connection ends "failed", or "closed" when its transports
    # shut down on their own.
    assert vehicle.state("failed", "closed", timeout=LOSS_S)
    assert user.state("failed", "closed", timeout=LOSS_S)

    lab.link_up("vehicle")
    vehicle, user, cand_v, _ = pair(start_peer, ice(turn))
    assert "srflx" in cand_v  # coturn is reachable again
    assert vehicle.state("connected", "failed", timeout=CONNECT_S) == "connected"
    assert vehicle.echo()["ok"]


def test_a_lab_leaves_alone_the_addresses_the_machine_must_reach(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A lab's bridge takes the route to its subnet: one holding the package registries'
    address (here a proxy at a documentation address) would cut off every apt-get and
    pip install while the lab is open, so the lab takes another."""
    first = netlab.PUBLIC_SUBNETS[0]
    monkeypatch.setattr(
        netlab, "_needed_addresses", lambda: (ipaddress.IPv4Network(f"{first[80 % 64]}/32"),)
    )
    taken = netlab._free_public_subnet()
    assert taken != first and not taken.overlaps(first)
