"""benchmarks.paper in quick mode, end to end, and the delay proxy it emulates links with.

The end-to-end test runs the real platform (iouv.serve on the test database, Redis channel
layer), real agent processes, the echo server and coturn (installed when missing), then
checks that every output exists and is well-formed, the data-channel columns and connect
tries included. It asserts nothing about timing: the machine may be busy.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import gzip
import json
import re
from pathlib import Path
from typing import Any

import pytest
from django.conf import settings

from benchmarks import paper
from benchmarks.delay_proxy import DelayProxy, Link
from tests.netlab import ensure_packages
from tests.servers import platform_process

# --------------------------------------------------------------------------------------
# The delay proxy
# --------------------------------------------------------------------------------------

# asyncio's timers may fire a hair early (clock resolution): lower bounds keep a margin.
EARLY_S = 0.001


async def _server(handler) -> tuple[asyncio.Server, int]:  # type: ignore[no-untyped-def]
    server = await asyncio.start_server(handler, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1]


async def test_delay_is_applied_in_both_directions() -> None:
    loop = asyncio.get_running_loop()
    arrived = loop.create_future()

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"hello")  # unprompted: the server-to-client direction
        await writer.drain()
        await reader.readexactly(4)
        arrived.set_result(loop.time())
        writer.close()

    server, port = await _server(handler)
    async with server, DelayProxy(target_port=port, delay_ms=40, jitter_ms=0) as proxy_port:
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy_port)
        connected = loop.time()
        assert await reader.readexactly(5) == b"hello"
        assert loop.time() - connected >= 0.040 - EARLY_S
        sent = loop.time()
        writer.write(b"ping")
        await writer.drain()
        assert await arrived - sent >= 0.040 - EARLY_S
        writer.close()


async def test_order_is_kept_when_the_jitter_would_reorder() -> None:
    """Chunks 2 ms apart with a 30 ms mean jitter would overtake each other if each
    were released at its own draw."""
    received = bytearray()
    done = asyncio.Event()

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while chunk := await reader.read(1024):
            received.extend(chunk)
            writer.write(chunk)  # and back: the other direction carries them too
            await writer.drain()
        done.set()
        writer.close()

    expected = b"".join(b"%d," % i for i in range(60))
    server, port = await _server(handler)
    proxy = DelayProxy(target_port=port, delay_ms=1, jitter_ms=30, seed=7)
    async with server, proxy as proxy_port:
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy_port)
        for i in range(60):
            writer.write(b"%d," % i)
            await writer.drain()
            await asyncio.sleep(0.002)
        echoed = await reader.readexactly(len(expected))
        writer.write_eof()
        await asyncio.wait_for(done.wait(), 10)
        writer.close()
    assert bytes(received) == expected
    assert echoed == expected
    assert proxy.chunks > 30  # they really travelled as separate chunks


async def test_close_propagates_both_ways_and_leaving_aborts() -> None:
    server_got: list[bytes] = []
    server_saw_eof = asyncio.Event()

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        first = not server_saw_eof.is_set()
        if first:
            writer.write(b"bye")
            writer.write_eof()  # the server is done talking ...
        with contextlib.suppress(ConnectionResetError):
            server_got.append(await reader.read())  # ... the client still talks, then closes
        server_saw_eof.set()
        writer.close()

    server, port = await _server(handler)
    async with server:
        async with DelayProxy(target_port=port, delay_ms=5, jitter_ms=2) as proxy_port:
            reader, writer = await asyncio.open_connection("127.0.0.1", proxy_port)
            assert await reader.read() == b"bye"  # data, then the server's EOF
            writer.write(b"last")
            writer.write_eof()
            await asyncio.wait_for(server_saw_eof.wait(), 5)
            assert server_got == [b"last"]
            writer.close()

            # A connection still open when the proxy stops is dropped, not left hanging.
            reader2, writer2 = await asyncio.open_connection("127.0.0.1", proxy_port)
            await asyncio.sleep(0.05)
        with contextlib.suppress(ConnectionResetError):  # an abort may arrive as a reset
            assert await asyncio.wait_for(reader2.read(), 5) == b""
        writer2.close()
        await asyncio.sleep(0.05)
        assert server_got[1:] in ([], [b""])  # the server's side was dropped too


async def test_a_refused_target_closes_the_client() -> None:
    async with DelayProxy(target_port=paper.free_port(), delay_ms=1) as proxy_port:
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy_port)
        with contextlib.suppress(ConnectionResetError):
            assert await asyncio.wait_for(reader.read(), 5) == b""
        writer.close()


def test_link_figures() -> None:
    link = Link("lte", delay_ms=22.5, jitter_ms=6.13)
    assert link.rtt_min_ms == 45.0
    assert link.rtt_mean_ms == pytest.approx(57.26)
    with pytest.raises(ValueError):
        Link("bad", delay_ms=-1)


def test_interval_rule_reproduces_the_papers_intervals() -> None:
    for (scenario, path), (figures, interval) in paper.PAPER_TC1.items():
        stats = paper.Stats(1, figures[0], figures[1], figures[2], figures[3], 0, 0)
        if scenario != "3g":  # the paper's one exception
            assert paper.interval_from(stats) == interval, (scenario, path)


# --------------------------------------------------------------------------------------
# Quick mode, end to end
# --------------------------------------------------------------------------------------

_NUMBER = re.compile(r"^-?\d+(\.\d+)?$")


def _tables(markdown: str) -> list[list[list[str]]]:
    """Every markdown table as rows of cells (the header first, the rule dropped)."""
    tables: list[list[list[str]]] = []
    current: list[list[str]] = []
    for line in [*markdown.splitlines(), ""]:
        if line.startswith("|"):
            if not re.fullmatch(r"\|(---\|)+", line):
                current.append([c.strip() for c in line.strip("|").split("|")])
        elif current:
            tables.append(current)
            current = []
    return tables


@pytest.mark.postgres
@pytest.mark.redis
@pytest.mark.django_db(transaction=True)
@pytest.mark.cost(50)  # the benchmark's quick run, end to end
async def test_quick_mode_writes_every_output(tmp_path: Path) -> None:
    ensure_packages("coturn", log_path=tmp_path / "apt.log")  # the datachannel_turn column
    plan = paper.Plan.quick()
    # As the benchmark runs its platform (benchmarks.paper.bench_env): its sessions
    # come faster than any user's budget allows.
    with platform_process(extra_env={"IOUV_RATE_LIMITS": "0"}) as base:
        meta = await paper.run(
            plan, base=base, out=tmp_path, command="pytest quick", var_dir=settings.VAR_DIR
        )

    _check_outputs(tmp_path, plan, meta)


def _check_outputs(out: Path, plan: paper.Plan, meta: dict[str, Any]) -> None:
    # raw.csv.gz: exactly the planned commands for TC1 and TC2, some for TC3 and the long run.
    with gzip.open(out / "raw.csv.gz", "rt", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == meta["samples"]
    counts: dict[tuple[str, str, str], int] = {}
    for row in rows:
        key = (row["scenario"], row["test"], row["path"])
        counts[key] = counts.get(key, 0) + 1
        assert float(row["response_ms"]) > 0
        assert row["ok"] == "True", row  # every command was executed by its car
    for name in plan.scenarios:
        scenario = paper.SCENARIOS[name]
        for path in plan.tc1_paths(scenario):
            assert counts[(name, "tc1", path)] == plan.tc1_count
        for path in ("echo", "p2p", "relay"):
            assert counts[(name, "tc2", path)] == sum(plan.tc2_counts)
        # The data channels: direct on loopback only, through TURN everywhere.
        dc_paths = ["datachannel", "datachannel_turn"] if name == "local" else ["datachannel_turn"]
        assert meta["datachannel"]["paths"][name] == dc_paths
        for path in dc_paths:
            assert counts[(name, "tc1", path)] == plan.tc1_count
            assert counts[(name, "tc2", path)] == sum(plan.tc2_counts)
        if name in plan.tc3_scenarios:
            for path in ("p2p", "relay"):
                assert counts[(name, "tc3", path)] >= plan.vehicles * len(plan.tc3_durations_s)
                vehicles = {
                    r["vehicle"] for r in rows if (r["scenario"], r["test"]) == (name, "tc3")
                }
                assert vehicles == {str(i) for i in range(1, plan.vehicles + 1)}
    assert counts[("remote", "long", "p2p")] >= 1
    connect_paths = ("p2p", "relay", "datachannel", "datachannel_turn")
    for path in connect_paths:
        assert counts[("local", "connect", path)] == plan.connect_tries
        assert len(meta["datachannel"]["connect_phases"][path]) == plan.connect_tries
    assert not any(test == "connect" and scenario != "local" for scenario, test, _ in counts)
    assert meta["datachannel"]["turn"]["allocations"] >= plan.connect_tries

    with open(out / "summary.csv", newline="") as fh:
        summary = list(csv.DictReader(fh))
    assert len(summary) == len({(r["scenario"], r["test"], r["path"], r["step"]) for r in rows})
    for line in summary:
        for column in ("min_ms", "max_ms", "avg_ms", "avg_dev_ms", "median_ms", "p95_ms"):
            assert _NUMBER.match(line[column]), (column, line)
        # A connect try is one command: it has no interval.
        assert _NUMBER.match(line["interval_ms"]) or line["test"] == "connect", line

    # report.md: the tables are filled; the figures our columns hold are numbers.
    report = (out / "report.md").read_text()
    tables = _tables(report)
    assert len(tables) >= 1 + 2 * len(plan.scenarios) + 3  # links, TC1+TC2 each, TC3...
    for table in tables:
        header, *body = table
        assert body, header
        for cells in body:
            assert len(cells) == len(header), (header, cells)
            assert all(cell for cell in cells[1:]), (header, cells)
            for column in ("Min (ms)", "Max (ms)", "Average (ms)", "Avg. deviation (ms)"):
                if column in header:
                    assert _NUMBER.match(cells[header.index(column)]), (header, cells)
    for heading in (
        "## TC1",
        "## TC2",
        "## TC3",
        "## Data channels over WebRTC",
        "### Time from connect to the first acked command",
        "## Where our time goes",
        "## Closing note",
    ):
        assert heading in report
    targets = next(t for t in tables if t[0] == ["Target", "Measured", "Verdict"])
    assert len(targets) == 3, targets
    assert all(row[2] in ("**met**", "**not met**") for row in targets[1:]), targets
    crossed = next(t for t in tables if t[0][0] == "Scenario" and "Data channel, direct" in t[0])
    assert "one** emulated link" in crossed[2][2]  # remote: through the UDP delay proxy
    assert crossed[2][1].startswith("not measured")  # no direct data channel there
    assert "point-to-point median overhead over the raw echo" in report
    assert "relay vs point-to-point with four vehicles" in report
    assert "pytest quick" in report

    # The plots: valid PNGs, each linked from the report.
    import matplotlib.image

    pngs = sorted(out.glob("*.png"))
    expected = {f"tc1_{s}_{p}.png" for s in plan.scenarios for p in ("p2p", "relay")}
    expected |= {f"tc1_{s}_{p}.png" for s, ps in meta["datachannel"]["paths"].items() for p in ps}
    assert {p.name for p in pngs} == expected | {"summary.png", "connect.png"}
    for png in pngs:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        height, width, _ = matplotlib.image.imread(png).shape
        assert height > 100 and width > 100
    for name in expected:
        assert f"]({name})" in report

    assert json.loads((out / "run.json").read_text())["plan"]["quick_mode"] is True
