"""The pilot's video while spectators watch through the SFU: capture-to-display latency
(p50, p95) with the pilot alone and with 10 and 50 spectators, beside the
render-encode-decode floor of one frame; the vehicle's outgoing bitrate and CPU, Janus's
and the spectators' CPU, at each count; on an unshaped link and on an emulated one.

    python -m benchmarks video_spectators            # or: python -m benchmarks.video_spectators
    python -m benchmarks.video_spectators --window-s 20 --counts 0 10 50

The vehicle is the agent's real parts in this process: a VideoService (a 640x480, 30 fps
synthetic camera of a vehicle turning and driving, 2.5 Mbit/s configured), its WebRTC
peers (the pilot's direct path) and its SfuPublisher, publishing to a private Janus
(tests.janus: Debian's package with deploy/janus's configuration) in a room the
platform's code opens (services.sfu). The pilot is Chromium in a network namespace
(tests/netlab.py) decoding each frame's code, so it knows each frame's capture time
(one clock). The spectators are headless subscribers (tests.janus.Spectator: aiortc,
receiving and decoding) with the platform's viewer tokens, in processes of their own.
Janus and the spectators run at the lowest CPU priority (nice 19, their autogroups
too): on a real deployment they are other machines, and here they must not take the
vehicle's or the pilot's share of the two cores.

The floor is measured in the same run, before anything else starts: drawing one frame,
encoding it with the agent's encoder settings, decoding it (libavcodec) and converting
it to RGB for display, median over 150 frames in a row. Needs root (namespaces, tc),
Janus (installed when missing) and Debian's Chromium; takes about 5 minutes.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "benchmarks" / "video_spectators"
WIDTH, HEIGHT, FPS, BITRATE = 640, 480, 30, 2_500_000
#: The links between the vehicle and the pilot: a name and the ``tc tbf`` options on the
#: pilot's side of the bridge (None: not shaped). This machine's kernel has no netem,
#: so a link's delay is not emulated, only its rate and queue (as benchmarks.video).
PROFILES: dict[str, str | None] = {
    "unshaped veth": None,
    "4 Mbit/s (tbf, 150 ms of queue)": "rate 4mbit burst 30kb latency 150ms",
}
#: Spectator counts measured, in this order (the crowd grows; each count its window).
COUNTS = (0, 10, 50)


def floor_ms(frames: int = 150) -> dict[str, float]:
    """The render-encode-decode floor of one frame (ms, medians over ``frames``)."""
    import av

    from agents.video.encoder import SharedEncoder
    from agents.video.sources import CameraPose, SyntheticCamera
    from tests.agents.video_page import moving_pose

    camera = SyntheticCamera(WIDTH, HEIGHT, fps=FPS, pose=moving_pose)
    # The agent's own encoder and settings (one call of its per-frame step): the floor is
    # what this encoder costs, not a codec configured otherwise.
    encoder = SharedEncoder(camera, bitrate=BITRATE)
    decoder = av.CodecContext.create("vp8", "r")
    parts: dict[str, list[float]] = {"render": [], "encode": [], "decode": []}
    for n in range(frames):
        t0 = time.perf_counter()
        rgb = camera.render(CameraPose.coerce(moving_pose()), n, int(time.time() * 1000))
        frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
        t1 = time.perf_counter()
        packets = encoder._encode(frame, n * 3000, n == 0, (WIDTH, HEIGHT), BITRATE)
        t2 = time.perf_counter()
        for packet in packets:
            for decoded in decoder.decode(av.Packet(bytes(packet))):
                decoded.to_ndarray(format="rgb24")  # what a display draws
        t3 = time.perf_counter()
        for name, took in zip(parts, (t1 - t0, t2 - t1, t3 - t2), strict=True):
            parts[name].append(took * 1000)
    out = {name: statistics.median(values) for name, values in parts.items()}
    out["total"] = statistics.median(map(sum, zip(*parts.values(), strict=True)))
    return out


def cpu_s(pid: int, *, tree: bool = True) -> float:
    """CPU seconds (user + system) of ``pid`` and, with ``tree``, every process below
    it (the spectators' processes, Janus and Chromium are this one's children)."""
    tick = os.sysconf("SC_CLK_TCK")
    children: dict[int, list[int]] = {}
    times: dict[int, float] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # gone meanwhile
        child = int(entry.name)
        children.setdefault(int(fields[1]), []).append(child)
        times[child] = (int(fields[11]) + int(fields[12])) / tick
    total, todo = 0.0, [pid]
    while todo:
        current = todo.pop()
        total += times.get(current, 0.0)
        if tree:
            todo.extend(children.get(current, []))
    return total


def background(pid: int) -> None:
    """Give ``pid`` (its every thread, and its autogroup when the kernel groups
    sessions, as this one's does) the lowest CPU priority: it stands in for other
    machines (the platform's server, the spectators' computers), and must not take the
    vehicle's or the pilot's share of the cores."""
    with contextlib.suppress(OSError):  # no autogroups: the threads' nice is enough
        Path(f"/proc/{pid}/autogroup").write_text("19")
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            os.setpriority(os.PRIO_PROCESS, int(task.name), 19)


class Crowd:
    """Spectator processes (benchmarks.video_peers), each in the background."""

    def __init__(self, viewer: dict[str, Any]) -> None:
        self.viewer = viewer
        #: Each process and how many spectators it holds.
        self.procs: list[tuple[subprocess.Popen[str], int]] = []

    @property
    def count(self) -> int:
        return sum(n for _, n in self.procs)

    def grow(self, count: int, per_process: int = 25) -> None:
        """Add ``count`` spectators and return once each of them receives video."""
        while count > 0:
            n = min(count, per_process)
            config = json.dumps({**self.viewer, "count": n})
            proc = subprocess.Popen(
                ["nice", "-n", "19", sys.executable, "-m", "benchmarks.video_peers", config],
                cwd=ROOT,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                start_new_session=True,  # an autogroup of its own, put in the background
            )
            background(proc.pid)
            self.procs.append((proc, n))
            reply = self._reply(proc)
            if reply.get("watching") != n:
                raise RuntimeError(f"spectators: {reply}")
            count -= n

    @staticmethod
    def _reply(proc: subprocess.Popen[str]) -> dict[str, Any]:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"a spectator process exited ({proc.wait()})")
        reply: dict[str, Any] = json.loads(line)
        if "error" in reply:
            raise RuntimeError(f"spectators: {reply['error']}")
        return reply

    def packets(self) -> int:
        """RTP packets received so far, over every spectator."""
        total = 0
        for proc, _ in self.procs:
            assert proc.stdin is not None
            proc.stdin.write("stats\n")
            proc.stdin.flush()
            total += int(self._reply(proc)["packets"])
        return total

    def cpu_s(self) -> float:
        return sum(cpu_s(proc.pid) for proc, _ in self.procs)

    def close(self) -> None:
        for proc, _ in self.procs:
            if proc.stdin is not None:
                with contextlib.suppress(OSError):
                    proc.stdin.close()
        for proc, _ in self.procs:
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        self.procs.clear()


@contextlib.contextmanager
def janus_settings() -> Iterator[Any]:
    """A private Janus, and Django's settings naming it (services.sfu reads them)."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")
    os.environ.setdefault("IOUV_DEV_SECRETS", "1")
    import django
    from django.conf import settings

    django.setup()
    from tests.janus import janus_server

    with tempfile.TemporaryDirectory() as tmp, janus_server(Path(tmp)) as server:
        for name, value in server.settings().items():
            setattr(settings, name, value)
        assert server.proc is not None
        background(server.proc.pid)
        yield server


def percentile(values: Sequence[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def shape(veth: str, tbf: str | None) -> None:
    """Put ``tbf``'s options on ``veth`` (None: take any shaping off)."""
    if tbf:
        command = ["tc", "qdisc", "replace", "dev", veth, "root", "tbf", *tbf.split()]
        subprocess.run(command, check=True)
    else:
        subprocess.run(
            ["tc", "qdisc", "del", "dev", veth, "root"], check=False, stderr=subprocess.DEVNULL
        )


async def sent(pc: Any) -> tuple[int, int]:
    """Video bytes (RTP payload and headers, as WebRTC counts them) and RTP packets
    ``pc`` has sent."""
    if pc is None:
        return 0, 0
    stats = [s for s in (await pc.getStats()).values() if s.type == "outbound-rtp"]
    return sum(s.bytesSent for s in stats), sum(s.packetsSent for s in stats)


class Vehicle:
    """The vehicle's video parts: its camera's VideoService, the pilot's WebRTC peers
    and, for one profile at a time, its publisher to the session's room at Janus."""

    def __init__(self, video: Any, rtc: Any, janus_pid: int) -> None:
        self.video, self.rtc, self.janus_pid = video, rtc, janus_pid
        self.publisher: Any = None

    async def sent(self) -> tuple[int, int, int]:
        """Bytes sent so far to the pilot and to the SFU, and packets to the SFU."""
        # The peers' only connection is the pilot's (the controller's place).
        peers = list(self.rtc._peers.values())
        to_pilot = sum([(await sent(peer.pc))[0] for peer in peers])
        to_sfu = await sent(self.publisher.pc if self.publisher else None)
        return to_pilot, *to_sfu


async def run(window_s: float, counts: Sequence[int], profiles: Sequence[str]) -> dict[str, Any]:
    from agents.rtc import RtcPeers
    from agents.video.service import VideoService
    from agents.video.sources import SyntheticCamera
    from tests.agents.video_page import VideoOnly, moving_pose, pilot_behind_a_link

    floor = floor_ms()
    results: dict[str, Any] = {"floor_ms": floor, "window_s": window_s, "profiles": {}}
    with (
        janus_settings() as janus,
        tempfile.TemporaryDirectory() as tmp,
        pilot_behind_a_link(Path(tmp)) as (lab, browser),
    ):
        veth = lab.machine("pilot").root_veth
        camera = SyntheticCamera(WIDTH, HEIGHT, fps=FPS, pose=moving_pose)
        async with VideoService(
            camera, ice_host_addresses=[lab.public_ip], bitrate=BITRATE
        ) as video:
            rtc = RtcPeers(VideoOnly(), video=video)
            vehicle = Vehicle(video, rtc, janus.proc.pid if janus.proc else 0)
            try:
                for profile in profiles:
                    await asyncio.to_thread(shape, veth, PROFILES[profile])
                    try:
                        rows = await one_profile(vehicle, lab.public_ip, browser, counts, window_s)
                    finally:
                        await asyncio.to_thread(shape, veth, None)
                    results["profiles"][profile] = rows
            finally:
                await rtc.close()
    return results


async def one_profile(
    vehicle: Vehicle, host: str, browser: Any, counts: Sequence[int], window_s: float
) -> list[dict[str, Any]]:
    """A session of its own (room, publisher, pilot's page), the crowd growing to each
    of ``counts`` in turn, a window measured at each."""
    from agents.sfu import SfuPublisher
    from services import sfu
    from tests.agents.video_page import signalling_server

    session_id = uuid.uuid4()
    await asyncio.to_thread(sfu.sfu_room_open, session_id=session_id)
    task = sfu.sfu_publish_for(session_id=session_id)
    viewer = sfu.sfu_viewer_for(session_id=session_id)
    assert task is not None and viewer is not None
    vehicle.publisher = publisher = SfuPublisher.for_room(vehicle.video, task)
    publishing = asyncio.create_task(publisher.run())
    crowd = Crowd(viewer)
    rows: list[dict[str, Any]] = []
    try:
        await asyncio.wait_for(publisher.publishing.wait(), 60)
        async with signalling_server(vehicle.rtc, host=host, controller=True) as url:
            await asyncio.to_thread(browser.call, "goto", url=f"{url}/?source_width={WIDTH}")
            await asyncio.to_thread(browser.wait, "window.result.codes.length >= 30", 60)
            for count in counts:
                if count > crowd.count:
                    await asyncio.to_thread(crowd.grow, count - crowd.count)
                rows.append(await measure(count, window_s, browser, vehicle, crowd))
                print(f"{host}: {rows[-1]}", file=sys.stderr, flush=True)
            # The next profile's pilot starts over with a fresh page.
            await asyncio.to_thread(browser.call, "goto", url="about:blank")
    finally:
        await asyncio.to_thread(crowd.close)
        publishing.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await publishing
        vehicle.publisher = None
        await asyncio.to_thread(sfu.sfu_room_close, session_id=session_id)
    return rows


async def measure(
    count: int, window_s: float, browser: Any, vehicle: Vehicle, crowd: Crowd
) -> dict[str, Any]:
    """One window with ``count`` spectators watching: the pilot's latency, the vehicle's
    bytes out (to the pilot, to the SFU), and CPU of each party."""
    from tests.agents.video_page import largest_gap_ms

    await asyncio.sleep(2.0)  # the joins' CPU burst passes before the window opens
    me = os.getpid()
    start_ms = time.time() * 1000
    pilot0, sfu0, packets0 = await vehicle.sent()
    cpu0 = (cpu_s(me, tree=False), cpu_s(vehicle.janus_pid), await asyncio.to_thread(crowd.cpu_s))
    seen0 = await asyncio.to_thread(crowd.packets)
    keys0 = vehicle.video.encoder.keyframes
    t0 = time.monotonic()
    await asyncio.sleep(window_s)
    elapsed = time.monotonic() - t0
    pilot1, sfu1, packets1 = await vehicle.sent()
    cpu1 = (cpu_s(me, tree=False), cpu_s(vehicle.janus_pid), await asyncio.to_thread(crowd.cpu_s))
    seen1 = await asyncio.to_thread(crowd.packets)
    keys1 = vehicle.video.encoder.keyframes
    end_ms = time.time() * 1000
    result = await asyncio.to_thread(browser.eval, "window.result")
    latencies = [lat for t, lat in result["latencyAt"] if start_ms <= t < end_ms]
    frames = [t for t in result["times"] if start_ms <= t[0] < end_ms]
    kbit = 8 / 1000 / elapsed
    return {
        "spectators": count,
        "pilot_p50_ms": statistics.median(latencies) if latencies else float("nan"),
        "pilot_p95_ms": percentile(latencies, 0.95),
        "pilot_fps": len(frames) / elapsed,
        "pilot_largest_gap_ms": largest_gap_ms(result["times"], start_ms, end_ms),
        "vehicle_to_pilot_kbit_s": (pilot1 - pilot0) * kbit,
        "vehicle_to_sfu_kbit_s": (sfu1 - sfu0) * kbit,
        # Keyframes cost the pilot's link several frames' worth each: the spectators'
        # requests must not multiply them.
        "vehicle_keyframes_per_s": (keys1 - keys0) / elapsed,
        "vehicle_cpu_pct": (cpu1[0] - cpu0[0]) / elapsed * 100,
        "janus_cpu_pct": (cpu1[1] - cpu0[1]) / elapsed * 100,
        "spectators_cpu_pct": (cpu1[2] - cpu0[2]) / elapsed * 100,
        # Of the packets the vehicle sent Janus, the share each spectator received
        # (Janus forwards every one; less means a spectator fell behind or Janus did).
        "spectators_received_share": (
            (seen1 - seen0) / count / max(1, packets1 - packets0) if count else None
        ),
    }


def report(run_json: dict[str, Any]) -> str:
    floor = run_json["floor_ms"]
    lines = [
        "# The pilot's video with spectators watching through the SFU",
        "",
        "Regenerated with `python -m benchmarks video_spectators` (see",
        "benchmarks/video_spectators.py): the agent's VideoService (640x480 at 30 fps of a",
        "moving synthetic scene, 2.5 Mbit/s configured), its WebRTC peers and SFU publisher",
        "in one process; the pilot's Chromium in a network namespace, reading each frame's",
        "capture time from its pixels; a private Janus; headless spectators (aiortc,",
        "decoding) in processes of their own; Janus and the spectators at nice 19 (they",
        "stand in for other machines). One run on the shared 2-core machine, every figure",
        f"over a {run_json['window_s']:.0f} s window.",
        "",
        f"Render-encode-decode floor of one frame (same run, median of 150): "
        f"**{floor['total']:.1f} ms** (draw {floor['render']:.1f}, encode "
        f"{floor['encode']:.1f}, decode and convert {floor['decode']:.1f}).",
        "",
    ]
    for profile, rows in run_json["profiles"].items():
        alone = rows[0]
        lines += [
            f"## {profile}",
            "",
            "| spectators | pilot p50 | vs alone | vs floor | pilot p95 | pilot fps | largest gap"
            " | vehicle out: pilot + SFU | vehicle CPU | Janus CPU | spectators' CPU"
            " | each spectator receives |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for row in rows:
            share = row["spectators_received_share"]
            lines.append(
                f"| {row['spectators']} | {row['pilot_p50_ms']:.0f} ms"
                f" | {row['pilot_p50_ms'] - alone['pilot_p50_ms']:+.0f} ms"
                f" | {row['pilot_p50_ms'] / floor['total']:.1f}x"
                f" | {row['pilot_p95_ms']:.0f} ms | {row['pilot_fps']:.0f}"
                f" | {row['pilot_largest_gap_ms']:.0f} ms"
                f" | {row['vehicle_to_pilot_kbit_s']:.0f} + {row['vehicle_to_sfu_kbit_s']:.0f}"
                " kbit/s"
                f" | {row['vehicle_cpu_pct']:.0f} % | {row['janus_cpu_pct']:.0f} %"
                f" | {row['spectators_cpu_pct']:.0f} %"
                f" | {'-' if share is None else f'{share:.0%}'} |"
            )
        lines.append("")
    lines += [
        "CPU is per cent of one core over the window (200 % is both cores). The vehicle's",
        "process also draws the synthetic scene and runs the pilot's signalling; the",
        "spectators' figure is all of them together. Each spectator receives: the share of",
        "the packets the vehicle sent Janus that reached each spectator, on average. Every",
        "row's figures are in `run.json`.",
        "",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.video_spectators", description=__doc__
    )
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--window-s", type=float, default=15.0)
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    parser.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=list(PROFILES))
    parser.add_argument("--quick", action="store_true", help="5 s windows, 0 and 10 spectators")
    args = parser.parse_args(argv)
    if args.quick:
        args.window_s, args.counts = 5.0, [0, 10]
    if sorted(args.counts) != args.counts or args.counts[0] != 0:
        parser.error("--counts must start at 0 (the pilot alone) and grow")
    from benchmarks.video import report_write

    result = asyncio.run(run(args.window_s, args.counts, args.profiles))
    report_write(args.out, result, report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
