"""benchmarks.paper's data-channel paths, briefly, against an agent's control hub in this
process (no platform): the prober and the connect try over WebRTC, direct and through a
coturn on loopback (benchmarks.turn_server), the path check that keeps a column honest,
and the UDP delay proxy that puts a TURN user behind an emulated link.

The signalling goes over the agent's own control socket (the LAN path), which carries the
same messages as the platform's relay; the end-to-end quick run in test_paper_quick
covers the relay. Timing is asserted only where the proxy adds a known floor.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import cast

import pytest

from benchmarks import paper
from benchmarks.delay_proxy import UdpDelayProxy
from benchmarks.turn_server import TurnServer, stun_answers, turn_server
from tests.agents.car_rig import Rig, car_rig, make_grant
from tests.netlab import ensure_packages

# asyncio's timers may fire a hair early (clock resolution): lower bounds keep a margin.
EARLY_S = 0.001


@pytest.fixture(scope="module")
def turn(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TurnServer]:
    """One coturn on loopback for the module (installed first when missing)."""
    ensure_packages("coturn", log_path=tmp_path_factory.mktemp("apt") / "apt.log")
    with turn_server(log_dir=tmp_path_factory.mktemp("turn")) as server:
        yield server


@pytest.fixture
async def agent() -> AsyncIterator[Rig]:
    """The control tests' car rig (tests.agents.car_rig), its agent offering host
    candidates on loopback only, as paper's agents do."""
    async with car_rig() as rig:
        rig.hub.webrtc_options = {"ice_host_addresses": list(paper.LOOPBACK)}
        yield rig


# --------------------------------------------------------------------------------------
# The UDP delay proxy
# --------------------------------------------------------------------------------------


