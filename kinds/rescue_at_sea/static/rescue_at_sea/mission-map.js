/*
 * The mission map (Leaflet, served from static/, no tile server needed).
 *
 * Two pages use it:
 *   - the rescue request ("draw"): clicks add the corners of the search area, which
 *     goes into the form's hidden "area" field as [[lat, lon], ...];
 *   - the mission page ("live"): the area, the planned path (searched part in green),
 *     the vehicles where they are now, the stations and the person once found, kept
 *     current by polling the mission's JSON every second.
 *
 * The map itself, the land and sea (or tiles), the station markers and the placing of
 * labels so that none overlaps another come from static/js/map-base.js.
 */
(function () {
  "use strict";

  const COLORS = {
    area: "#2f81f7",
    path: "#9fb3c8",
    done: "#3fb950",
    person: "#f85149",
    search: "#d29922",
    delivery: "#a371f7",
    station: "#e6edf3",
  };

  const { makeMap, labels, stationMarkers, reachAreas, requestView, escapeHtml, jsonScript } = window.IoUVMap;

  /* Approximate area of a polygon in m² (equirectangular, fine for a few km). */
  function areaM2(points) {
    if (points.length < 3) return 0;
    const lat0 = (points[0][0] * Math.PI) / 180;
    const R = 6371008.8;
    const xy = points.map(([lat, lon]) => [
      ((lon - points[0][1]) * Math.PI / 180) * R * Math.cos(lat0),
      ((lat - points[0][0]) * Math.PI / 180) * R,
    ]);
    let sum = 0;
    for (let i = 0; i < xy.length; i++) {
      const [x0, y0] = xy[i];
      const [x1, y1] = xy[(i + 1) % xy.length];
      sum += x0 * y1 - x1 * y0;
    }
    return Math.abs(sum) / 2;
  }

  // --- the request page: draw the area ----------------------------------------------
  function drawPage(node) {
    const config = jsonScript("map-config") || {};
    const map = makeMap(node, config.tiles);
    const stations = config.stations || [];
    // Opens on the station of the search drones, with the sea 1.2 km around it in view
    // (the demo's castaway is 900 m off the beach), and how far they reach.
    requestView(map, config, 1200);
    reachAreas(map, config.reach);
    stationMarkers(map, stations);
    const field = document.querySelector("input[name=area]");
    const info = document.querySelector("[data-area-info]");
    let points = [];
    try {
      const previous = JSON.parse(field.value || "[]");
      if (Array.isArray(previous)) points = previous;
    } catch (e) {
      points = [];
    }
    const polygon = L.polygon([], { color: COLORS.area, weight: 2, fillOpacity: 0.2, className: "area-polygon" }).addTo(map);
    const corners = L.layerGroup().addTo(map);

    function update() {
      polygon.setLatLngs(points);
      corners.clearLayers();
      points.forEach((p) => L.circleMarker(p, { radius: 4, color: COLORS.area, className: "area-corner" }).addTo(corners));
      field.value = points.length ? JSON.stringify(points) : "";
      if (points.length < 3) {
        info.textContent = points.length ? `${points.length} point(s): add at least ${3 - points.length} more.` : "No area yet.";
      } else {
        const km2 = areaM2(points) / 1e6;
        info.textContent = `${points.length} points · ${km2 < 0.1 ? Math.round(km2 * 1e6) + " m²" : km2.toFixed(2) + " km²"}`;
      }
    }
    map.on("click", (e) => {
      points.push([Number(e.latlng.lat.toFixed(7)), Number(e.latlng.lng.toFixed(7))]);
      update();
    });
    document.querySelector("[data-undo]").addEventListener("click", () => { points.pop(); update(); });
    document.querySelector("[data-clear]").addEventListener("click", () => { points = []; update(); });
    update();
    window.iouvMap = { map, points: () => points };
  }

  // --- the mission page: watch it live --------------------------------------------------
  function livePage(node) {
    const tiles = jsonScript("map-tiles");
    let mission = jsonScript("mission-data");
    const map = makeMap(node, tiles);
    // The view first: Leaflet cannot draw a path on a map without one.
    map.fitBounds(L.latLngBounds(mission.area).pad(0.6));
    const area = L.polygon(mission.area, {
      color: COLORS.area, weight: 2, fillOpacity: 0.12, className: "area-polygon",
    }).addTo(map);
    const path = L.polyline(mission.path, {
      color: COLORS.path, weight: 2, dashArray: "4 6", className: "mission-path",
    }).addTo(map);
    // Added once there is progress: Leaflet cannot clip an empty polyline.
    const done = L.polyline(mission.path.slice(0, 1), { color: COLORS.done, weight: 4, className: "mission-done" });
    const stations = new Map();
    const vehicles = new Map();
    let detection = null;
    let fitted = false;
    const url = node.dataset.missionUrl;

    function render() {
      path.setLatLngs(mission.path);
      if (mission.progress >= 0) {
        done.setLatLngs(mission.path.slice(0, mission.progress + 1));
        if (!map.hasLayer(done)) done.addTo(map);
      } else if (map.hasLayer(done)) {
        map.removeLayer(done);
      }
      for (const v of mission.vehicles) {
        const key = v.station.name;
        if (!stations.has(key)) {
          stations.set(key, true);
          stationMarkers(map, [v.station]);
        }
        if (v.lat == null || v.lon == null) continue;
        let entry = vehicles.get(v.id);
        const color = COLORS[v.role] || COLORS.station;
        if (!entry) {
          entry = {
            dot: L.circleMarker([v.lat, v.lon], {
              radius: 8, color, weight: 3, fillColor: color, fillOpacity: 0.8,
              className: `vehicle-marker vehicle-${v.role}`,
            }).addTo(map),
            tag: labels(map).add([v.lat, v.lon], escapeHtml(v.name), { group: "vehicle" }),
          };
          vehicles.set(v.id, entry);
        }
        entry.dot.setLatLng([v.lat, v.lon]);
        entry.tag.setLatLng([v.lat, v.lon]);
        entry.dot.getElement()?.setAttribute("data-vehicle", v.name);
        entry.dot.getElement()?.setAttribute("data-latlon", `${v.lat.toFixed(6)},${v.lon.toFixed(6)}`);
      }
      if (mission.detection && !detection) {
        const d = mission.detection;
        detection = L.circleMarker([d.lat, d.lon], {
          radius: 11, color: COLORS.person, weight: 3, fillColor: COLORS.person, fillOpacity: 0.5,
          className: "detection-marker",
        }).addTo(map);
        labels(map).add(
          [d.lat, d.lon],
          escapeHtml(
            `Person · ${d.lat.toFixed(5)}, ${d.lon.toFixed(5)}` +
              (d.confidence != null ? ` · confidence ${d.confidence.toFixed(2)}` : ""),
          ),
          { group: "alert", radius: 11, className: "map-label detection-label" },
        );
      }
      if (!fitted && vehicles.size) {
        // Once the vehicles show, frame them with the area.
        const b = area.getBounds();
        const bounds = L.latLngBounds(b.getSouthWest(), b.getNorthEast());
        for (const e of vehicles.values()) bounds.extend(e.dot.getLatLng());
        map.fitBounds(bounds.pad(0.15));
        fitted = true;
      }
      panel();
    }

    function panel() {
      const set = (sel, text) => {
        const el = document.querySelector(sel);
        if (el) el.textContent = text;
      };
      set("[data-mission-status]", mission.status || mission.state_label);
      set("[data-mission-state]", mission.state_label);
      const tag = document.querySelector("[data-session-state]");
      if (tag && tag.textContent !== mission.session.state) {
        tag.textContent = mission.session.state;
        tag.className = `tag state-${mission.session.state}`;
      }
      const phase = mission.phase || {};
      const detail = phase.detail ? ` — ${phase.detail}` : "";
      set("[data-mission-progress]", phase.label ? `${phase.label.charAt(0).toUpperCase()}${phase.label.slice(1)}${detail}` : "–");
      set("[data-mission-eta]", phase.eta_s != null ? `about ${duration(phase.eta_s)} (${window.IoUV.clock(new Date(Date.now() + phase.eta_s * 1000)).slice(0, 5)})` : "–");
      const d = mission.detection;
      set(
        "[data-mission-detection]",
        d ? `${d.lat.toFixed(5)}, ${d.lon.toFixed(5)}${d.confidence != null ? ` (confidence ${d.confidence.toFixed(2)})` : ""}${mission.released ? " · life jacket delivered" : ""}` : "not found yet",
      );
      const list = document.querySelector("[data-mission-vehicles]");
      if (list) {
        list.replaceChildren(
          ...mission.vehicles.map((v) => {
            const li = document.createElement("li");
            const battery = v.battery != null ? ` · ${Math.round(v.battery)}%` : "";
            const alt = v.alt != null ? ` · ${v.alt.toFixed(0)} m` : "";
            li.textContent = `${v.name} (${v.role}${v.active ? "" : ", released"}) · ${v.doing || v.status}${alt}${battery}`;
            return li;
          }),
        );
      }
      const timeline = document.querySelector("[data-mission-timeline]");
      if (timeline) {
        timeline.replaceChildren(
          ...mission.timeline.map((e) => {
            const li = document.createElement("li");
            const at = window.IoUV.clock(e.at);
            li.innerHTML = `<span class="muted">${escapeHtml(at)}</span> ${escapeHtml(describe(e))}`;
            li.dataset.kind = e.kind;
            return li;
          }),
        );
      }
      node.dataset.missionState = mission.state;
    }

    function duration(seconds) {
      if (seconds < 60) return `${Math.max(1, Math.round(seconds / 5) * 5)} s`;
      const minutes = Math.round(seconds / 60);
      return minutes < 60 ? `${minutes} min` : `${Math.floor(minutes / 60)} h ${minutes % 60} min`;
    }

    function describe(e) {
      const d = e.data || {};
      switch (e.kind) {
        case "requested": return "rescue requested";
        case "mission_planned": return `search planned: ${d.lines} lines ${d.spacing_m} m apart, ${d.path_m} m of path at ${d.altitude_m} m`;
        case "assigned": return `${d.vehicle_name} assigned (${d.role})`;
        case "search_leg": return d.start_index ? `${d.vehicle_name} continues from waypoint ${d.start_index + 1}` : `${d.vehicle_name} starts the search`;
        case "mission_state": return d.text || d.to;
        case "person_detected": return `person detected at ${Number(d.lat).toFixed(5)}, ${Number(d.lon).toFixed(5)}`;
        case "notice_sent": {
          // Which notice: the monitors hear of a wait and of the person found, the team
          // of the person found by e-mail and webhook; each line says which.
          const who = d.channel === "dashboard" ? "monitors alerted" : `rescue team told by ${d.channel === "email" ? "e-mail" : d.channel}`;
          const what = String(d.message || d.topic || "").split("\n")[0].replace(/_/g, " ");
          return what ? `${who}: ${what}` : who;
        }
        case "native_mission_refused": return `the autopilot refused the mission (${d.reason}): the agent flies it step by step`;
        case "native_mission_started": return d.adopted ? "the agent is back and follows the mission the autopilot flies" : "the autopilot flies the mission itself: it finishes, or comes home, even without its agent";
        case "payload_released": return "life jacket released";
        case "vehicle_released": return `${d.vehicle_name} released: ${d.reason}`;
        case "state": return `session ${d.to}${d.reason ? ": " + d.reason : ""}`;
        default: return e.kind.replaceAll("_", " ");
      }
    }

    let misses = 0;
    let afterFinal = 0;
    async function poll() {
      try {
        const response = await fetch(url, { headers: { Accept: "application/json" }, credentials: "same-origin" });
        if (!response.ok) throw new Error(String(response.status));
        mission = await response.json();
        misses = 0;
        render();
      } catch (e) {
        misses += 1;
        if (misses === 5) set_status("Lost contact with the platform; retrying…");
      }
      // Keep watching a little after the end: the vehicles are still flying home.
      if (mission.final) afterFinal += 1;
      if (afterFinal < 30) setTimeout(poll, 1000);
    }
    function set_status(text) {
      const el = document.querySelector("[data-mission-status]");
      if (el) el.textContent = text;
    }
    render();
    setTimeout(poll, 1000);
    window.iouvMap = { map, vehicles, mission: () => mission };
  }

  for (const node of document.querySelectorAll("[data-map-mode]")) {
    if (node.dataset.mapMode === "draw") drawPage(node);
    else livePage(node);
  }
})();
