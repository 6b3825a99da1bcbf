"""The pilot's video through a link cut from 4 to 0.5 Mbit/s and back: how long the
picture freezes, how long until capture-to-display latency is back under 300 ms, and
when the encoder steps down and back up.

    python -m benchmarks video                        # or: python -m benchmarks.video
    python -m benchmarks.video --cut-s 20 --restore-s 60 --out docs/benchmarks/video

The agent's real VideoService (a 640x480, 30 fps synthetic camera of a vehicle turning
and driving, configured bitrate 2.5 Mbit/s) in this process; Chromium as the pilot in a
network namespace of tests/netlab.py, behind a veth whose rate ``tc tbf`` sets (4 Mbit/s,
then 0.5 Mbit/s, then 4 Mbit/s again). The page (tests/agents/video_page.py) decodes
each frame's code and so knows its capture time: latency is ``Date.now() - ts`` on one
clock. Needs root (namespaces, tc) and Debian's Chromium; takes about 1.5 minutes.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "benchmarks" / "video"
#: Capture-to-display latency the pilot can steer by.
LATENCY_OK_MS = 300
#: The window over which "latency is back under LATENCY_OK_MS" must hold.
LATENCY_WINDOW_MS = 1000


def tbf(veth: str, rate: str, *, change: bool) -> None:
    """Set the link's rate (a queue of 150 ms at that rate, 30 kB of burst)."""
    verb = "change" if change else "add"
    queue = ["burst", "30kb", "latency", "150ms"]
    subprocess.run(
        ["tc", "qdisc", verb, "dev", veth, "root", "tbf", "rate", rate, *queue], check=True
    )


def latency_ok_after(latency_at: Sequence[Sequence[float]], start: float) -> float | None:
    """Milliseconds from ``start`` until every legible frame of a whole window has
    latency under LATENCY_OK_MS (and the window has some), or None."""
    points = [(t, lat) for t, lat in latency_at if t >= start]
    for i, (t0, _) in enumerate(points):
        window = [lat for t, lat in points[i:] if t < t0 + LATENCY_WINDOW_MS]
        if len(window) >= 3 and max(window) < LATENCY_OK_MS:
            return t0 - start
    return None


def median_latency(latency_at: Sequence[Sequence[float]], start: float, end: float) -> float:
    values = [lat for t, lat in latency_at if start <= t < end]
    return statistics.median(values) if values else float("nan")


async def run(cut_s: float, restore_s: float, warm_s: float) -> dict[str, Any]:
    from agents.rtc import RtcPeers
    from agents.video.service import VideoService
    from agents.video.sources import SyntheticCamera
    from tests.agents.video_page import (
        VideoOnly,
        largest_gap_ms,
        moving_pose,
        pilot_behind_a_link,
        signalling_server,
    )

    statuses: list[tuple[float, Any]] = []
    at_top = asyncio.Event()

    def changed(status: Any) -> None:
        statuses.append((time.time() * 1000, status))
        if status.width == 640:
            at_top.set()

    with tempfile.TemporaryDirectory() as tmp, pilot_behind_a_link(Path(tmp)) as (lab, browser):
        veth = lab.machine("pilot").root_veth
        tbf(veth, "4mbit", change=False)
        camera = SyntheticCamera(640, 480, fps=30, pose=moving_pose)
        hosts = [lab.public_ip]
        async with VideoService(camera, ice_host_addresses=hosts, bitrate=2_500_000) as video:
            video.encoder.add_listener(changed)
            rtc = RtcPeers(VideoOnly(), video=video)
            try:
                async with signalling_server(rtc, host=lab.public_ip, controller=True) as url:
                    await asyncio.to_thread(browser.call, "goto", url=f"{url}/?source_width=640")
                    await asyncio.to_thread(browser.wait, "window.result.codes.length >= 5", 30)
                    await asyncio.sleep(warm_s)
                    cut = time.time() * 1000
                    tbf(veth, "500kbit", change=True)
                    await asyncio.sleep(cut_s)
                    restored = time.time() * 1000
                    at_top.clear()
                    tbf(veth, "4mbit", change=True)
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(at_top.wait(), restore_s)
                    await asyncio.sleep(3)  # frames at the top step reach the page
                    result = await asyncio.to_thread(browser.eval, "window.result")
                    end = time.time() * 1000
            finally:
                await rtc.close()
    times, latency_at = result["times"], result["latencyAt"]

    def first_status(after: float, cond: Any) -> float | None:
        return next((t - after for t, s in statuses if t >= after and cond(s)), None)

    back_top = first_status(restored, lambda s: s.width == 640)
    return {
        "warm_s": warm_s,
        "cut_s": cut_s,
        "before": {
            "median_latency_ms": median_latency(latency_at, cut - warm_s * 1000, cut),
            "largest_gap_ms": largest_gap_ms(times, cut - warm_s * 1000, cut),
        },
        "cut": {
            "largest_gap_ms": largest_gap_ms(times, cut, restored),
            "latency_ok_after_ms": latency_ok_after(latency_at, cut),
            "step_down_after_ms": first_status(cut, lambda s: s.width < 640),
            "lowest": min(
                ((s.width, s.height, s.fps, s.bitrate) for t, s in statuses if cut <= t < restored),
                default=None,
                key=lambda x: x[3],
            ),
            "median_latency_last_5s_ms": median_latency(latency_at, restored - 5000, restored),
        },
        "restore": {
            "largest_gap_ms": largest_gap_ms(times, restored, end),
            "top_step_after_ms": back_top,
            "latency_ok_after_ms": latency_ok_after(latency_at, restored),
        },
        "statuses": [(round(t - cut), s.width, s.height, s.fps, s.bitrate) for t, s in statuses],
    }


