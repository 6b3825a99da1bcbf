"""Command round trip to an agent over loopback, beside a raw WebSocket echo.

    python -m benchmarks.control_rtt [--n 2000] [--interval-ms 10]

Both servers run in this process on 127.0.0.1 with the same websockets settings. The
echo is the floor: a client sends a frame and waits for the same frame back. The agent
case is the real path: an authenticated controller sends ``command`` messages to the
control server of a simulated Pi car; each is parsed, checked by the command gate,
applied by the car adapter (gpiozero on mock pins) and acknowledged with its ``seq``.
The figure is the time from send to the matching ack, per command, sequential.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import statistics
import time
from typing import Any

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve

from agents.control import ControlHub, ControlServer
from agents.protocol import (
    Limits,
    UserGrant,
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
    new_nonce,
)
from agents.simulation import adapter_simulated


def summary(samples_ms: list[float]) -> dict[str, float]:
    ordered = sorted(samples_ms)
    return {
        "n": len(ordered),
        "min": ordered[0],
        "median": statistics.median(ordered),
        "mean": statistics.fmean(ordered),
        "p99": ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))],
        "max": ordered[-1],
    }


async def echo_rtts(n: int, interval_s: float) -> list[float]:
    async def echo(ws: ServerConnection) -> None:
        async for message in ws:
            await ws.send(message)

    async with serve(echo, "127.0.0.1", 0, compression=None) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        async with connect(f"ws://127.0.0.1:{port}/", compression=None, proxy=None) as ws:
            frame = json.dumps({"type": "command", "seq": 0, "name": "stop", "args": {}})
            out = []
            for _ in range(n):
                start = time.perf_counter()
                await ws.send(frame)
                await ws.recv()
                out.append((time.perf_counter() - start) * 1000)
                if interval_s:
                    await asyncio.sleep(interval_s)
            return out


async def agent_rtts(n: int, interval_s: float) -> list[float]:
    private_pem, public_pem = generate_keypair()
    now = time.time()
    task = VehicleTask(
        session_id="bench",
        vehicle_id="car-bench",
        user="bench",
        allowed_commands=("forward", "stop", "left", "right", "backward"),
        limits=Limits(link_loss_timeout_ms=5000, failsafe_action="stop"),
        issued_at=now,
        expires_at=now + 60,
        nonce=new_nonce(),
    )
    grant = UserGrant(
        session_id="bench",
        vehicle_id="car-bench",
        user="bench",
        role="controller",
        allowed_commands=task.allowed_commands,
        issued_at=now,
        expires_at=now + 600,
        nonce=new_nonce(),
    ).sign(load_private_key(private_pem))
    reports: list[Any] = []
    async with adapter_simulated("car", {}) as (car, _):
        hub = ControlHub(
            vehicle_id="car-bench",
            vehicle_name="car-bench",
            adapter=car,
            public_key=load_public_key(public_pem),
            report=lambda *event: reports.append(event),
        )
        async with hub, ControlServer(hub) as server:
            hub.task_accept(task)
            url = f"ws://127.0.0.1:{server.port}/"
            async with connect(url, compression=None, proxy=None) as ws:
                await ws.send(json.dumps({"type": "auth", "grant": grant}))
                while json.loads(await ws.recv())["type"] != "welcome":
                    pass
                out = []
                names = ("forward", "stop")  # alternate so the car really moves and stops
                for seq in range(n):
                    frame = json.dumps(
                        {"type": "command", "seq": seq, "name": names[seq % 2], "args": {}}
                    )
                    start = time.perf_counter()
                    await ws.send(frame)
                    while True:
                        msg = json.loads(await ws.recv())
                        if msg["type"] == "ack" and msg["seq"] == seq:
                            break
                        if msg["type"] == "ping":
                            await ws.send(json.dumps({"type": "pong", "t": msg["t"]}))
                    out.append((time.perf_counter() - start) * 1000)
                    if not msg["ok"]:
                        raise RuntimeError(f"command refused: {msg}")
                    if interval_s:
                        await asyncio.sleep(interval_s)
                return out


async def main(n: int, interval_ms: float) -> None:
    interval_s = interval_ms / 1000
    echo = summary(await echo_rtts(n, interval_s))
    agent = summary(await agent_rtts(n, interval_s))
    print(
        f"machine: {platform.node()} {platform.processor() or platform.machine()}, "
        f"python {platform.python_version()}"
    )
    print(f"{n} sequential round trips over loopback, interval {interval_ms:g} ms\n")
    print(f"{'':22}{'min':>8}{'median':>9}{'mean':>8}{'p99':>8}{'max':>8}  (ms)")
    for name, s in (("raw WebSocket echo", echo), ("agent command -> ack", agent)):
        print(
            f"{name:22}{s['min']:8.3f}{s['median']:9.3f}{s['mean']:8.3f}"
            f"{s['p99']:8.3f}{s['max']:8.3f}"
        )
    print(
        f"\nagent overhead over the echo: median {agent['median'] - echo['median']:+.3f} ms, "
        f"p99 {agent['p99'] - echo['p99']:+.3f} ms"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--interval-ms", type=float, default=10.0, help="the paper's fastest")
    args = parser.parse_args()
    asyncio.run(main(args.n, args.interval_ms))