class _Echo(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.peers: list[tuple[str, int]] = []
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # The selector loop's datagram transport does not subclass DatagramTransport.
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.peers.append(addr)
        assert self.transport is not None
        self.transport.sendto(data, addr)


async def _udp_echo() -> tuple[asyncio.DatagramTransport, _Echo, int]:
    loop = asyncio.get_running_loop()
    transport, echo = await loop.create_datagram_endpoint(_Echo, local_addr=("127.0.0.1", 0))
    return transport, echo, transport.get_extra_info("sockname")[1]


def _client(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    sock.connect(("127.0.0.1", port))
    return sock


async def test_udp_proxy_delays_both_ways() -> None:
    loop = asyncio.get_running_loop()
    transport, _, port = await _udp_echo()
    try:
        async with UdpDelayProxy(target_port=port, delay_ms=30) as proxy_port:
            sock = _client(proxy_port)
            with sock:
                sent = loop.time()
                await loop.sock_sendall(sock, b"ping")
                assert await asyncio.wait_for(loop.sock_recv(sock, 100), 5) == b"ping"
                assert loop.time() - sent >= 0.060 - 2 * EARLY_S
    finally:
        transport.close()


async def test_udp_proxy_keeps_order_and_clients_apart() -> None:
    """Datagrams 2 ms apart under a 30 ms mean jitter would overtake each other if each
    were released at its own draw; two clients get two flows and their own answers."""
    loop = asyncio.get_running_loop()
    transport, echo, port = await _udp_echo()
    proxy = UdpDelayProxy(target_port=port, delay_ms=1, jitter_ms=30, seed=7)
    try:
        async with proxy as proxy_port:
            first, second = _client(proxy_port), _client(proxy_port)
            with first, second:
                for i in range(30):
                    await loop.sock_sendall(first, b"%d" % i)
                    await asyncio.sleep(0.002)
                await loop.sock_sendall(second, b"other")
                got = [await asyncio.wait_for(loop.sock_recv(first, 100), 5) for _ in range(30)]
                assert got == [b"%d" % i for i in range(30)]
                assert await asyncio.wait_for(loop.sock_recv(second, 100), 5) == b"other"
        assert proxy.flows == 2
        assert len(set(echo.peers)) == 2  # the target saw one address per client
    finally:
        transport.close()


async def test_udp_proxy_draws_the_jitter_once_per_burst() -> None:
    """Back to back, the second datagram queues behind the first and shares its delay
    instead of drawing its own (which would hold it up to max(X1, X2))."""
    loop = asyncio.get_running_loop()
    transport, _, port = await _udp_echo()
    gaps = []
    try:
        async with UdpDelayProxy(target_port=port, delay_ms=5, jitter_ms=40, seed=3) as proxy:
            sock = _client(proxy)
            with sock:
                for _ in range(5):
                    await loop.sock_sendall(sock, b"a")
                    await loop.sock_sendall(sock, b"b")
                    assert await asyncio.wait_for(loop.sock_recv(sock, 10), 5) == b"a"
                    first = loop.time()
                    assert await asyncio.wait_for(loop.sock_recv(sock, 10), 5) == b"b"
                    gaps.append(loop.time() - first)
    finally:
        transport.close()
    # Independent 40 ms draws would space them by tens of ms most of the time.
    assert max(gaps) < 0.010, gaps


# --------------------------------------------------------------------------------------
# coturn
# --------------------------------------------------------------------------------------


def test_turn_server_answers_stun_and_stops(tmp_path: Path) -> None:
    ensure_packages("coturn", log_path=tmp_path / "apt.log")
    with turn_server(log_dir=tmp_path) as server:
        assert stun_answers(server.host, server.port)
        username, password = server.credentials("session-1", ttl_s=60)
        assert username.endswith(":session-1") and password
        assert server.ice_servers("s", port=1234)[0]["urls"] == [
            "turn:127.0.0.1:1234?transport=udp"
        ]
    assert server.process.poll() is not None
    assert not stun_answers(server.host, server.port)


# --------------------------------------------------------------------------------------
# Data channels against an agent
# --------------------------------------------------------------------------------------


async def test_direct_data_channel_carries_commands_and_acks(agent: Rig) -> None:
    prober = await paper.DataChannelProber.open(
        agent.url, grant=make_grant(), path=paper.DC, keepalive_s=None
    )
    try:
        assert prober.client.ice_path == "webrtc_direct"
        for seq in range(3):
            ms, ok = await prober.probe(seq, "forward" if seq % 2 else "stop", {})
            assert ok and 0 < ms < paper.PROBE_TIMEOUT_S * 1000
        # Read while the channel is open: closing it reports the fall back to the socket.
        assert agent.events("control_path")[-1]["path"] == "webrtc_direct"
    finally:
        await prober.close()


async def test_turn_data_channel_goes_through_coturn(agent: Rig, turn: TurnServer) -> None:
    before = turn.allocations()
    prober = await paper.DataChannelProber.open(
        agent.url,
        grant=make_grant(),
        path=paper.DCT,
        ice_servers=turn.ice_servers("session-1"),
        keepalive_s=None,
    )
    try:
        ms, ok = await prober.probe(1, "stop", {})
        assert ok and ms > 0
        # Read while the channel is open: closing it reports the fall back to the socket.
        assert agent.events("control_path")[-1]["path"] == "webrtc_turn"
    finally:
        await prober.close()
    assert turn.allocations() > before


async def test_turn_behind_the_udp_delay_proxy_crosses_the_link(
    agent: Rig, turn: TurnServer
) -> None:
    async with UdpDelayProxy(target_port=turn.port, delay_ms=20) as proxy_port:
        prober = await paper.DataChannelProber.open(
            agent.url,
            grant=make_grant(),
            path=paper.DCT,
            ice_servers=turn.ice_servers("session-1", port=proxy_port),
            keepalive_s=None,
        )
        try:
            ms, ok = await prober.probe(1, "stop", {})
        finally:
            await prober.close()
    assert ok
    assert ms >= 40 - 2 * EARLY_S * 1000  # one round trip over the emulated link


async def test_a_path_that_is_not_the_one_claimed_fails(agent: Rig) -> None:
    client = paper.rtc_client(agent.url, grant=make_grant(), path=paper.DC)
    client.timeout_s = 2  # how long to wait for the agent to say "webrtc_turn"
    try:
        await client.start()
        await paper.rtc_path_check(client, paper.DC)
        with pytest.raises(paper.BenchError, match="not webrtc_turn"):
            await paper.rtc_path_check(client, paper.DCT)
    finally:
        await client.close()


async def test_connect_tries_time_every_step_and_leave_no_failsafe(
    agent: Rig, turn: TurnServer
) -> None:
    ms, phases, ok = await paper.ws_first_ack(agent.url, grant=make_grant())
    assert ok and set(phases) == {key for key, _ in paper.CONNECT_PHASES["ws"]}
    assert sum(phases.values()) == pytest.approx(ms, abs=0.01)
    for path, servers in ((paper.DC, []), (paper.DCT, turn.ice_servers("session-1"))):
        ms, phases, ok = await paper.rtc_first_ack(
            agent.url, grant=make_grant(), path=path, ice_servers=servers
        )
        assert ok, path
        assert set(phases) == {key for key, _ in paper.CONNECT_PHASES["rtc"]}
        assert sum(phases.values()) == pytest.approx(ms, abs=0.01)
        assert all(v >= 0 for v in phases.values())
    # Every try handed control back before leaving: no link-loss fail-safe.
    await asyncio.sleep(0.2)
    assert agent.hub.stats["failsafes"] == 0
    assert agent.hub.stats["commands"] == 3