def report(run_json: dict[str, Any]) -> str:
    def ms(v: float | None) -> str:
        return "never" if v is None else f"{v / 1000:.1f} s"

    c, r, b = run_json["cut"], run_json["restore"], run_json["before"]
    lowest = c["lowest"]
    low = (
        f"{lowest[0]}x{lowest[1]} at {lowest[2]} fps, {lowest[3] / 1000:.0f} kbit/s"
        if lowest
        else "-"
    )
    return "\n".join(
        [
            "# The pilot's video through a cut link",
            "",
            "Regenerated with `python -m benchmarks video` (see benchmarks/video.py): the",
            "agent's VideoService (640x480 at 30 fps of a moving synthetic scene, 2.5 Mbit/s",
            "configured) to Chromium in a network namespace, the link's rate set by `tc tbf`",
            f"(150 ms of queue): 4 Mbit/s, cut to 0.5 Mbit/s for {run_json['cut_s']:.0f} s,",
            "then 4 Mbit/s again. One run on the shared 2-core machine.",
            "",
            "| | figure |",
            "|---|---|",
            "| before the cut: median capture-to-display latency "
            f"| {b['median_latency_ms']:.0f} ms |",
            f"| before the cut: largest gap between frames | {b['largest_gap_ms']:.0f} ms |",
            f"| cut: encoder steps down after | {ms(c['step_down_after_ms'])} |",
            f"| cut: lowest step | {low} |",
            f"| cut: largest gap between frames (freeze) | {c['largest_gap_ms']:.0f} ms |",
            f"| cut: latency back under {LATENCY_OK_MS} ms (a whole second of frames) after "
            f"| {ms(c['latency_ok_after_ms'])} |",
            f"| cut: median latency, its last 5 s | {c['median_latency_last_5s_ms']:.0f} ms |",
            f"| restored: back at 640x480 after | {ms(r['top_step_after_ms'])} |",
            f"| restored: largest gap between frames | {r['largest_gap_ms']:.0f} ms |",
            "",
            "The encoder's steps (ms from the cut, width, height, fps, target bit/s) are in",
            "`run.json`.",
            "",
        ]
    )


def report_write(out: Path, result: dict[str, Any], text: str) -> None:
    """Write a video benchmark's ``run.json`` (``result``) and ``report.md`` (``text``)
    into ``out``, and print the report."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "run.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "report.md").write_text(text)
    print(text)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.video", description=__doc__)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--warm-s", type=float, default=8.0)
    parser.add_argument("--cut-s", type=float, default=20.0)
    parser.add_argument("--restore-s", type=float, default=60.0)
    parser.add_argument("--quick", action="store_true", help="shorter phases")
    args = parser.parse_args(argv)
    if args.quick:
        args.warm_s, args.cut_s, args.restore_s = 4.0, 10.0, 30.0
    result = asyncio.run(run(args.cut_s, args.restore_s, args.warm_s))
    report_write(args.out, result, report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
