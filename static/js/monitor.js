/* IoUV monitor dashboard: the live fleet (/ws/fleet/) as a table and on a map, and live
 * sessions (/ws/sessions/), with a stop button per session for monitors allowed to stop
 * one. */
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

  /* The fleet map: the stations, and every vehicle with a position where it last
   * reported it, coloured and labelled by its status (map-base.js places the labels so
   * that none hides another). Offline vehicles stay, greyed, at their last position. */
  const STATUS_COLORS = {
    idle: "#2ecc71", reserved: "#2f9bff", in_service: "#2f9bff", releasing: "#f5a623",
    returning: "#f5a623", maintenance: "#f5a623", failsafe: "#ff5d5d", offline: "#6e7681",
  };
  function fleetMap() {
    const node = root.querySelector("[data-fleet-map]");
    if (!node || !window.IoUVMap || !window.L) return null;
    const { makeMap, labels, stationMarkers, escapeHtml, jsonScript } = window.IoUVMap;
    const config = jsonScript("map-config") || {};
    const stations = config.stations || [];
    const map = makeMap(node, config.tiles);
    if (stations.length) {
      map.fitBounds(L.latLngBounds(stations.map((s) => [s.lat, s.lon])).pad(0.3), { maxZoom: 15 });
    } else {
      map.setView([0, 0], 2);
    }
    stationMarkers(map, stations);
    const shown = new Map();
    let framed = false;

    function update(list) {
      const seen = new Set();
      for (const v of list) {
        if (!v.position) continue;
        seen.add(v.id);
        const at = [v.position.lat, v.position.lon];
        const color = STATUS_COLORS[v.status] || STATUS_COLORS.offline;
        const text = `${escapeHtml(v.name)} · ${escapeHtml(v.status.replace("_", " "))}`;
        let entry = shown.get(v.id);
        if (!entry) {
          entry = {
            dot: L.circleMarker(at, { radius: 7, weight: 2, className: "vehicle-marker" }).addTo(map),
            tag: labels(map).add(at, text, { group: "vehicle", radius: 7 }),
          };
          shown.set(v.id, entry);
        }
        entry.dot.setLatLng(at);
        entry.dot.setStyle({ color, fillColor: color, fillOpacity: v.status === "offline" ? 0.3 : 0.85 });
        entry.tag.setLatLng(at);
        entry.tag.setHtml(text);
        const tagClasses = entry.tag.element.classList;
        for (const c of [...tagClasses]) if (c.startsWith("status-")) tagClasses.remove(c);
        tagClasses.add(`status-${v.status}`);
        const el = entry.dot.getElement();
        if (el) {
          // Not data-vehicle: that names the vehicle's row in the fleet table.
          el.dataset.mapVehicle = v.name;
          el.dataset.status = v.status;
          el.dataset.latlon = `${at[0].toFixed(6)},${at[1].toFixed(6)}`;
        }
      }
      for (const [id, entry] of shown) {
        if (seen.has(id)) continue;
        entry.dot.remove();
        entry.tag.remove();
        shown.delete(id);
      }
      if (!framed && shown.size) {
        // Once, when the first positions arrive: the stations and every vehicle.
        const bounds = L.latLngBounds(stations.map((s) => [s.lat, s.lon]));
        for (const e of shown.values()) bounds.extend(e.dot.getLatLng());
        map.fitBounds(bounds.pad(0.3), { maxZoom: 15 });
        framed = true;
      }
    }
    window.iouvMap = { map, vehicles: shown };
    return { update };
  }
  const fleetOnMap = fleetMap();

  // How each session's controller reaches its vehicle, as its agent last said.
  const PATH_WORDS = {
    webrtc_direct: "WebRTC, direct",
    webrtc_turn: "WebRTC via TURN",
    relay: "relay",
    websocket: "vehicle's socket",
  };

  function renderSessions() {
    renderEnded();
    const body = root.querySelector("[data-sessions] tbody");
    body.textContent = "";
    const live = [...sessions.values()].filter((s) => !FINAL.includes(s.state));
    const none = root.querySelector("[data-no-sessions]");
    none.textContent = "No live session.";
    none.hidden = live.length > 0;
    for (const s of live) {
      const tr = document.createElement("tr");
      tr.dataset.session = s.id;
      tr.append(
        cell(s.service_name), cell(s.user),
        cell(s.vehicles.map((v) => v.name).join(", ") || "–"),
        cell(s.state, `state-${s.state}`),
        cell(PATH_WORDS[s.control_path] || "–", s.control_path ? `path-${s.control_path}` : ""),
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

  /* The page is live while every feed it opened is. */
  const open = new Map();
  function feed(path, onMessage) {
    const ws = new WebSocket(`${scheme}://${location.host}${path}`);
    const state = root.querySelector("[data-conn-state]");
    const show = () => {
      state.textContent = [...open.values()].every(Boolean) ? "live" : "reconnecting";
    };
    open.set(path, false);
    ws.onmessage = (event) => onMessage(JSON.parse(event.data));
    ws.onopen = () => { open.set(path, true); show(); };
    ws.onclose = () => {
      open.set(path, false);
      show();
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
    if (fleetOnMap) fleetOnMap.update([...vehicles.values()]);
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
