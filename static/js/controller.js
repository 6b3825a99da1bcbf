/* IoUV controller: the user task in the browser.
 *
 * Connects straight to the vehicle's agent (or to the platform's relay) with a signed
 * grant, builds its controls from the vehicle's declared command vocabulary, and
 * speaks the control protocol of docs/protocol.md:
 *   - hold a key or button = the command repeats; release = it stops repeating (and
 *     "stop" is sent when the vehicle has one);
 *   - the repeat interval follows the measured round trip, with at most one command
 *     of a kind in flight, so commands never queue up on a slow link;
 *   - keepalives while in control, so the agent's link-loss watchdog stays quiet;
 *   - telemetry by subscription, video over WebRTC, refusals and fail-safes shown;
 *   - the path that works best: the page signals a WebRTC connection through the
 *     platform's relay socket (the vehicle only dials out) and, once its data channels
 *     open, control and video ride it, directly or through TURN; until then, or if it
 *     fails, the relay carries control; on a LAN the vehicle's own socket is the last
 *     resort. The page shows the path and its round trip;
 *   - driving pauses while the video is frozen (stop, land and return home still work);
 *     a key, button or stick still held when the picture moves again drives on.
 * No build step: plain ES2017 in one file.
 */
(function () {
  "use strict";

  const MIN_INTERVAL_MS = 100;
  const MAX_INTERVAL_MS = 1000;
  const TELEMETRY_HZ = 4;
  // WebRTC: how long ICE may take before control stays on the relay, and when to try
  // again after a failure (a network that changed may let it through).
  const RTC_CONNECT_MS = 10000;
  const RTC_RETRY_MS = 30000;
  // Driving pauses when the picture has not moved for this long.
  const STALE_VIDEO_MS = 1500;
  // A socket carrying control hears the vehicle at least once a second (its telemetry,
  // the answers to our pings): silent this long, it is given up and another opened.
  // A platform machine cut off from the network, or a proxy still holding a connection
  // to it, would otherwise keep it open, and the browser would wait on TCP for minutes.
  const SILENT_SOCKET_MS = 5000;
  // Commands that make the vehicle safe: never behind other traffic, never paused.
  const SAFE_COMMANDS = new Set(["stop", "land", "return_to_home"]);
  // Refusals the link caused (the round trip over the vehicle's limit, a command too
  // old when it arrived): they pass with the link, so a held motion keeps repeating and
  // moves again once the link allows it. Any other refusal would only come again.
  const LINK_REFUSALS = new Set(["latency", "stale"]);
  const PATH_WORDS = {
    webrtc_direct: "WebRTC, direct",
    webrtc_turn: "WebRTC through TURN",
    relay: "relay through the platform",
    websocket: "the vehicle's own socket",
  };
  const KEY_ALIASES = { " ": "Space", Spacebar: "Space" };
  // What a touch screen shows on the picture (its telemetry panel is below the fold
  // there): the first of these the vehicle reports, in this order.
  const HUD_TOPICS = ["altitude", "speed", "battery_level"];
  // How a key is written on its button (the arrows as arrows).
  const KEY_SHOWN = { ArrowUp: "↑", ArrowDown: "↓", ArrowLeft: "←", ArrowRight: "→", " ": "Space" };

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") node.className = v;
      else if (k.includes("-")) node.setAttribute(k, v); // data-*, aria-*
      else node[k] = v;
    }
    for (const child of children) node.append(child);
    return node;
  }

  function keyName(key) {
    const k = KEY_ALIASES[key] || key;
    return k.length === 1 ? k.toLowerCase() : k;
  }

  // An argument in words: "altitude (m)" for alt_m in metres, "latitude (deg)" for lat.
  const ARG_WORDS = { lat: "latitude", lon: "longitude", alt: "altitude" };
  function argLabel(arg, spec) {
    const unit = spec.unit || "";
    let name = unit && arg.endsWith(`_${unit}`) ? arg.slice(0, -unit.length - 1) : arg;
    name = ARG_WORDS[name] || name.replace(/_/g, " ");
    return unit ? `${name} (${unit})` : name;
  }

  function csrfToken() {
    const m = document.cookie.match(/(?:^|; )csrftoken=([^;]+)/);
    return m ? decodeURIComponent(m[1]) : "";
  }

  const GAMEPAD_DEAD_ZONE = 0.15;
  // [axis, key when pushed to the negative side, key when pushed to the positive side]
  const GAMEPAD_AXES = [[1, "w", "s"], [0, "a", "d"], [3, "ArrowUp", "ArrowDown"], [2, "ArrowLeft", "ArrowRight"]];
  // The on-screen sticks of a touch screen: the gamepad's two sticks, by the same axes
  // and keys, so a vehicle's vocabulary maps the same way to both.
  const STICKS = [
    { side: "left", x: 0, y: 1, keys: { up: "w", down: "s", left: "a", right: "d" } },
    { side: "right", x: 2, y: 3, keys: { up: "ArrowUp", down: "ArrowDown", left: "ArrowLeft", right: "ArrowRight" } },
  ];
  const STICK_KEYS = new Set(STICKS.flatMap((s) => Object.values(s.keys).map(keyName)));
  const GAMEPAD_DPAD = [[12, "ArrowUp"], [13, "ArrowDown"], [14, "ArrowLeft"], [15, "ArrowRight"]];
  // [button, commands it presses, the first the vehicle has]
  const GAMEPAD_BUTTONS = [
    [0, ["land", "stop"]], [1, ["return_to_home"]], [2, ["stop"]], [3, ["take_off"]],
    [8, ["disarm"]], [9, ["arm"]],
  ];

  // Wait for ICE candidates, but not forever (closed networks never "complete").
  function iceGathered(pc, ms) {
    return new Promise((resolve) => {
      if (pc.iceGatheringState === "complete") return resolve();
      pc.addEventListener("icegatheringstatechange", () => {
        if (pc.iceGatheringState === "complete") resolve();
      });
      setTimeout(resolve, ms);
    });
  }

  // A fresh grant for this page's session (a grant is single-use): whether the platform
  // gave one, and its answer (the user task, or {error: {code, message}}).
  async function grantFetch(url) {
    const response = await fetch(url, {
      method: "POST",
      headers: { "X-CSRFToken": csrfToken(), Accept: "application/json" },
      credentials: "same-origin",
    });
    return { ok: response.ok, body: await response.json() };
  }

  // A telemetry value in a person's words, by the agent's description of its topic
  // (telemetry_info: label, unit, decimals, yes/no words): "12.3 m", "armed", "82 %".
  function formatValue(value, info = {}) {
    if (value === null || value === undefined) return "–";
    const unit = info.unit ? (info.unit === "°" ? "°" : ` ${info.unit}`) : "";
    if (typeof value === "number") {
      const digits = info.decimals ?? (Number.isInteger(value) ? 0 : 2);
      return `${value.toFixed(digits)}${unit}`;
    }
    if (typeof value === "boolean") return value ? (info.yes || "yes") : (info.no || "no");
    if (typeof value === "object") {
      if ("lat" in value && "lon" in value) {
        const ns = value.lat >= 0 ? "N" : "S";
        const ew = value.lon >= 0 ? "E" : "W";
        return `${Math.abs(value.lat).toFixed(5)}° ${ns}, ${Math.abs(value.lon).toFixed(5)}° ${ew}`;
      }
      return Object.entries(value).map(([k, v]) => `${k.replace(/_/g, " ")} ${formatValue(v, info)}`).join(" · ");
    }
    return String(value).replace(/_/g, " ");
  }

  class Controller {
    constructor(root, task, options) {
      this.root = root;
      this.task = task;
      this.options = options;
      this.ws = null;
      this.seq = 0;
      this.role = "pending";
      this.commands = new Map(); // name -> spec
      this.keys = new Map(); // key -> command name
      this.held = new Map(); // name -> {lastSent, inFlight}
      this.pending = new Map(); // seq -> {name, sentAt}
      this.rtt = null; // smoothed round trip (ms)
      this.rttDev = 0;
      this.lastSent = 0;
      this.over = false;
      this.reconnects = 0;
      this.stats = { acks: 0, refused: 0, refusedBy: {}, telemetry: 0, framesDecoded: 0, failsafes: 0 };
      this.lastRefusal = null;
      this.telemetryInfo = {}; // topic -> {label, unit, decimals, yes, no}
      this.pc = null;
      this.channels = null; // the WebRTC data channels once open: {control, input, urgent}
      this.direct = false; // the relay socket failed: the vehicle's own socket instead
      this.path = null;
      this.lastFrameAt = 0; // when the picture last moved (0: no picture yet)
      this.videoFrozen = false;
      // What the vehicle's camera sends now (its video_status: width, height, fps,
      // bitrate, which follow this user's link when piloting) and what this browser
      // receives (getStats: width, height, fps, kbps).
      this.videoStatus = null;
      this.videoReceived = null;
      this.timers = [];
      this.commandList = [];
      this.stickAxes = [0, 0, 0, 0]; // the on-screen sticks, as gamepad axes
      this.stickHeld = new Map(); // command name -> deflection, from sticks of any kind
      this.stickPaused = new Set(); // motions a stick asks for while the video is frozen
      this.keyPaused = new Set(); // motions a key or button holds while the video is frozen
      // What the person steers with, for the layout and the hints: "touch", "keys" or
      // "gamepad"; a touch screen starts with touch, and the last input used wins.
      const coarse = window.matchMedia && window.matchMedia("(pointer: coarse)").matches;
      this.inputMode = coarse ? "touch" : "keys";
      root.dataset.input = this.inputMode;
      this.ui = {
        state: root.querySelector("[data-conn-state]"),
        role: root.querySelector("[data-role]"),
        rtt: root.querySelector("[data-rtt]"),
        path: root.querySelector("[data-path]"),
        videoStats: root.querySelector("[data-video-stats]"),
        interval: root.querySelector("[data-interval]"),
        telemetry: root.querySelector("[data-telemetry]"),
        controls: root.querySelector("[data-controls]"),
        overlay: root.querySelector("[data-overlay-actions]"),
        sticks: root.querySelector("[data-sticks]"),
        hud: root.querySelector("[data-hud]"),
        banner: root.querySelector("[data-banner]"),
        toast: root.querySelector("[data-toast]"),
        video: root.querySelector("video"),
        videoNote: root.querySelector("[data-video-note]"),
        log: root.querySelector("[data-log]"),
      };
      window.iouvController = this; // for tests and the curious
    }

    // --- lifecycle -------------------------------------------------------------------
    start() {
      this.bindInputs();
      this.connect();
      this.watchSession();
      this.timers.push(setInterval(() => this.tick(), 20));
      this.timers.push(setInterval(() => { this.checkSocket(); this.ping(); }, 1000));
      this.timers.push(setInterval(() => this.readVideoStats(), 1000));
      this.timers.push(setInterval(() => this.keepalive(), this.keepaliveMs()));
    }

    keepaliveMs() {
      const timeout = (this.vehicle && this.vehicle.link_loss_timeout_ms) || 500;
      return Math.max(50, Math.min(100, timeout / 4));
    }

    // WebRTC is tried for a point-to-point session: signalled on the platform's relay
    // socket, which carries control meanwhile and if WebRTC fails.
    wantsRtc() {
      // A viewer watches through the SFU when the platform has one: no connection to
      // the vehicle of its own (its places are kept for the pilot).
      if (this.watchesSfu()) return false;
      return !this.task.relay && !!this.task.relay_url && !!window.RTCPeerConnection && !this.direct;
    }

    watchesSfu() {
      return !!(this.task.sfu && this.task.role !== "controller" && window.IouvSfu && window.RTCPeerConnection);
    }

    // The vehicle's own socket, when the page may open it (not ws:// from https://).
    directUsable() {
      const url = this.task.control_url;
      return !!url && url !== this.task.relay_url && (location.protocol === "http:" || url.startsWith("wss:"));
    }

    connect() {
      this.setState("connecting");
      const url = this.direct || this.task.relay || !this.task.relay_url ? this.task.control_url : this.task.relay_url;
      const ws = new WebSocket(url);
      this.ws = ws;
      let opened = false;
      ws.onopen = () => {
        opened = true;
        this.lastHeard = performance.now();
        this.sendSignal({ type: "auth", grant: this.task.grant });
      };
      ws.onmessage = (event) => {
        this.lastHeard = performance.now();
        let msg;
        try { msg = JSON.parse(event.data); } catch (e) { return; }
        this.handle(msg);
      };
      ws.onclose = (event) => this.socketLost(ws, opened, event.reason);
    }

    // The control socket ``ws`` closed, or was given up as silent: carry on over WebRTC
    // if it is up, else connect again (the vehicle's own socket, if the relay never
    // opened; else the relay with a fresh grant).
    socketLost(ws, opened, reason) {
      if (this.ws !== ws) return;
      this.ws = null;
      if (this.channels && !this.over) {
        // The platform's socket is gone but the WebRTC connection carries on.
        this.toast("The platform's relay dropped; the direct connection carries on.", "warn");
        return;
      }
      if (!opened && !this.direct && !this.over && this.directUsable()) {
        // The relay never opened and the grant was not used: try the vehicle's socket.
        this.direct = true;
        this.connect();
        return;
      }
      this.role = "pending";
      this.releaseAll(false);
      this.closeVideo();
      this.setPath(null);
      if (this.over) { this.setState("ended"); return; }
      this.setState("disconnected");
      const why = reason ? ` (${reason})` : "";
      this.showBanner(`Connection to the vehicle lost${why}. Reconnecting…`, "warn");
      this.reconnect();
    }

    // Called every second: a control socket silent for SILENT_SOCKET_MS is let go (its
    // close handshake could not finish either) and treated as closed.
    checkSocket() {
      const ws = this.ws;
      if (!ws || ws.readyState !== WebSocket.OPEN || this.channels) return;
      if (performance.now() - this.lastHeard < SILENT_SOCKET_MS) return;
      ws.onclose = null;
      ws.onmessage = null;
      ws.close();
      this.socketLost(ws, true, `no answer for ${SILENT_SOCKET_MS / 1000} s`);
    }

    async reconnect() {
      // A grant is single-use: ask the platform for a fresh one, then connect again.
      const delay = Math.min(5000, 500 * 2 ** Math.min(this.reconnects, 4)) * (0.5 + Math.random() / 2);
      this.reconnects += 1;
      await new Promise((r) => setTimeout(r, delay));
      if (this.over) return;
      try {
        const { ok, body } = await grantFetch(this.options.grantUrl);
        if (!ok && body.error && body.error.code === "no_vehicle_yet") {
          this.reconnect(); // between vehicles: the next one's grant comes soon
          return;
        }
        if (!ok) {
          this.endSession(body.error ? body.error.message : "the session is over");
          return;
        }
        this.task = body;
        this.connect();
      } catch (e) {
        this.reconnect();
      }
    }

    // A message to the vehicle on the best path: the WebRTC data channels while open
    // (held motions on the lossy "input" channel, safe commands on "urgent"), else the
    // socket. Returns false when no path is open.
    send(message) {
      const ch = this.channels;
      if (ch) {
        let channel = ch.control;
        if (message.type === "command") {
          if (SAFE_COMMANDS.has(message.name)) channel = ch.urgent;
          else if (this.held.has(message.name)) channel = ch.input;
        }
        if (channel.readyState === "open") {
          channel.send(JSON.stringify(message));
          return true;
        }
      }
      return this.sendSignal(message);
    }

    // A message on the socket only (auth and the WebRTC signalling).
    sendSignal(message) {
      if (!this.ws || this.ws.readyState !== WebSocket.OPEN) return false;
      this.ws.send(JSON.stringify(message));
      return true;
    }

    // --- protocol --------------------------------------------------------------------
    handle(msg) {
      switch (msg.type) {
        case "welcome": return this.onWelcome(msg);
        case "ack": return this.onAck(msg);
        case "telemetry": return this.onTelemetry(msg);
        case "pong": return this.onRtt(performance.now() - msg.t);
        case "ping": return this.send({ type: "pong", t: msg.t, client_t: Date.now() });
        case "role": return this.setRole(msg.role);
        case "event": return this.onEvent(msg);
        case "webrtc_answer": return this.onAnswer(msg);
        case "video_status": return this.onVideoStatus(msg);
        case "error":
          if (msg.code === "webrtc" || msg.code === "no_webrtc") return this.rtcFailed(msg.message);
          return this.toast(`${msg.code}: ${msg.message}`, "bad");
        default: return undefined;
      }
    }

    onWelcome(msg) {
      this.reconnects = 0;
      this.vehicle = msg.vehicle;
      // Only the driver's: a watched mission's end concerns all its vehicles.
      if (msg.vehicle.consequence && msg.role === "controller") this.setConsequence(msg.vehicle.consequence);
      this.setState("connected");
      this.hideBanner();
      this.setRole(msg.role);
      if (msg.vehicle.failsafe) {
        // The vehicle acted on its own while no page of this user was connected (a
        // reload that took longer than the link-loss timeout, a network that dropped):
        // say so, and what it is doing, rather than "connected" as if nothing happened.
        const f = msg.vehicle.failsafe;
        const ago = f.ago_s != null ? ` ${Math.max(1, Math.round(f.ago_s))} s ago` : "";
        const next = msg.role === "controller"
          ? "You are in control again: any command takes it over."
          : "Take control to drive it again.";
        this.showBanner(`While this page was away, ${this.failsafeWhy(f)}, so it performed its fail-safe${ago}: ${this.failsafeDoes(f)}. ${next}`, "warn");
      }
      this.buildControls(msg.commands);
      this.telemetryInfo = msg.telemetry_info || {};
      if (msg.telemetry.length) {
        this.send({ type: "subscribe", topics: msg.telemetry, rate_hz: TELEMETRY_HZ });
      }
      if (this.watchesSfu()) { if (msg.vehicle.video) this.startSfu(); }
      else if (this.wantsRtc()) this.startRtc();
      else if (msg.vehicle.video) this.startVideo();
      if (!msg.vehicle.video && this.ui.videoNote) this.ui.videoNote.textContent = "This vehicle has no camera.";
    }

    onAck(msg) {
      const sent = this.pending.get(msg.seq);
      this.pending.delete(msg.seq);
      if (sent) {
        this.onRtt(performance.now() - sent.sentAt);
        const hold = this.held.get(sent.name);
        if (hold) hold.inFlight = false;
      }
      if (msg.ok) { this.stats.acks += 1; return; }
      this.stats.refused += 1;
      this.stats.refusedBy[msg.code] = (this.stats.refusedBy[msg.code] || 0) + 1;
      this.lastRefusal = { name: sent ? sent.name : "?", code: msg.code, error: msg.error };
      if (msg.code === "not_armed") {
        // Moving with the motors off: the hint says what to press.
        this.readyHint(false, true);
        this.toast(`${sent ? sent.name.replace(/_/g, " ") : "command"}: the motors are off. Press Arm first.`, "bad");
      } else if (LINK_REFUSALS.has(msg.code)) {
        // Said once while it lasts, not on every repeat of the held motion.
        const now = performance.now();
        if (this.linkRefusedAt === undefined || now - this.linkRefusedAt > 3000) {
          this.toast(`${sent ? sent.name : "command"} refused: ${msg.error}`, "warn");
        }
        this.linkRefusedAt = now;
      } else {
        this.toast(`${sent ? sent.name : "command"} refused: ${msg.error}`, "bad");
      }
      // Don't keep hammering a refused command, unless the link refused it.
      if (sent && !LINK_REFUSALS.has(msg.code)) this.held.delete(sent.name);
    }

    onRtt(ms) {
      // RFC 6298-style smoothing: the send interval follows the average plus deviation.
      if (this.rtt === null) { this.rtt = ms; this.rttDev = ms / 2; }
      else {
        this.rttDev = 0.75 * this.rttDev + 0.25 * Math.abs(this.rtt - ms);
        this.rtt = 0.875 * this.rtt + 0.125 * ms;
      }
      if (this.ui.rtt) this.ui.rtt.textContent = `${this.rtt.toFixed(1)} ms`;
      if (this.ui.interval) this.ui.interval.textContent = `${this.interval().toFixed(0)} ms`;
    }

    interval() {
      const wanted = this.rtt === null ? MIN_INTERVAL_MS : this.rtt + 2 * this.rttDev;
      return Math.min(MAX_INTERVAL_MS, Math.max(MIN_INTERVAL_MS, wanted));
    }

    // A vehicle whose motors are armed by hand (a boat: it has Arm and no Take off)
    // ignores the arrows until they are: while they are off, say what to press.
    readyHint(armed, insist) {
      const hint = this.root.querySelector("[data-ready-hint]");
      if (!hint) return;
      const byHand = this.commands.has("arm") && !this.commands.has("take_off");
      if (!byHand || this.role !== "controller" || armed !== false) {
        hint.hidden = true;
        return;
      }
      const name = (this.vehicle && this.vehicle.name) || "The vehicle";
      const steer = this.inputMode === "touch" ? "the sticks steer it" : "the arrow keys steer it";
      hint.textContent = `${name}'s motors are off: press Arm first, then ${steer}.`;
      hint.hidden = false;
      if (insist) {
        hint.classList.remove("attention");
        void hint.offsetWidth; // restart the highlight
        hint.classList.add("attention");
      }
    }

    onTelemetry(msg) {
      this.stats.telemetry += 1;
      if ("is_armed" in msg.data) this.readyHint(msg.data.is_armed, false);
      if (this.ui.hud) {
        const shown = HUD_TOPICS.filter((t) => t in msg.data && msg.data[t] !== null);
        this.ui.hud.replaceChildren(...shown.map((topic) => {
          const info = this.telemetryInfo[topic] || {};
          const plain = topic.replace(/_/g, " ");
          return el("span", { "data-hud-topic": topic },
            `${info.label || plain.charAt(0).toUpperCase() + plain.slice(1)} ${formatValue(msg.data[topic], info)}`);
        }));
      }
      const box = this.ui.telemetry;
      if (!box) return;
      for (const [topic, value] of Object.entries(msg.data)) {
        const info = this.telemetryInfo[topic] || {};
        let row = box.querySelector(`[data-topic="${topic}"]`);
        if (!row) {
          const plain = topic.replace(/_/g, " ");
          const label = info.label || plain.charAt(0).toUpperCase() + plain.slice(1);
          row = el("div", { class: "telemetry-row", "data-topic": topic },
            el("span", { class: "topic" }, label), el("span", { class: "value" }));
          box.append(row);
        }
        row.querySelector(".value").textContent = formatValue(value, info);
      }
    }

    // A fail-safe's cause and action in words, from the vehicle's own description of
    // its actions (the welcome's safe_actions): no codes.
    failsafeWhy(f) {
      const name = (this.vehicle && this.vehicle.name) || "the vehicle";
      const timeout = (this.vehicle && this.vehicle.link_loss_timeout_ms) || 500;
      if (f.cause === "link_lost") return `nothing reached ${name} from you for ${(timeout / 1000).toFixed(1)} s`;
      return `${name} had to act on its own (${String(f.cause || "").replace(/_/g, " ")})`;
    }

    failsafeDoes(f) {
      const name = (this.vehicle && this.vehicle.name) || "the vehicle";
      const words = ((this.vehicle && this.vehicle.safe_actions) || {})[f.action];
      return `${name} will ${words || String(f.action || "stop").replace(/_/g, " ")}`;
    }

    onEvent(msg) {
      if (msg.event === "failsafe") {
        this.stats.failsafes += 1;
        this.releaseAll(false);
        const why = this.failsafeWhy(msg.data);
        this.showBanner(`The link was lost (${why}): ${this.failsafeDoes(msg.data)}.`, "bad", "failsafe");
      } else if (msg.event === "session_ended") {
        this.endSession(msg.data.reason);
      } else if (msg.event === "path") {
        this.setPath(msg.data.path);
      } else if (msg.event === "consequence") {
        this.setConsequence(msg.data);
      } else if (msg.event === "link_recovered") {
        // Said once, then gone: a banner for the rest of the session would push the
        // controls down.
        if (this.bannerTopic === "failsafe") this.hideBanner();
        this.toast("Link back: you are in control again.", "ok");
      } else if (msg.event === "envelope_breach") {
        const d = msg.data || {};
        const unit = { altitude: "m", geofence: "m from the centre", speed: "m/s" }[d.limit] || "";
        const value = Number(d.value).toFixed(1);
        this.showBanner(
          `Safety limit: ${d.limit} ${value} ${unit} is past the ${d.limit_value} limit — ` +
          `the vehicle corrects itself (${String(d.action || "").replace(/_/g, " ")}).`, "warn", "envelope");
      } else if (msg.event === "envelope_restored") {
        // The breach's banner goes: what stays is a moment's note, not a banner that
        // pushes the controls below the fold for the rest of the session.
        if (this.bannerTopic === "envelope") this.hideBanner();
        this.toast(`Back inside the ${msg.data.limit} limit.`, "ok");
      }
    }

    // What ending the session would make the vehicle do now, as its agent says (a drone
    // landing goes on landing): the End button's confirmation says it.
    setConsequence(c) {
      const name = (this.vehicle && this.vehicle.name) || "The vehicle";
      this.consequence = `${name} will ${c.words}.`;
      for (const form of document.querySelectorAll("form[data-confirm]")) form.dataset.consequence = this.consequence;
    }

    setRole(role) {
      this.role = role;
      if (this.ui.role) this.ui.role.textContent = role === "controller" ? "in control" : "watching";
      this.root.classList.toggle("viewer", role !== "controller");
      const take = this.root.querySelector("[data-take-control]");
      if (take) take.hidden = role === "controller" || this.options.watching;
    }

    // --- controls --------------------------------------------------------------------
    buildControls(commands) {
      this.commandList = commands;
      this.commands.clear();
      this.keys.clear();
      const box = this.ui.controls;
      if (!box) return;
      box.textContent = "";
      if (this.ui.overlay) this.ui.overlay.textContent = "";
      if (this.ui.sticks) this.ui.sticks.textContent = "";
      if (this.options.watching) return;
      // On a touch screen the keys of the two sticks are steered by on-screen sticks
      // over the picture, and the other plain commands sit on the picture too.
      const touch = this.inputMode === "touch";
      const groups = new Map();
      const overlay = [];
      for (const c of commands) {
        if (!c.allowed) continue;
        this.commands.set(c.name, c);
        if (c.key) this.keys.set(keyName(c.key), c.name);
        const onStick = c.key && STICK_KEYS.has(keyName(c.key));
        if (touch && onStick) continue;
        if (touch && !this.neededArgs(c).length && this.ui.overlay) {
          overlay.push(c);
          continue;
        }
        const g = c.group || "other";
        if (!groups.has(g)) groups.set(g, []);
        groups.get(g).push(c);
      }
      for (const [group, list] of groups) {
        const pad = el("div", { class: `pad pad-${group}`, "data-group": group },
          el("h4", {}, group.replace(/_/g, " ")));
        for (const c of list) {
          const needed = this.neededArgs(c);
          if (needed.length) {
            // Arguments without a default (a waypoint, say): ask for them beside the button.
            const button = this.commandButton(c, false);
            const inputs = needed.map(([arg, spec]) => el("input", {
              type: "number", step: "any", placeholder: argLabel(arg, spec),
              "aria-label": `${c.name.replace(/_/g, " ")}: ${argLabel(arg, spec)}`,
              min: spec.min ?? "", max: spec.max ?? "", "data-arg": arg, required: true,
            }));
            button.addEventListener("click", () => {
              const args = {};
              for (const input of inputs) {
                if (!input.reportValidity()) return;
                args[input.dataset.arg] = Number(input.value);
              }
              if (this.role === "controller") this.command(c.name, args);
            });
            pad.append(el("span", { class: "args" }, button, ...inputs));
            continue;
          }
          pad.append(this.commandButton(c, true));
        }
        box.append(pad);
      }
      if (touch) {
        for (const c of overlay) this.ui.overlay.append(this.commandButton(c, true));
        for (const stick of STICKS) {
          const bound = Object.entries(stick.keys)
            .map(([dir, key]) => [dir, this.commands.get(this.keys.get(keyName(key)))])
            .filter(([, c]) => c);
          if (bound.length && this.ui.sticks) this.ui.sticks.append(this.stickPad(stick, bound));
        }
      }
    }

    neededArgs(c) {
      return Object.entries(c.args || {}).filter(([, spec]) => !("default" in spec));
    }

    // One command as a real button: pressed (and, for a motion, held) by a pointer, and
    // by Enter or Space when focused (see bindInputs); named for screen readers.
    commandButton(c, pressable) {
      const label = c.name.replace(/_/g, " ");
      const keyLabel = c.key === " " ? "Space" : c.key;
      // Its name is what it shows ("up w"), so speech input can say it; the key is also
      // given as its shortcut.
      const button = el("button", {
        type: "button", class: c.motion ? "cmd motion" : "cmd", "data-command": c.name,
        title: c.description || label,
      }, label, ...(c.key ? [" ", el("kbd", { title: keyLabel }, KEY_SHOWN[c.key] || keyLabel)] : []));
      if (c.key) button.setAttribute("aria-keyshortcuts", keyLabel);
      if (pressable) {
        button.addEventListener("pointerdown", (e) => { e.preventDefault(); this.press(c.name); });
        for (const ev of ["pointerup", "pointerleave", "pointercancel"]) {
          button.addEventListener(ev, () => this.release(c.name));
        }
      }
      return button;
    }

    // An on-screen stick: a knob dragged inside a ring gives the stick's two axes in
    // -1..1 (up and left negative, as on a gamepad), read with the gamepad's each tick,
    // so a half push sends half the commands' speed. Letting go centres it: a stop.
    stickPad(stick, bound) {
      const knob = el("span", { class: "stick-knob" });
      const names = bound.map(([, c]) => c.name.replace(/_/g, " "));
      // Words all four share ("camera up", "camera left", ...) become the stick's caption.
      const words = names.map((n) => n.split(" "));
      let shared = 0;
      while (words.every((w) => w.length > shared + 1 && w[shared] === words[0][shared])) shared += 1;
      const caption = words[0].slice(0, shared).join(" ");
      const ring = el("div", {
        class: `stick stick-at-${stick.side}`, role: "group", "data-stick": stick.side,
        "aria-label": `${stick.side} stick: ${names.join(", ")}`,
      }, knob, ...bound.map(([dir], i) => el("span", { class: `stick-label stick-${dir}`, "aria-hidden": "true" },
        words[i].slice(shared).join(" "))));
      if (caption) ring.append(el("span", { class: "stick-caption", "aria-hidden": "true" }, caption));
      let pointer = null;
      const move = (e) => {
        const r = ring.getBoundingClientRect();
        const radius = r.width / 2;
        let x = (e.clientX - r.left - radius) / radius;
        let y = (e.clientY - r.top - radius) / radius;
        const length = Math.hypot(x, y);
        if (length > 1) { x /= length; y /= length; }
        this.stickAxes[stick.x] = x;
        this.stickAxes[stick.y] = y;
        knob.style.transform = `translate(${(x * radius * 0.55).toFixed(1)}px, ${(y * radius * 0.55).toFixed(1)}px)`;
      };
      const end = (e) => {
        if (e.pointerId !== pointer) return;
        pointer = null;
        this.stickAxes[stick.x] = 0;
        this.stickAxes[stick.y] = 0;
        knob.style.transform = "";
        ring.classList.remove("active");
      };
      ring.addEventListener("pointerdown", (e) => {
        e.preventDefault();
        pointer = e.pointerId;
        if (ring.setPointerCapture) ring.setPointerCapture(pointer);
        ring.classList.add("active");
        move(e);
      });
      ring.addEventListener("pointermove", (e) => { if (e.pointerId === pointer) move(e); });
      ring.addEventListener("pointerup", end);
      ring.addEventListener("pointercancel", end);
      return ring;
    }

    // The layout and hints follow the input in use: a touch on the screen, a key, or a
    // gamepad's stick or button. Switching lets go of everything held first.
    setInputMode(mode) {
      if (mode === this.inputMode) return;
      const relayout = (mode === "touch") !== (this.inputMode === "touch");
      this.inputMode = mode;
      this.root.dataset.input = mode;
      if (!relayout) return;
      this.releaseAll(true);
      this.stickAxes.fill(0);
      if (this.commandList.length) this.buildControls(this.commandList);
    }

    bindInputs() {
      // A focused on-screen button works from the keyboard as under a finger: Enter or
      // Space presses it, and a motion is held until the key is let go.
      const focusedCommand = (e) => {
        if (e.key !== "Enter" && e.key !== " ") return null;
        const button = e.target.closest && e.target.closest("button.cmd[data-command]");
        // Buttons with arguments beside them keep their own click (the form's check).
        return button && !button.closest(".args") ? button.dataset.command : null;
      };
      window.addEventListener("pointerdown", (e) => {
        if (e.pointerType === "touch") this.setInputMode("touch");
      }, true);
      window.addEventListener("keydown", (e) => {
        if (e.target.closest && e.target.closest("input, textarea, select")) return;
        if (!["Tab", "Shift", "Control", "Alt", "Meta"].includes(e.key)) this.setInputMode("keys");
        const focused = focusedCommand(e);
        if (focused) {
          e.preventDefault();
          if (!e.repeat) this.press(focused);
          return;
        }
        const name = this.keys.get(keyName(e.key));
        if (!name) return;
        e.preventDefault();
        if (!e.repeat) this.press(name);
      });
      window.addEventListener("keyup", (e) => {
        const focused = focusedCommand(e);
        if (focused) {
          this.release(focused);
          return;
        }
        const name = this.keys.get(keyName(e.key));
        if (name) this.release(name);
      });
      // Losing focus loses key-up events: release everything rather than keep moving.
      window.addEventListener("blur", () => this.releaseAll(true));
      const take = this.root.querySelector("[data-take-control]");
      if (take) take.addEventListener("click", () => this.send({ type: "take_control" }));
      window.addEventListener("gamepadconnected", () => {
        this.toast("Gamepad connected", "ok");
        this.setInputMode("gamepad");
      });
    }

    press(name) {
      const spec = this.commands.get(name);
      if (!spec || this.role !== "controller") return;
      if (this.videoFrozen && spec.motion) {
        // It waits while held: the picture moving again presses it (setVideoFrozen).
        if (!this.keyPaused.has(name)) this.toast("Driving is paused while the video is frozen.", "warn");
        this.keyPaused.add(name);
        return;
      }
      this.highlight(name, true);
      if (spec.motion) this.held.set(name, { lastSent: 0, inFlight: false });
      else this.command(name);
    }

    release(name) {
      this.highlight(name, false);
      this.keyPaused.delete(name);
      if (!this.held.delete(name)) return;
      const stillMoving = [...this.held.keys()].some((n) => (this.commands.get(n) || {}).motion);
      if (!stillMoving && this.commands.has("stop")) this.command("stop");
    }

    releaseAll(sendStop) {
      const wasHeld = this.held.size > 0;
      this.held.clear();
      this.keyPaused.clear();
      // A stick still pushed presses its motion again on the next tick; a button held
      // for a one-off command (return home, land) is not sent again until pressed anew.
      for (const name of [...this.stickHeld.keys()]) {
        if ((this.commands.get(name) || {}).motion) this.stickHeld.delete(name);
      }
      this.root.querySelectorAll(".cmd.active").forEach((b) => b.classList.remove("active"));
      if (sendStop && wasHeld && this.commands.has("stop")) this.command("stop");
    }

    highlight(name, on) {
      const button = this.root.querySelector(`[data-command="${name}"]`);
      if (button) button.classList.toggle("active", on);
    }

    command(name, args) {
      const seq = this.seq++;
      // t: when it was sent, on this page's clock; the vehicle drops commands that arrive
      // too late to still mean what the user wanted.
      if (!this.send({ type: "command", seq, name, args: args || {}, t: Date.now() })) return;
      // A held motion on the lossy channel may vanish: its ack is waited for briefly.
      const lossy = !!this.channels && this.held.has(name) && !SAFE_COMMANDS.has(name);
      this.pending.set(seq, { name, sentAt: performance.now(), lossy });
      this.lastSent = performance.now();
      const hold = this.held.get(name);
      if (hold) { hold.inFlight = true; hold.lastSent = this.lastSent; }
    }

    tick() {
      this.pollSticks();
      if (this.role !== "controller") return;
      const now = performance.now();
      if (this.lastFrameAt) {
        const frozen = now - this.lastFrameAt > STALE_VIDEO_MS;
        if (frozen !== this.videoFrozen) this.setVideoFrozen(frozen);
      }
      const every = this.interval();
      for (const [name, hold] of this.held) {
        // Repeat a held command once its last one was acknowledged and the interval
        // passed: on a slow link the rate drops instead of commands piling up.
        if (!hold.inFlight && now - hold.lastSent >= every) this.command(name, this.heldArgs(name, hold.amount));
      }
      // Forget acks that never came (a dropped relay frame, a lost datagram) so holds
      // can continue.
      for (const [seq, sent] of this.pending) {
        if (now - sent.sentAt > (sent.lossy ? Math.max(300, 2 * every) : 3000)) {
          this.pending.delete(seq);
          const hold = this.held.get(sent.name);
          if (hold) hold.inFlight = false;
        }
      }
    }

    keepalive() {
      if (this.role === "controller" && performance.now() - this.lastSent >= this.keepaliveMs()) {
        this.send({ type: "keepalive" });
      }
    }

    ping() {
      this.send({ type: "ping", t: performance.now() });
    }

    // Sticks: a gamepad in the Standard Gamepad layout, and the on-screen sticks of a
    // touch screen, read the same way. The sticks are proportional: past a dead zone, a
    // stick held part way sends its commands at that part of the key's own value
    // (speed, amount, angle), full deflection being the key; left stick = w/a/s/d,
    // right stick = the arrows (mode 2: throttle and yaw left, pitch and roll right),
    // and the d-pad = the arrows at full. Buttons act by command: A land (or stop),
    // B return home, X stop, Y take off, Back disarm, Start arm.
    pollSticks() {
      const pads = navigator.getGamepads ? navigator.getGamepads() : [];
      const pad = pads && [...pads].find(Boolean);
      const want = new Map(); // command name -> deflection 0..1
      const byKey = (key, amount) => {
        const name = this.keys.get(keyName(key));
        if (name && amount > (want.get(name) || 0)) want.set(name, amount);
      };
      let padUsed = false;
      for (const [axis, negative, positive] of GAMEPAD_AXES) {
        const fromPad = pad ? pad.axes[axis] || 0 : 0;
        const fromScreen = this.stickAxes[axis] || 0;
        const v = Math.abs(fromScreen) > Math.abs(fromPad) ? fromScreen : fromPad;
        const amount = (Math.abs(v) - GAMEPAD_DEAD_ZONE) / (1 - GAMEPAD_DEAD_ZONE);
        if (amount > 0) byKey(v < 0 ? negative : positive, Math.min(1, amount));
        if (Math.abs(fromPad) > GAMEPAD_DEAD_ZONE) padUsed = true;
      }
      const b = pad ? pad.buttons : [];
      for (const [index, key] of GAMEPAD_DPAD) {
        if (b[index] && b[index].pressed) { byKey(key, 1); padUsed = true; }
      }
      for (const [index, names] of GAMEPAD_BUTTONS) {
        const name = names.find((n) => this.commands.has(n));
        if (b[index] && b[index].pressed) padUsed = true;
        if (name && b[index] && b[index].pressed) want.set(name, 1);
      }
      if (padUsed) this.setInputMode("gamepad");
      const paused = new Set();
      for (const [name, amount] of want) {
        // While the picture is frozen a stick's motion waits (said once, when pushed),
        // and the first tick after the picture moves again presses it: the stick still
        // pushed drives on, as a key still held does.
        if (this.videoFrozen && (this.commands.get(name) || {}).motion) {
          if (!this.stickPaused.has(name)) this.toast("Driving is paused while the video is frozen.", "warn");
          paused.add(name);
          want.delete(name);
          continue;
        }
        if (!this.stickHeld.has(name)) this.press(name);
        const hold = this.held.get(name);
        if (hold) hold.amount = amount;
      }
      for (const name of this.stickHeld.keys()) if (!want.has(name)) this.release(name);
      this.stickHeld = want;
      this.stickPaused = paused;
    }

    // A held command's arguments at ``amount`` (0..1) of each number's default, never
    // below its minimum; none (the defaults) for a key or a full deflection.
    heldArgs(name, amount) {
      if (amount === undefined || amount >= 0.999) return undefined;
      const spec = this.commands.get(name) || {};
      const args = {};
      for (const [arg, a] of Object.entries(spec.args || {})) {
        if (typeof a.default !== "number") continue;
        const value = a.default * amount;
        args[arg] = typeof a.min === "number" ? Math.max(a.min, value) : value;
      }
      return args;
    }

    // --- video -----------------------------------------------------------------------
    // Video alone, while control stays on a socket (the relay the user asked for, or
    // the vehicle's own): the same offer as startRtc's, without the data channels.
    async startVideo() {
      if (!window.RTCPeerConnection || !this.ui.video) return;
      this.closeVideo();
      const pc = new RTCPeerConnection({ iceServers: this.task.ice_servers || [] });
      this.pc = pc;
      pc.addTransceiver("video", { direction: "recvonly" });
      pc.ontrack = (event) => this.showTrack(pc, event);
      pc.onconnectionstatechange = () => {
        if (this.pc !== pc || pc.connectionState !== "failed") return;
        this.closeVideo();
        if (this.ui.videoNote) this.ui.videoNote.textContent = "No video: the vehicle could not be reached directly.";
      };
      if (this.ui.videoNote) this.ui.videoNote.textContent = "Starting video…";
      try {
        await pc.setLocalDescription(await pc.createOffer());
        await iceGathered(pc, 3000);
      } catch (e) {
        if (this.pc === pc) this.closeVideo();
        if (this.ui.videoNote) this.ui.videoNote.textContent = `No video: ${e}`;
        return;
      }
      if (this.pc !== pc) return;
      this.sendSignal({ type: "webrtc_offer", sdp: pc.localDescription.sdp });
    }

    // The vehicle's video through the platform's SFU (static/js/sfu.js), for a viewer.
    // It outlives reconnections of the control socket: the SFU's token lasts hours.
    startSfu() {
      if (this.sfuWatch || !this.ui.video) return;
      const notes = {
        connecting: "Starting video…",
        waiting: "Waiting for the vehicle's video…",
      };
      const watch = new window.IouvSfu.Watcher(this.task.sfu, {
        iceServers: this.task.ice_servers || [],
        onTrack: (event) => {
          this.ui.video.srcObject = event.streams[0] || new MediaStream([event.track]);
          // One counting loop per picture: a subscription made again replaces it.
          const track = event.track;
          this.sfuTrack = track;
          const count = () => {
            if (this.sfuWatch !== watch || this.sfuTrack !== track) return;
            this.stats.framesDecoded += 1;
            this.lastFrameAt = performance.now();
            if (this.ui.videoNote && this.sfuState === "watching") this.ui.videoNote.textContent = "";
            this.ui.video.requestVideoFrameCallback(count);
          };
          if (this.ui.video.requestVideoFrameCallback) this.ui.video.requestVideoFrameCallback(count);
        },
        onState: (state, why) => {
          this.sfuState = state;
          this.root.dataset.sfu = state;
          if (!this.ui.videoNote || this.over) return;
          if (state === "unavailable") {
            this.ui.video.srcObject = null;
            this.ui.videoNote.textContent = `Video unavailable: ${why}. Trying again…`;
          } else if (state === "waiting") {
            this.ui.videoNote.textContent = notes.waiting;
          } else if (state === "connecting") {
            this.ui.videoNote.textContent = notes.connecting;
          }
        },
      });
      this.sfuWatch = watch;
      watch.start();
    }

    showTrack(pc, event) {
      this.ui.video.srcObject = event.streams[0] || new MediaStream([event.track]);
      const count = () => {
        if (this.pc !== pc) return;
        this.stats.framesDecoded += 1;
        if (this.stats.framesDecoded === 1) {
          // The picture is here: no "connected" over a black box before it.
          if (this.ui.videoNote) this.ui.videoNote.textContent = "";
          if (this.connState === "connected") this.setState("connected");
        }
        this.lastFrameAt = performance.now();
        this.ui.video.requestVideoFrameCallback(count);
      };
      if (this.ui.video.requestVideoFrameCallback) this.ui.video.requestVideoFrameCallback(count);
    }

    // The picture stopped moving (or moves again): motions stop while it is frozen,
    // since the user would steer blind. A key or button still held waits (its key-up
    // forgets it) and drives once the picture moves: the browser repeats no press for
    // a held key, so the user would otherwise have to let go and press again.
    setVideoFrozen(frozen) {
      this.videoFrozen = frozen;
      this.root.classList.toggle("video-frozen", frozen);
      if (frozen) {
        const waiting = [...this.held.keys()].filter(
          (n) => (this.commands.get(n) || {}).motion && !this.stickHeld.has(n));
        this.releaseAll(true);
        for (const name of waiting) this.keyPaused.add(name);
        this.showBanner("The video is frozen: driving is paused until the picture moves again. Stop, land and return home still work.", "warn");
      } else {
        const waiting = [...this.keyPaused];
        this.keyPaused.clear();
        for (const name of waiting) this.press(name);
        this.showBanner("The video moves again: you can drive.", "info");
        setTimeout(() => { if (!this.videoFrozen) this.hideBanner(); }, 2000);
      }
    }

    // --- WebRTC: control and video on one connection ---------------------------------
    async startRtc() {
      this.closeVideo();
      const pc = new RTCPeerConnection({ iceServers: this.task.ice_servers || [] });
      this.pc = pc;
      const control = pc.createDataChannel("control");
      const channels = {
        control,
        input: pc.createDataChannel("input", { ordered: false, maxRetransmits: 0 }),
        urgent: pc.createDataChannel("urgent", { ordered: false }),
      };
      control.onopen = () => {
        if (this.pc === pc) this.channels = channels;
      };
      control.onmessage = (event) => {
        let msg;
        try { msg = JSON.parse(event.data); } catch (e) { return; }
        this.handle(msg);
      };
      control.onclose = () => {
        if (this.channels !== channels) return;
        this.channels = null;
        if (this.pc === pc) this.rtcFailed("the connection closed");
      };
      if (this.vehicle && this.vehicle.video && this.ui.video) {
        pc.addTransceiver("video", { direction: "recvonly" });
        pc.ontrack = (event) => this.showTrack(pc, event);
        if (this.ui.videoNote) this.ui.videoNote.textContent = "Starting video…";
      }
      pc.onconnectionstatechange = () => {
        if (this.pc === pc && pc.connectionState === "failed") this.rtcFailed("could not reach the vehicle");
      };
      try {
        await pc.setLocalDescription(await pc.createOffer());
        await iceGathered(pc, 3000);
      } catch (e) {
        this.rtcFailed(String(e));
        return;
      }
      if (this.pc !== pc) return;
      this.sendSignal({ type: "webrtc_offer", sdp: pc.localDescription.sdp });
      setTimeout(() => {
        if (this.pc === pc && !this.channels) this.rtcFailed("no connection within 10 s");
      }, RTC_CONNECT_MS);
    }

    async onAnswer(msg) {
      if (!this.pc) return;
      try {
        await this.pc.setRemoteDescription({ type: "answer", sdp: msg.sdp });
      } catch (e) {
        this.rtcFailed(String(e));
      }
    }

    // WebRTC did not work (or stopped): control stays on the socket, and the page
    // tries again later.
    rtcFailed(why) {
      if (!this.pc && !this.channels) return;
      this.closeVideo();
      if (this.over) return;
      if (!this.ws) {
        // The socket went earlier and the WebRTC connection was the last path.
        this.role = "pending";
        this.releaseAll(false);
        this.setPath(null);
        this.setState("disconnected");
        this.showBanner("Connection to the vehicle lost. Reconnecting…", "warn");
        this.reconnect();
        return;
      }
      this.toast(`No direct connection (${why}): control goes ${this.direct ? "to the vehicle's socket" : "through the platform"}.`, "warn");
      if (this.ui.videoNote && this.vehicle && this.vehicle.video) this.ui.videoNote.textContent = "No video: the vehicle could not be reached directly.";
      clearTimeout(this.rtcRetry);
      this.rtcRetry = setTimeout(() => {
        if (!this.over && this.ws && !this.pc && this.wantsRtc()) this.startRtc();
      }, RTC_RETRY_MS);
    }

    setPath(path) {
      this.path = path;
      if (this.ui.path) {
        this.ui.path.textContent = path ? PATH_WORDS[path] || path : "–";
        this.ui.path.dataset.path = path || "";
      }
    }

    // The vehicle's camera changed what it sends (its bitrate follows the pilot's link,
    // and with it the picture's size and frame rate).
    onVideoStatus(msg) {
      this.videoStatus = { width: msg.width, height: msg.height, fps: msg.fps, bitrate: msg.bitrate };
      this.showVideoStats();
    }

    // What this browser receives, from its own statistics (once a second).
    async readVideoStats() {
      const pc = this.pc;
      if (!pc || !pc.getStats) return;
      let report;
      try { report = await pc.getStats(); } catch (e) { return; }
      report.forEach((s) => {
        if (s.type !== "inbound-rtp" || s.kind !== "video") return;
        const last = this.lastInbound;
        const kbps = last && s.timestamp > last.timestamp
          ? Math.round((8 * (s.bytesReceived - last.bytesReceived)) / (s.timestamp - last.timestamp))
          : null;
        this.lastInbound = { timestamp: s.timestamp, bytesReceived: s.bytesReceived };
        this.videoReceived = {
          width: s.frameWidth || 0, height: s.frameHeight || 0,
          fps: Math.round(s.framesPerSecond || 0), kbps,
        };
      });
      this.showVideoStats();
    }

    showVideoStats() {
      if (!this.ui.videoStats) return;
      const sent = this.videoStatus, got = this.videoReceived;
      const rate = (bps) => (bps >= 1e6 ? `${(bps / 1e6).toFixed(1)} Mbit/s` : `${Math.round(bps / 1e3)} kbit/s`);
      this.ui.videoStats.textContent = sent
        ? `${sent.width}×${sent.height}, ${sent.fps} fps, ${rate(sent.bitrate)}`
        : "–";
      this.ui.videoStats.title = got
        ? `Received: ${got.width}×${got.height}, ${got.fps} fps${got.kbps === null ? "" : `, ${rate(got.kbps * 1000)}`}`
        : "What the vehicle's camera sends now: it follows your link";
    }

    closeVideo() {
      if (this.pc) { this.pc.close(); this.pc = null; }
      this.lastInbound = null;
      this.videoReceived = null;
      this.channels = null;
      this.lastFrameAt = 0;
      this.videoFrozen = false;
      this.root.classList.remove("video-frozen");
    }

    // --- the session as the platform sees it ---------------------------------------------
    watchSession() {
      if (!this.options.feedUrl) return;
      const connect = () => {
        const feed = new WebSocket(this.options.feedUrl);
        feed.onmessage = (event) => {
          const msg = JSON.parse(event.data);
          if (msg.type === "event") this.logEvent(msg.event);
          const s = msg.session;
          const tag = this.root.querySelector("[data-session-state]");
          if (s && tag) { tag.textContent = s.state; tag.className = `tag state-${s.state}`; }
          if (s && s.consequence) {
            // What ending it would make the vehicles do now (they change in a mission);
            // the vehicle's own word, when it gave one, is the more current.
            const words = this.consequence || s.consequence;
            for (const form of document.querySelectorAll("form[data-confirm]")) form.dataset.consequence = words;
          }
          if (s && ["ended", "failed", "aborted"].includes(s.state)) this.endSession(s.reason);
        };
        feed.onclose = () => { if (!this.over) setTimeout(connect, 2000); };
        this.feed = feed;
      };
      connect();
    }

    logEvent(event) {
      if (!this.ui.log) return;
      // The platform says each event in words (services.eventwords); in order, the
      // newest last: the log reads as the story of the session.
      const text = event.text || event.kind.replace(/_/g, " ");
      this.ui.log.append(el("li", {}, el("time", { class: "muted", dateTime: event.at }, window.IoUV.clock(event.at)),
        " ", text));
    }

    endSession(reason) {
      if (this.over) return;
      this.over = true;
      // The header no longer says "active" (a spectator has no session feed to say so).
      const tag = this.root.querySelector("[data-session-state]");
      if (tag && !["ended", "failed", "aborted"].includes(tag.textContent)) {
        tag.textContent = "over";
        tag.className = "tag state-ended";
      }
      this.releaseAll(false);
      // A page with a status banner of its own (a rescue's mission) says it there: one
      // banner, not two saying the same.
      if (this.root.querySelector("[data-mission-status]")) {
        if (this.ui.banner) this.ui.banner.hidden = true;
      } else {
        this.showBanner(`Session over: ${reason || "ended"}.`, "info");
      }
      this.setState("ended");
      this.root.classList.add("over");
      if (this.ws) this.ws.close(1000, "session over");
      this.closeVideo();
      if (this.sfuWatch) { this.sfuWatch.close(); this.sfuWatch = null; }
      // Take away what no longer applies: nothing to end, steer or take over, no live
      // picture; the telemetry stays, marked as the last values received.
      for (const form of document.querySelectorAll("form[data-confirm]")) form.remove();
      const take = this.root.querySelector("[data-take-control]");
      if (take) take.hidden = true;
      if (this.ui.role) this.ui.role.textContent = "–";
      if (this.ui.video) this.ui.video.srcObject = null;
      if (this.ui.videoNote) this.ui.videoNote.textContent = "The session is over: no live video.";
      if (this.ui.telemetry) {
        this.ui.telemetry.classList.add("stale");
        this.ui.telemetry.dataset.stale = "true";
        this.ui.telemetry.title = "The last values received before the session ended";
      }
      for (const [id, text] of [["rtt", "–"], ["interval", "–"]]) {
        if (this.ui[id]) this.ui[id].textContent = text;
      }
    }

    // --- UI helpers ------------------------------------------------------------------
    setState(state) {
      this.connState = state;
      if (this.ui.state) {
        // Connected but no picture yet: say so rather than "connected" over a black
        // video (the first frames can take seconds).
        const waiting = state === "connected" && this.vehicle && this.vehicle.video && !this.stats.framesDecoded;
        this.ui.state.textContent = waiting ? "connected, waiting for the picture" : state;
        this.ui.state.dataset.connState = state;
      }
    }

    // ``topic`` says what the banner is about, so that the news that ends it (back
    // inside a limit, the link back) takes it away and no other one.
    showBanner(text, kind, topic) {
      this.bannerTopic = topic || null;
      const b = this.ui.banner;
      if (!b) return;
      b.textContent = text;
      b.className = `banner banner-${kind}`;
      b.hidden = false;
    }

    hideBanner() {
      if (this.ui.banner && !this.over) this.ui.banner.hidden = true;
    }

    toast(text, kind) {
      const t = this.ui.toast;
      if (!t) return;
      t.textContent = text;
      t.className = `toast toast-${kind}`;
      t.hidden = false;
      clearTimeout(this.toastTimer);
      this.toastTimer = setTimeout(() => { t.hidden = true; }, 3500);
    }
  }

  window.IoUV = Object.assign(window.IoUV || {}, { Controller });

  // An open session whose workflow has not assigned a vehicle yet (an autonomous kind
  // finds one after the request): the session's feed says when its log moves (a
  // vehicle reserved, a task sent, the session over), and only then is the platform
  // asked for a grant, so the page needs no reload and does not ask every few seconds
  // for what is not there (each "not yet" a 409 in the platform's log). A slow ask
  // now and then covers a feed that cannot connect. Resolves null once the session
  // is over.
  const SLOW_ASK_MS = 30000;
  function awaitTask(root) {
    return new Promise((resolve) => {
      let done = false;
      let asking = false;
      let feed = null;
      let slow = null;
      const finish = (task) => {
        if (done) return;
        done = true;
        clearTimeout(slow);
        if (feed) { feed.onclose = null; feed.close(); }
        resolve(task);
      };
      const ask = async () => {
        if (done || asking) return;
        asking = true;
        try {
          const { ok, body } = await grantFetch(root.dataset.grantUrl);
          if (ok) finish(body);
          else if (!body.error || body.error.code !== "no_vehicle_yet") finish(null);
        } catch (e) {
          // The platform is unreachable for now: the feed or the slow ask tries again.
        } finally {
          asking = false;
        }
      };
      const slowly = () => {
        clearTimeout(slow);
        slow = setTimeout(() => { ask(); slowly(); }, SLOW_ASK_MS);
      };
      const connect = () => {
        if (done || !root.dataset.feedUrl) return;
        feed = new WebSocket(root.dataset.feedUrl);
        feed.onmessage = (event) => {
          const msg = JSON.parse(event.data);
          const s = msg.session || {};
          if (["ended", "failed", "aborted"].includes(s.state)) return finish(null);
          // A vehicle now holds a role in it (on connecting: maybe since the page was
          // made), or its log moved on: time to ask.
          if ((s.vehicles || []).length && (msg.type === "session" || msg.type === "event")) ask();
        };
        feed.onclose = () => { if (!done) setTimeout(connect, 2000); };
      };
      connect();
      slowly();
    });
  }

  document.addEventListener("DOMContentLoaded", async () => {
    const root = document.getElementById("controller");
    const data = document.getElementById("user-task");
    if (!root || !data) return;
    let task = JSON.parse(data.textContent);
    if (!task && root.dataset.awaitVehicle === "true") {
      task = await awaitTask(root);
      if (!task) {
        const note = root.querySelector("[data-video-note]");
        if (note) note.textContent = "No live video.";
        return;
      }
    }
    if (!task) return;
    new Controller(root, task, {
      grantUrl: root.dataset.grantUrl,
      feedUrl: root.dataset.feedUrl,
      watching: root.dataset.watching === "true",
    }).start();
  });
})();
