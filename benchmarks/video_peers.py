"""Headless spectators for benchmarks.video_spectators, in a process of their own.

    python -m benchmarks.video_peers '{"url": ..., "token": ..., "room": ..., "pin": ...,
                                       "feed": 1, "count": 40}'

``count`` subscribers (:class:`tests.janus.Spectator`) of one Janus VideoRoom feed, as
many spectators' browsers would be: their receiving and decoding runs here, not on the
vehicle's event loop. Once every one has received packets, prints
``{"watching": count}``; then answers each ``stats`` line on stdin with
``{"packets": n}`` (RTP packets received, over the spectators); leaves the room and exits
when stdin closes. Errors go out as ``{"error": "..."}`` and exit status 1.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections.abc import Sequence

from tests.janus import Spectator

#: Spectators joining at once (Janus's and aiortc's handshakes are CPU-bound here).
JOINING = 10
#: Packets each spectator must have received to count as watching.
WATCHING_PACKETS = 20


def _say(**fields: object) -> None:
    print(json.dumps(fields), flush=True)


async def _run(config: dict[str, object]) -> int:
    count = int(str(config["count"]))
    spectators = [
        Spectator(
            str(config["url"]),
            token=str(config["token"]),
            room=int(str(config["room"])),
            pin=str(config["pin"]),
            feed=int(str(config["feed"])),
        )
        for _ in range(count)
    ]
    joining = asyncio.Semaphore(JOINING)

    async def join(spectator: Spectator) -> None:
        async with joining:
            await spectator.watch()

    try:
        await asyncio.gather(*(join(s) for s in spectators))
        deadline = time.monotonic() + float(str(config.get("within_s", 300)))
        while not all([await s.packets() > WATCHING_PACKETS for s in spectators]):
            if time.monotonic() > deadline:
                _say(error=f"not every one of {count} spectators received video")
                return 1
            await asyncio.sleep(0.2)
        _say(watching=count)
        while line := await asyncio.to_thread(sys.stdin.readline):
            if line.strip() == "stats":
                _say(packets=sum([await s.packets() for s in spectators]))
        return 0
    finally:
        await asyncio.gather(*(s.close() for s in spectators), return_exceptions=True)


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    try:
        return asyncio.run(_run(json.loads(args[0])))
    except Exception as exc:  # reported to the benchmark, which stops the run
        _say(error=f"{type(exc).__name__}: {exc}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
