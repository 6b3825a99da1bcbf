"""A test page that watches the agent's video in a browser, the server that signals for
it, and a pilot's Chromium behind an emulated link: what tests/agents/test_video.py,
test_video_rate.py and benchmarks/video.py use.

``PAGE`` offers to receive video over a WebSocket (``webrtc_offer`` ->
``webrtc_answer``, as the control socket carries them), plays it, draws every frame on
a canvas and decodes the synthetic camera's frame code in JavaScript. ``window.result``
holds ``frames`` (count), ``firstFrameMs``, ``codes`` (counters read), ``latencies``
(capture to display, ms, on a machine with one clock), ``width`` (the last frame's),
``times`` (``[Date.now(), width]`` of every frame), ``latencyAt`` (``[Date.now(),
latency ms]`` of every frame whose code was legible) and ``error``.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import subprocess
import time
from collections.abc import AsyncIterator, Iterator, Sequence
from http import HTTPStatus
from pathlib import Path
from typing import Any

import pytest

from agents.rtc import RtcPeers
from agents.video import VideoError
from tests.browser import chromium_missing_reason
from tests.netlab import NetLab, netlab_available
from tests.netlab_browser import BrowserProcess

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>IoUV video test</title></head>
<body>
<video id="v" autoplay muted playsinline></video>
<script>
"use strict";
const result = window.result = {frames: 0, firstFrameMs: null, codes: [], latencies: [],
                                width: 0, error: null, times: [], latencyAt: []};
// The width the camera drew the frame code at (?source_width=640): pictures the
// encoder's ladder scaled down carry it scaled too.
const sourceWidth = Number(new URLSearchParams(location.search).get("source_width")) || 0;
const video = document.getElementById("v");
const pc = new RTCPeerConnection({iceServers: []});
pc.ontrack = (ev) => { video.srcObject = new MediaStream([ev.track]); };
const ws = new WebSocket(`ws://${location.host}/ws`);

// Complete SDP (no trickle ICE), but never wait forever for gathering to finish.
function gathered(ms) {
  return new Promise((resolve) => {
    if (pc.iceGatheringState === "complete") return resolve();
    const timer = setTimeout(resolve, ms);
    pc.addEventListener("icegatheringstatechange", () => {
      if (pc.iceGatheringState === "complete") { clearTimeout(timer); resolve(); }
    });
  });
}
const send = (msg) => ws.send(JSON.stringify(msg));
ws.onopen = async () => {
  pc.addTransceiver("video", {direction: "recvonly"});
  await pc.setLocalDescription(await pc.createOffer());
  await gathered(2000);
  send({type: "webrtc_offer", sdp: pc.localDescription.sdp});
};
ws.onmessage = async (ev) => {
  const msg = JSON.parse(ev.data);
  try {
    if (msg.type === "webrtc_answer") {
      await pc.setRemoteDescription({type: "answer", sdp: msg.sdp});
    } else if (msg.type === "error") {
      result.error = msg.message;
    }
  } catch (e) { result.error = String(e); }
};

// The frame code (agents.video.framecode.stamp_frame_code): two rows of 48 blocks at the top.
const CRC = new Uint32Array(256).map((_, n) => {
  let c = n;
  for (let k = 0; k < 8; k++) c = c & 1 ? 0xEDB88320 ^ (c >>> 1) : c >>> 1;
  return c >>> 0;
});
function crc32(bytes) {
  let c = 0xFFFFFFFF;
  for (const b of bytes) c = CRC[(c ^ b) & 0xFF] ^ (c >>> 8);
  return (c ^ 0xFFFFFFFF) >>> 0;
}
function readCode(data, width) {
  // As agents.video.framecode.read_frame_code: the middle half of each block, where the scaling
  // from the source's width put it.
  const source = sourceWidth || width, scale = width / source;
  const block = Math.floor(source / 48), x0 = Math.floor((source - block * 48) / 2);
  const at = (v) => Math.round(v * scale);
  const rows = [0, 1].map((r) => {
    let value = 0;
    for (let i = 0; i < 48; i++) {
      let sum = 0, n = 0;
      const x1 = Math.max(at(x0 + (i + 0.25) * block) + 1, at(x0 + (i + 0.75) * block));
      for (let y = at((r + 0.25) * block); y < at((r + 0.75) * block); y++)
        for (let x = at(x0 + (i + 0.25) * block); x < x1; x++) {
          const p = (y * width + x) * 4;
          sum += data[p] + data[p + 1] + data[p + 2]; n += 3;
        }
      value = value * 2 + (sum / n > 127 ? 1 : 0);
    }
    return value;
  });
  const counter = Math.floor(rows[0] / 65536), check = rows[0] % 65536, ts = rows[1];
  const bytes = [];
  for (let i = 3; i >= 0; i--) bytes.push(Math.floor(counter / 2 ** (8 * i)) % 256);
  for (let i = 5; i >= 0; i--) bytes.push(Math.floor(ts / 2 ** (8 * i)) % 256);
  return (crc32(bytes) & 0xFFFF) === check ? {counter, ts} : null;
}
const canvas = document.createElement("canvas");
const ctx = canvas.getContext("2d", {willReadFrequently: true});
function onFrame() {
  result.frames++;
  if (result.firstFrameMs === null) result.firstFrameMs = performance.now();
  const w = video.videoWidth, h = video.videoHeight;
  result.width = w;
  result.times.push([Date.now(), w]);
  canvas.width = w; canvas.height = h;
  ctx.drawImage(video, 0, 0);
  // Only the code's two rows of blocks (scaled like the picture) are read.
  const source = sourceWidth || w;
  const rows = Math.min(h, Math.ceil((2 * Math.floor(source / 48) * w) / source) + 1);
  const code = readCode(ctx.getImageData(0, 0, w, rows).data, w);
  if (code) {
    const now = Date.now();
    result.codes.push(code.counter);
    result.latencies.push(now - code.ts);
    result.latencyAt.push([now, now - code.ts]);
  }
  video.requestVideoFrameCallback(onFrame);
}
video.requestVideoFrameCallback(onFrame);
</script></body></html>
"""


