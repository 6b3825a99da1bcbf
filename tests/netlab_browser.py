"""Debian's Chromium, driven by Playwright, as a user inside a network lab's site
(tests/netlab.py), plus ``BrowserProcess``, the test-side handle that drives it.

Run: ``ip netns exec NS python -m tests.netlab_browser [--chromium PATH]``. Chromium starts
with the flags of tests/browser.py and ``WebRtcHideLocalIpsWithMdns`` off, so that its
host candidates are real addresses (aioice cannot resolve mDNS ``.local`` names across
namespaces).

It speaks JSON lines: one request on stdin, one reply on stdout for each, in order.
Requests carry an ``id`` that the reply repeats; a reply is ``{"id", "ok": true,
"value"}`` or ``{"id", "ok": false, "error"}``. ``expr`` is a JavaScript expression
evaluated in the page with ``c`` bound to ``window.iouvController``.

``{"cmd": "open", "base", "username", "password", "path"}``
    sign in through the login form at ``base``, then open ``base + path`` (a session's
    page); the value is the page's URL.
``{"cmd": "goto", "url"}``
    open ``url`` (a page of the test's own); the value is the page's URL.
``{"cmd": "wait", "expr", "timeout"}``
    wait (``timeout`` seconds) until ``expr`` is truthy; the value is what it was.
``{"cmd": "eval", "expr"}``
    the value of ``expr`` now.
``{"cmd": "key", "action": "down"|"up"|"press", "key"}``
    the keyboard (``ArrowUp``: the car's forward).
``{"cmd": "close"}`` (or EOF)
    close the browser and exit 0.

Every page of the browser records, in ``window.netlab``, which transport carried what:
``sent[transport][command name]`` (commands sent) and ``acks[transport]`` (positive
acks received), with transport ``"datachannel"`` or ``"websocket"``; and
``telemetry``, the last value of each telemetry topic the page received.
The page's console and errors go to stderr (the test's log file).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import IO, Any

from tests.netlab_peer import stdin_lines

#: Runs first in every page: counts commands and acks per transport, keeps telemetry.
RECORD_TRANSPORTS = """
(() => {
  const netlab = { sent: { datachannel: {}, websocket: {} }, acks: { datachannel: 0, websocket: 0 },
                   telemetry: {} };
  window.netlab = netlab;
  for (const [cls, transport] of [[WebSocket, "websocket"], [RTCDataChannel, "datachannel"]]) {
    const send = cls.prototype.send;
    cls.prototype.send = function (data) {
      try {
        const msg = JSON.parse(data);
        if (msg.type === "command") {
          netlab.sent[transport][msg.name] = (netlab.sent[transport][msg.name] || 0) + 1;
        }
      } catch (e) { /* not JSON: not ours to count */ }
      return send.call(this, data);
    };
    const on = Object.getOwnPropertyDescriptor(cls.prototype, "onmessage");
    Object.defineProperty(cls.prototype, "onmessage", {
      configurable: true,
      get() { return on.get.call(this); },
      set(handler) {
        on.set.call(this, handler && function (event) {
          try {
            const msg = JSON.parse(event.data);
            if (msg.type === "ack" && msg.ok) netlab.acks[transport] += 1;
            if (msg.type === "telemetry") Object.assign(netlab.telemetry, msg.data);
          } catch (e) { /* as above */ }
          return handler.call(this, event);
        });
      },
    });
  }
})();
"""

_STARTED = time.monotonic()


def _log(text: str) -> None:
    sys.stderr.write(f"[{time.monotonic() - _STARTED:8.3f}] {text}\n")
    sys.stderr.flush()


def _reply(**fields: Any) -> None:
    sys.stdout.write(json.dumps(fields, default=str) + "\n")
    sys.stdout.flush()


def _in_page(expr: str) -> str:
    return f"() => {{ const c = window.iouvController; return ({expr}); }}"


async def browser_main(args: argparse.Namespace) -> int:
    from playwright.async_api import async_playwright

    from tests.browser import launch_options

    options = launch_options(extra_args=["--disable-features=WebRtcHideLocalIpsWithMdns"])
    options["executable_path"] = args.chromium
    async with async_playwright() as pw:
        browser = await pw.chromium.launch(**options)
        context = await browser.new_context()
        await context.add_init_script(RECORD_TRANSPORTS)
        page = await context.new_page()
        page.on("console", lambda m: _log(f"console.{m.type}: {m.text}"))
        page.on("pageerror", lambda e: _log(f"pageerror: {e}"))
        _reply(id=0, ok=True, value="ready")

        async def handle(request: dict[str, Any]) -> Any:
            cmd = request.get("cmd")
            if cmd == "open":
                base = request["base"]
                await page.goto(f"{base}/accounts/login/")
                await page.fill("#id_username", request["username"])
                await page.fill("#id_password", request["password"])
                await page.click("button[type=submit]")
                await page.wait_for_url(f"{base}/")
                await page.goto(f"{base}{request['path']}")
                return page.url
            if cmd == "goto":
                await page.goto(request["url"])
                return page.url
            if cmd == "wait":
                handle = await page.wait_for_function(
                    _in_page(request["expr"]), timeout=float(request["timeout"]) * 1000
                )
                return await handle.json_value()
            if cmd == "eval":
                return await page.evaluate(_in_page(request["expr"]))
            if cmd == "key":
                keyboard = page.keyboard
                action = {"down": keyboard.down, "up": keyboard.up, "press": keyboard.press}
                await action[request["action"]](request["key"])
                return None
            raise ValueError(f"unknown command {cmd!r}")

        lines = await stdin_lines()
        try:
            while (line := await lines.get()) is not None:
                if not line.strip():
                    continue
                request = json.loads(line)
                if request.get("cmd") == "close":
                    _reply(id=request.get("id"), ok=True, value=None)
                    break
                _log(f"request {line.strip()[:200]}")
                try:
                    value = await handle(request)
                except Exception as exc:  # reported to the test, which decides
                    _reply(id=request.get("id"), ok=False, error=f"{type(exc).__name__}: {exc}")
                else:
                    _reply(id=request.get("id"), ok=True, value=value)
        finally:
            await browser.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from tests.browser import CHROMIUM_PATH

    parser = argparse.ArgumentParser(prog="python -m tests.netlab_browser", description=__doc__)
    parser.add_argument("--chromium", default=CHROMIUM_PATH, help="the Chromium binary")
    args = parser.parse_args(argv)
    return asyncio.run(browser_main(args))


# -- the test-side handle --------------------------------------------------------------


class BrowserError(AssertionError):
    """A request failed or timed out; the message has the browser's log tail."""


