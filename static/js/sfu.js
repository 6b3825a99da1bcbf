/*
 * Watching a vehicle through the platform's SFU (Janus VideoRoom), for everyone but
 * its pilot (docs/video.md, "The SFU"). The user task of a viewer carries `sfu`:
 * Janus's WebSocket URL, a token Janus checks on every request, the session's room,
 * its pin and the vehicle's feed. One WebSocket (subprotocol "janus-protocol"), one
 * session, one subscriber handle; Janus offers, the page answers with a complete SDP.
 *
 *   const watch = new IouvSfu.Watcher(task.sfu, {iceServers, onTrack, onState});
 *   watch.start();   // onState("connecting" | "waiting" | "watching" | "unavailable", why)
 *   watch.close();
 *
 * When Janus cannot be reached or goes away the state is "unavailable" and the watcher
 * tries again with backoff; while the vehicle is not publishing (it is reconnecting)
 * it is "waiting" and asks again every few seconds.
 */
(function () {
  "use strict";

  const KEEPALIVE_MS = 20000; // Janus drops a session silent for 60 s
  const REQUEST_MS = 15000;
  const NO_SUCH_FEED = 428;
  const NO_SUCH_ROOM = 426;

  function iceGathered(pc, ms) {
    if (pc.iceGatheringState === "complete") return Promise.resolve();
    return new Promise((resolve) => {
      const done = () => { clearTimeout(timer); pc.removeEventListener("icegatheringstatechange", check); resolve(); };
      const check = () => { if (pc.iceGatheringState === "complete") done(); };
      const timer = setTimeout(done, ms);
      pc.addEventListener("icegatheringstatechange", check);
    });
  }

  class JanusError extends Error {
    constructor(code, reason) {
      super(`${code}: ${reason}`);
      this.code = code;
    }
  }

  class Watcher {
    constructor(sfu, { iceServers = [], onTrack = () => {}, onState = () => {} } = {}) {
      this.sfu = sfu;
      this.iceServers = iceServers;
      this.onTrack = onTrack;
      this.onState = onState;
      this.state = "idle";
      this.closed = false;
      this.attempts = 0;
      this.ws = null;
      this.pc = null;
      this.pending = new Map(); // transaction -> {resolve, reject, timer}
      this.timers = [];
    }

    setState(state, why = "") {
      this.state = state;
      this.onState(state, why);
    }

    start() {
      if (this.closed) return;
      this.setState(this.attempts ? this.state : "connecting");
      const ws = new WebSocket(this.sfu.url, "janus-protocol");
      this.ws = ws;
      ws.onopen = () => this.run(ws).catch((e) => this.failed(ws, e));
      ws.onmessage = (ev) => this.received(ev);
      ws.onclose = () => this.failed(ws, new JanusError(0, "the video server closed the connection"));
      ws.onerror = () => {}; // onclose follows
    }

    async run(ws) {
      const created = await this.send(ws, { janus: "create" });
      this.session = created.data.id;
      this.timers.push(setInterval(() => this.send(ws, { janus: "keepalive" }).catch(() => {}), KEEPALIVE_MS));
      const attached = await this.send(ws, { janus: "attach", plugin: "janus.plugin.videoroom" });
      this.handle = attached.data.id;
      await this.subscribe(ws);
    }

    async subscribe(ws) {
      let answer;
      for (;;) {
        try {
          answer = await this.plugin(ws, {
            request: "join", ptype: "subscriber", room: this.sfu.room, pin: this.sfu.pin,
            streams: [{ feed: this.sfu.feed }],
          });
          break;
        } catch (e) {
          // The vehicle is not (yet, or any more) publishing: ask again shortly.
          if (e.code !== NO_SUCH_FEED && e.code !== NO_SUCH_ROOM) throw e;
          this.setState("waiting", "the vehicle's video has not reached the video server yet");
          await new Promise((r) => setTimeout(r, 2000));
          if (this.ws !== ws) return;
        }
      }
      const pc = new RTCPeerConnection({ iceServers: this.iceServers });
      this.pc = pc;
      pc.ontrack = (event) => this.onTrack(event, pc);
      pc.onconnectionstatechange = () => {
        if (this.pc !== pc) return;
        if (pc.connectionState === "connected") { this.attempts = 0; this.setState("watching"); }
        if (pc.connectionState === "failed") this.failed(ws, new JanusError(0, "no media path to the video server"));
      };
      await pc.setRemoteDescription(answer.jsep);
      await pc.setLocalDescription(await pc.createAnswer());
      await iceGathered(pc, 2000);
      await this.plugin(ws, { request: "start" }, { type: "answer", sdp: pc.localDescription.sdp });
    }

    // Something on the socket: an answer to a request, or an event of the handle.
    received(ev) {
      let msg;
      try { msg = JSON.parse(ev.data); } catch (e) { return; }
      const waiting = this.pending.get(msg.transaction);
      if (msg.janus === "ack" && !(waiting && waiting.ackIsAnswer)) return; // an event follows
      if (waiting) {
        this.pending.delete(msg.transaction);
        clearTimeout(waiting.timer);
        if (msg.janus === "error") waiting.reject(new JanusError(msg.error.code, msg.error.reason));
        else waiting.resolve(msg);
        return;
      }
      const data = msg.plugindata && msg.plugindata.data;
      // The vehicle stopped publishing (its link to Janus dropped): Janus tells its
      // subscribers "updated" with no stream active, and the feed that comes back is a
      // new one, which this subscription would never show.
      const inactive = data && data.videoroom === "updated" && Array.isArray(data.streams)
        && !data.streams.some((s) => s.active !== false);
      const gone = msg.janus === "hangup" || msg.janus === "detached" || inactive
        || (data && (data.videoroom === "destroyed" || data.unpublished !== undefined || data.leaving !== undefined));
      if (gone && this.ws) {
        // The vehicle left the room (or the room went): subscribe again from scratch.
        const ws = this.ws;
        this.retry(ws, "the vehicle's video stopped reaching the video server", "waiting");
      }
    }

    send(ws, message) {
      const transaction = Math.random().toString(36).slice(2);
      const full = { ...message, transaction, token: this.sfu.token };
      if (this.session && message.janus !== "create") full.session_id = this.session;
      if (this.handle && message.janus === "message") full.handle_id = this.handle;
      return new Promise((resolve, reject) => {
        const timer = setTimeout(() => {
          this.pending.delete(transaction);
          reject(new JanusError(0, "the video server did not answer"));
        }, REQUEST_MS);
        this.pending.set(transaction, { resolve, reject, timer, ackIsAnswer: message.janus === "keepalive" });
        ws.send(JSON.stringify(full));
      });
    }

    async plugin(ws, body, jsep) {
      const message = { janus: "message", body };
      if (jsep) message.jsep = jsep;
      const reply = await this.send(ws, message);
      const data = (reply.plugindata && reply.plugindata.data) || {};
      if (data.error_code) throw new JanusError(data.error_code, data.error);
      return reply;
    }

    failed(ws, error) {
      if (this.ws !== ws || this.closed) return;
      const refused = error && (error.code === 403 || error.code === 433);
      this.retry(ws, refused ? "the video server refused this page (reload it)" : "the video server cannot be reached", "unavailable");
    }

    retry(ws, why, state) {
      if (this.ws !== ws) return;
      this.teardown();
      this.setState(state, why);
      const delay = Math.min(15000, 1000 * 2 ** Math.min(this.attempts, 4)) * (0.5 + Math.random() / 2);
      this.attempts += 1;
      this.retryTimer = setTimeout(() => this.start(), delay);
    }

    teardown() {
      for (const t of this.timers) clearInterval(t);
      this.timers = [];
      for (const p of this.pending.values()) { clearTimeout(p.timer); p.reject(new JanusError(0, "closed")); }
      this.pending.clear();
      if (this.pc) { this.pc.close(); this.pc = null; }
      const ws = this.ws;
      this.ws = null;
      this.session = this.handle = null;
      if (ws) {
        ws.onclose = null;
        try {
          if (ws.readyState === WebSocket.OPEN) ws.close();
        } catch (e) { /* already closing */ }
      }
    }

    close() {
      this.closed = true;
      clearTimeout(this.retryTimer);
      this.teardown();
    }
  }

  window.IouvSfu = { Watcher, JanusError };
})();
