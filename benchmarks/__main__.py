"""Regenerate every benchmark report under docs/benchmarks/ with one command.

    python -m benchmarks            # the full runs (see each module's --help for times)
    python -m benchmarks --quick    # the smoke-test sizes, in a few minutes
    python -m benchmarks --paper-args "--interval-s 0.2" --scale-args "--agents 1000"
    python -m benchmarks video      # one report alone: the pilot's video through a cut link
    python -m benchmarks records    # one report alone: the flight record's size and CPU cost

Runs, one after the other so neither disturbs the other's timings:

* ``benchmarks.paper`` - the paper's response-time tests TC1-TC3, point-to-point vs
  through the platform vs WebRTC data channels (direct and through TURN), over loopback
  and emulated remote and LTE links, and the time from connect to the first acked command;
* ``benchmarks.scale`` - 1,000 agents on one platform, assignment and deployment
  throughput, fail-safe reaction times, one platform process vs two;

then writes ``docs/benchmarks/README.md``: the machine, the commands, and links to the
two reports.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "benchmarks"


def machine() -> list[str]:
    """The lines of the report that say what it ran on."""
    cpu = platform.processor() or "unknown CPU"
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    mem = ""
    meminfo = Path("/proc/meminfo")
    if meminfo.exists():
        kb = int(meminfo.read_text().split("MemTotal:")[1].split()[0])
        mem = f", {kb / 1024 / 1024:.0f} GiB RAM"
    return [
        f"- CPU: {cpu}, {os.cpu_count()} logical cores{mem}",
        f"- OS: {platform.platform()}",
        f"- Python: {platform.python_version()}",
        f"- Date: {datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')}",
    ]


def run(module: str, quick: bool, extra: str) -> float:
    # Relative to ROOT (the run's cwd), so the reports name no machine's path.
    out = (OUT / module.rsplit(".", 1)[1]).relative_to(ROOT)
    command = [sys.executable, "-m", module, "--out", str(out)]
    if quick:
        command.append("--quick")
    command += shlex.split(extra)
    print("==", " ".join(command[1:]), flush=True)
    started = time.monotonic()
    subprocess.run(command, cwd=ROOT, check=True)
    return time.monotonic() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "only",
        nargs="?",
        choices=["video", "video_spectators", "records"],
        help="run this benchmark alone (video: needs root and Chromium, benchmarks/video.py;"
        " video_spectators: also Janus, benchmarks/video_spectators.py;"
        " records: 30 minutes of simulated flight, benchmarks/records.py)",
    )
    parser.add_argument("--quick", action="store_true", help="smoke-test sizes")
    parser.add_argument("--paper-args", default="", help="more options for benchmarks.paper")
    parser.add_argument("--scale-args", default="", help="more options for benchmarks.scale")
    args = parser.parse_args()
    if args.only:
        run(f"benchmarks.{args.only}", args.quick, "")
        return
    extra = {"paper": args.paper_args, "scale": args.scale_args}
    took = {name: run(f"benchmarks.{name}", args.quick, extra[name]) for name in extra}
    mode = "quick" if args.quick else "full"
    lines = [
        "# Benchmarks",
        "",
        f"Regenerated with `{shlex.join(['python', '-m', 'benchmarks', *sys.argv[1:]])}`"
        f" ({mode} mode):",
        "",
        *machine(),
        "",
        f"- [The paper's response-time tests, point-to-point vs relay vs data channels]"
        f"(paper/report.md)"
        f" ({took['paper'] / 60:.1f} min)",
        f"- [Platform scale: 1,000 agents, throughput, fail-safe reaction, two processes]"
        f"(scale/report.md) ({took['scale'] / 60:.1f} min)",
        "- [The pilot's video through a link cut from 4 to 0.5 Mbit/s and back](video/report.md)"
        " (run alone: `python -m benchmarks video`, needs root and Chromium)",
        "- [The pilot's video with 10 and 50 spectators watching through the SFU]"
        "(video_spectators/report.md) (run alone: `python -m benchmarks video_spectators`,"
        " needs root, Chromium and Janus)",
        "- [The flight record's size per hour and the agent's CPU cost of recording]"
        "(records/README.md) (run alone: `python -m benchmarks records`, about 32 min)",
        "",
        "Timings come from one run on a shared machine: compare the columns of one report",
        "(they were measured together) rather than figures across reports or machines.",
        "",
    ]
    (OUT / "README.md").write_text("\n".join(lines))
    print(f"wrote {OUT / 'README.md'}")


if __name__ == "__main__":
    main()