class BrowserProcess:
    """Drives one browser program through its stdin/stdout (see the module docstring).

    ``proc`` is the started process (e.g. ``NetLab.popen(site, BrowserProcess.argv(),
    stdin=PIPE, stdout=PIPE, stderr=log, text=True)``), ``log_path`` where its stderr
    goes (quoted in failures). A thread reads the replies into a queue, so every wait
    has a deadline.
    """

    def __init__(self, proc: subprocess.Popen[str], log_path: os.PathLike[str] | str) -> None:
        self.proc = proc
        self.log_path = log_path
        self._ids = iter(range(1, 1 << 30))
        self._replies: queue.Queue[dict[str, Any] | None] = queue.Queue()
        assert proc.stdout is not None
        threading.Thread(target=self._read, args=(proc.stdout,), daemon=True).start()

    @staticmethod
    def argv() -> list[str]:
        return [sys.executable, "-m", "tests.netlab_browser"]

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            with contextlib.suppress(ValueError):
                self._replies.put(json.loads(line))
        self._replies.put(None)

    def log_tail(self, chars: int = 3000) -> str:
        try:
            with open(self.log_path, errors="replace") as log:
                return log.read()[-chars:]
        except OSError:
            return ""

    def _await(self, request_id: int, timeout: float, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            try:
                reply = self._replies.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise BrowserError(
                    f"browser: no answer to {what} within {timeout}s\n{self.log_tail()}"
                ) from None
            if reply is None:
                self._replies.put(None)
                raise BrowserError(
                    f"browser exited ({self.proc.poll()}) before {what}\n{self.log_tail()}"
                )
            if reply.get("id") == request_id:
                return reply

    def started(self, timeout: float = 60.0) -> None:
        """Wait for Chromium to be up (the program's first reply)."""
        self._await(0, timeout, "start")

    def call(self, cmd: str, *, within: float = 30.0, **args: Any) -> Any:
        """Send one request; its value. BrowserError when it fails or no answer comes
        ``within`` seconds."""
        request_id = next(self._ids)
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"id": request_id, "cmd": cmd, **args}) + "\n")
        self.proc.stdin.flush()
        reply = self._await(request_id, within, f"{cmd} {args}")
        if not reply.get("ok"):
            raise BrowserError(f"browser: {cmd} {args}: {reply.get('error')}\n{self.log_tail()}")
        return reply.get("value")

    def eval(self, expr: str) -> Any:
        return self.call("eval", expr=expr)

    def wait(self, expr: str, timeout: float) -> Any:
        """Wait until ``expr`` is truthy in the page; its value. On a timeout the error
        says what the controller's state was."""
        try:
            return self.call("wait", within=timeout + 15, expr=expr, timeout=timeout)
        except BrowserError as exc:
            try:
                state = self.eval(
                    "c && {path: c.path, role: c.role, conn: c.connState, stats: c.stats,"
                    " channels: !!c.channels, pc: c.pc && c.pc.connectionState,"
                    " netlab: window.netlab}"
                )
            except BrowserError:
                raise exc from None
            raise BrowserError(f"{exc}\ncontroller state: {json.dumps(state)}") from None

    def close(self, timeout: float = 15.0) -> int | None:
        """Ask the program to close the browser and exit; its return code."""
        with contextlib.suppress(BrokenPipeError, OSError, ValueError):
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps({"id": -1, "cmd": "close"}) + "\n")
            self.proc.stdin.flush()
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


if __name__ == "__main__":
    sys.exit(main())