@contextlib.asynccontextmanager
async def signalling_server(
    rtc: RtcPeers, *, host: str = "127.0.0.1", controller: bool = False
) -> AsyncIterator[str]:
    """Serve PAGE at / and bridge /ws to ``rtc`` with the control socket's messages;
    yields the base URL. ``controller``: the page offers as the session's pilot. Stops
    the server and every connection on exit."""
    from websockets.asyncio.server import ServerConnection, serve
    from websockets.http11 import Request, Response

    def process_request(conn: ServerConnection, request: Request) -> Response | None:
        if request.path.startswith("/ws"):
            return None  # go on with the WebSocket handshake
        response = conn.respond(HTTPStatus.OK, PAGE)
        response.headers["Content-Type"] = "text/html; charset=utf-8"
        return response

    async def handler(ws: ServerConnection) -> None:
        peer_id = f"ws-{id(ws)}"
        try:
            async for raw in ws:
                msg = json.loads(raw)
                if msg["type"] != "webrtc_offer":
                    continue
                try:
                    answer = await rtc.accept(peer_id, msg["sdp"], controller=controller)
                    reply = {"type": "webrtc_answer", "sdp": answer}
                except VideoError as exc:
                    reply = {"type": "error", "code": "webrtc", "message": str(exc)}
                await ws.send(json.dumps(reply))
        finally:
            await rtc.close_peer(peer_id)

    async with serve(handler, host, 0, process_request=process_request) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        yield f"http://{host}:{port}"


def largest_gap_ms(times: Sequence[Sequence[float]], start_ms: float, end_ms: float) -> float:
    """The longest time without a new frame (a freeze) between ``start_ms`` and ``end_ms``
    (Unix ms), from ``times`` as the page records them, counting from ``start_ms`` to
    the first frame and from the last one to ``end_ms``."""
    stamps = [start_ms, *(t[0] for t in times if start_ms <= t[0] <= end_ms), end_ms]
    return max(b - a for a, b in itertools.pairwise(stamps))


class VideoOnly:
    """RtcPeers' owner: a connection for video alone opens no data channel."""

    async def channel_opened(self, peer_id: str, link: Any) -> None:
        return None

    async def received(self, link: Any, raw: Any) -> None:
        return None

    async def path_changed(self, peer_id: str, path: str) -> None:
        return None

    async def channel_closed(self, peer_id: str) -> None:
        return None


def moving_pose() -> dict[str, float]:
    """A vehicle turning and driving: a picture that needs its bitrate (a still one
    compresses to little and would never fill a link)."""
    t = time.monotonic()
    return {"lat": 43.7 + (t % 60) * 2e-5, "lon": 7.25, "heading": (t * 40) % 360}


@contextlib.contextmanager
def pilot_behind_a_link(tmp_path: Path) -> Iterator[tuple[NetLab, BrowserProcess]]:
    """A network lab with one machine, ``pilot``, whose Chromium is up (no page yet);
    skips without root, namespaces or Chromium."""
    available, why = netlab_available()
    if not available:
        pytest.skip(why)
    if (missing := chromium_missing_reason()) is not None:
        pytest.skip(missing)
    root = Path(__file__).resolve().parents[2]
    log_path = tmp_path / "browser.log"
    with NetLab(machines=["pilot"], workdir=tmp_path / "lab") as lab:
        with open(log_path, "w") as log:
            proc = lab.popen(
                "pilot",
                BrowserProcess.argv(),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
                cwd=root,
                env={**os.environ, "PYTHONPATH": str(root), "PYTHONUNBUFFERED": "1"},
            )
        browser = BrowserProcess(proc, log_path)
        try:
            browser.started()
            yield lab, browser
        finally:
            browser.close()
