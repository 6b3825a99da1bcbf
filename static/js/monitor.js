/* IoUV monitor dashboard: the live fleet (/ws/fleet/) and live sessions (/ws/sessions/),
 * with a stop button per session for monitors allowed to stop one. */
(function () {
  "use strict";
  const root = document.getElementById("monitor");
  if (!root) return;
  const canStop = root.dataset.canStop === "true";
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const vehicles = new Map();
  const sessions = new Map();
  const FINAL = ["ended", "failed", "aborted"];

  function cell(text, cls) {
    const td = document.createElement("td");
    td.textContent = text;
    if (cls) td.className = cls;
    return td;
  }

  function renderFleet() {
    const body = root.querySelector("[data-fleet] tbody");
    body.textContent = "";
    for (const v of [...vehicles.values()].sort((a, b) => a.name.localeCompare(b.name))) {
      const tr = document.createElement("tr");
      tr.dataset.vehicle = v.name;
      tr.append(
        cell(v.name), cell(v.type), cell(v.station),
        cell(v.status.replace("_", " "), `status-${v.status}`),
        cell(v.battery === null ? "–" : `${v.battery.toFixed(0)} %`),
        cell(v.position ? `${v.position.lat.toFixed(5)}, ${v.position.lon.toFixed(5)}` : "–"),
        cell(v.last_seen ? window.IoUV.clock(v.last_seen) : "never"),
      );
      body.append(tr);
    }
  }

  function renderSessions() {
    renderEnded();
    const body = root.querySelector("[data-sessions] tbody");
    body.textContent = "";
    const live = [...sessions.values()].filter((s) => !FINAL.includes(s.state));
    root.querySelector("[data-no-sessions]").hidden = live.length > 0;
    for (const s of live) {
      const tr = document.createElement("tr");
      tr.dataset.session = s.id;
      tr.append(
        cell(s.service_name), cell(s.user),
        cell(s.vehicles.map((v) => v.name).join(", ") || "–"),
        cell(s.state, `state-${s.state}`),
        cell(s.lastEvent || ""),
      );
      const actions = document.createElement("td");
      if (canStop) {
        const stop = document.createElement("button");
        stop.className = "danger";
        stop.textContent = "Stop";
        stop.dataset.stop = s.id;
        stop.addEventListener("click", () => stopSession(s.id, stop));
        actions.append(stop);
      }
      tr.append(actions);
      body.append(tr);
    }
  }

  /* Sessions that ended while this page was open, with whether the platform's last
   * word (a stop, the end) has reached each vehicle, or the vehicle is offline and its
   * own fail-safe holds. */
  function renderEnded() {
    const box = root.querySelector("[data-ended]");
    const list = box.querySelector("ul");
    list.textContent = "";
    const ended = [...sessions.values()].filter(
      (s) => FINAL.includes(s.state) && (s.delivery || []).length,
    );
    box.hidden = ended.length === 0;
    for (const s of ended) {
      const item = document.createElement("li");
      item.dataset.endedSession = s.id;
      const head = document.createElement("strong");
      head.textContent = `${s.service_name} (${s.user}): ${s.reason}`;
      item.append(head);
      for (const d of s.delivery) {
        const line = document.createElement("div");
        line.className = `delivery delivery-${d.state}`;
        line.dataset.delivery = d.state;
        const at = d.at ? ` at ${window.IoUV.clock(d.at)}` : "";
        line.textContent = `${d.text}${at}`;
        item.append(line);
      }
      list.append(item);
    }
  }

  async function stopSession(id, button) {
    const s = sessions.get(id) || {};
    const consequence = s.consequence || "Its vehicles perform their fail-safe.";
    if (!window.confirm(`Stop ${s.user || "this user"}'s session? ${consequence} The user loses control.`)) return;
    button.disabled = true;
    const token = root.parentElement.querySelector("[name=csrfmiddlewaretoken]").value;
    const response = await fetch(`/sessions/${id}/stop`, {
      method: "POST", headers: { "X-CSRFToken": token, Accept: "application/json" },
      credentials: "same-origin",
    });
    if (!response.ok) { button.disabled = false; return; }
    const body = await response.json();
    if (body.session) { sessions.set(body.session.id, body.session); renderSessions(); }
  }

  function feed(path, onMessage) {
    const ws = new WebSocket(`${scheme}://${location.host}${path}`);
    ws.onmessage = (event) => onMessage(JSON.parse(event.data));
    ws.onopen = () => { root.querySelector("[data-conn-state]").textContent = "live"; };
    ws.onclose = () => {
      root.querySelector("[data-conn-state]").textContent = "reconnecting";
      setTimeout(() => feed(path, onMessage), 2000);
    };
  }

  /* Notices for the monitors' dashboard (any kind of service may send them: a person
   * found at sea, a mission that waits for a vehicle) become alerts. */
  function alert(session, event) {
    const data = event.data || {};
    if (event.kind !== "notice_sent" || data.channel !== "dashboard") return;
    const box = root.querySelector("[data-alerts]");
    const item = document.createElement("li");
    item.className = data.level === "bad" ? "alert-bad" : "alert-warn";
    item.dataset.kind = event.kind;
    item.dataset.topic = data.topic || "";
    const where = Number.isFinite(data.lat) && Number.isFinite(data.lon)
      ? ` (${Number(data.lat).toFixed(5)}, ${Number(data.lon).toFixed(5)})` : "";
    item.textContent = `${window.IoUV.clock(event.at || new Date())} · ${data.message || data.topic}${where}`;
    box.prepend(item);
    box.hidden = false;
  }

  feed("/ws/fleet/", (msg) => {
    if (msg.type !== "fleet") return;
    if (msg.full) vehicles.clear();
    for (const v of msg.vehicles) vehicles.set(v.id, v);
    renderFleet();
  });
  feed("/ws/sessions/", (msg) => {
    if (msg.type === "sessions") {
      sessions.clear();
      for (const s of msg.sessions) sessions.set(s.id, s);
    } else if (msg.type === "event" && msg.session) {
      const kind = msg.event.kind.replace(/_/g, " ");
      sessions.set(msg.session.id, { ...msg.session, lastEvent: kind });
      alert(msg.session, msg.event);
    }
    renderSessions();
  });
})();
