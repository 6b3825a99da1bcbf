/*
 * The parcel's map (static/js/map-base.js gives the map itself).
 *
 *   - the request page ("pick"): the first click sets the pickup, the second the
 *     drop-off, a third starts over; they go into the form's hidden fields;
 *   - the delivery page and the recipient's page ("live"): the pickup, the drop-off,
 *     where the parcel waits if its carrier had to give up, the vehicle where it is
 *     now, the phase and the arrival time, kept current by polling the state's JSON.
 */
(function () {
  "use strict";

  const {
    makeMap, labels, stationMarkers, reachAreas, requestView, escapeHtml, jsonScript, distanceM,
  } = window.IoUVMap;
  const COLORS = { pickup: "#d29922", dropoff: "#3fb950", carrier: "#a371f7", route: "#9fb3c8" };

  /* A point with its name; its label is placed with the map's others (map-base.js), so
   * it leaves the map with the point (removeFrom). */
  function pin(map, point, color, cls, text) {
    const dot = L.circleMarker(point, {
      radius: 9, color, weight: 3, fillColor: color, fillOpacity: 0.5, className: cls,
    }).addTo(map);
    const tag = labels(map).add(point, escapeHtml(text), { group: "pin", radius: 9 });
    return { removeFrom() { dot.remove(); tag.remove(); } };
  }

  // --- the request page: pick the two points ------------------------------------------
  function pickPage(node) {
    const config = jsonScript("map-config") || {};
    const map = makeMap(node, config.tiles);
    const stations = config.stations || [];
    // Opens on the carriers' station, and shows where a parcel can be picked up.
    requestView(map, config, 2000);
    reachAreas(map, config.reach);
    stationMarkers(map, stations);
    const fields = {
      pickup: document.querySelector("input[name=pickup]"),
      dropoff: document.querySelector("input[name=dropoff]"),
    };
    const info = document.querySelector("[data-pick-info]");
    const layer = L.layerGroup().addTo(map);
    let pins = [];
    let points = [];
    for (const name of ["pickup", "dropoff"]) {
      try {
        const p = JSON.parse(fields[name].value || "null");
        if (p) points.push(Array.isArray(p) ? p : [p.lat, p.lon]);
      } catch (e) { /* nothing picked yet */ }
    }

    function update() {
      layer.clearLayers();
      for (const p of pins) p.removeFrom();
      pins = [];
      if (points[0]) pins.push(pin(map, points[0], COLORS.pickup, "pickup-marker", "pickup"));
      if (points[1]) {
        pins.push(pin(map, points[1], COLORS.dropoff, "dropoff-marker", "drop-off"));
        L.polyline(points, { color: COLORS.route, weight: 2, dashArray: "4 6" }).addTo(layer);
      }
      fields.pickup.value = points[0] ? JSON.stringify(points[0]) : "";
      fields.dropoff.value = points[1] ? JSON.stringify(points[1]) : "";
      info.textContent = !points.length ? "No pickup yet."
        : points.length === 1 ? "Pickup set: now click the drop-off."
        : `${(distanceM(points[0], points[1]) / 1000).toFixed(2)} km from pickup to drop-off.`;
    }
    map.on("click", (e) => {
      const p = [Number(e.latlng.lat.toFixed(7)), Number(e.latlng.lng.toFixed(7))];
      points = points.length >= 2 ? [p] : [...points, p];
      update();
    });
    update();
    window.iouvMap = { map, points: () => points };
  }

  // --- the delivery page and the recipient's: watch it live ----------------------------
  function livePage(node) {
    let state = jsonScript("delivery-data");
    const map = makeMap(node, jsonScript("map-tiles"));
    map.fitBounds(L.latLngBounds([state.pickup, state.dropoff]).pad(0.5));
    pin(map, state.pickup, COLORS.pickup, "pickup-marker", "pickup");
    pin(map, state.dropoff, COLORS.dropoff, "dropoff-marker", "drop-off");
    L.polyline([state.pickup, state.dropoff], { color: COLORS.route, weight: 2, dashArray: "4 6" }).addTo(map);
    const vehicles = new Map();
    const stations = new Set();
    let waiting = null;
    const url = node.dataset.stateUrl;

    function render() {
      for (const v of state.vehicles) {
        if (!stations.has(v.station.name)) {
          stations.add(v.station.name);
          stationMarkers(map, [v.station]);
        }
        if (v.lat == null || v.lon == null) continue;
        let entry = vehicles.get(v.id);
        if (!entry) {
          entry = {
            dot: L.circleMarker([v.lat, v.lon], {
              radius: 8, color: COLORS.carrier, weight: 3, fillColor: COLORS.carrier,
              fillOpacity: 0.8, className: "vehicle-marker carrier-marker",
            }).addTo(map),
            tag: labels(map).add([v.lat, v.lon], escapeHtml(v.name), { group: "vehicle" }),
          };
          vehicles.set(v.id, entry);
        }
        entry.dot.setLatLng([v.lat, v.lon]);
        entry.tag.setLatLng([v.lat, v.lon]);
        entry.dot.setStyle({ opacity: v.active ? 1 : 0.4, fillOpacity: v.active ? 0.8 : 0.2 });
        entry.dot.getElement()?.setAttribute("data-vehicle", v.name);
      }
      if (state.waiting_at && !waiting) {
        waiting = pin(map, state.waiting_at, COLORS.pickup, "handover-marker", "parcel waits here");
      } else if (!state.waiting_at && waiting) {
        waiting.removeFrom();
        waiting = null;
      }
      panel();
    }

    function eta() {
      if (state.delivered) return "delivered";
      if (state.final) return "–";
      if (state.eta_s == null) return "waiting for a vehicle";
      // The portal's one time format (24-hour, static/js/clock.js), as every other page.
      const at = window.IoUV.clock(new Date(state.eta_at)).slice(0, 5);
      const min = Math.max(1, Math.round(state.eta_s / 60));
      return `in about ${min} min (${at})`;
    }

    function panel() {
      // Every element that shows the value, but never the map itself: it carries the
      // state as data-delivery-state too (for tests), and text written into it would
      // wipe the map out (the recipient's page, where the map comes first).
      const set = (sel, text) => {
        for (const el of document.querySelectorAll(`${sel}:not([data-map-mode])`)) el.textContent = text;
      };
      set("[data-delivery-status]", state.status || state.state_label);
      set("[data-delivery-state]", state.state_label);
      set("[data-eta]", eta());
      const tag = document.querySelector("[data-session-state]");
      if (tag && tag.textContent !== state.session.state) {
        tag.textContent = state.session.state;
        tag.className = `tag state-${state.session.state}`;
      }
      const cancel = document.querySelector("[data-cancel-form]");
      if (cancel && state.final) cancel.remove();
      else if (cancel && state.consequence) cancel.dataset.consequence = state.consequence;
      const list = document.querySelector("[data-delivery-vehicles]");
      if (list) {
        list.replaceChildren(...state.vehicles.map((v) => {
          const li = document.createElement("li");
          const battery = v.battery != null ? ` · ${Math.round(v.battery)}%` : "";
          li.textContent = `${v.name} (${v.kind}${v.active ? "" : ", released"}) · ${v.status.replace("_", " ")}${battery}`;
          return li;
        }));
      }
      const timeline = document.querySelector("[data-delivery-timeline]");
      if (timeline && state.timeline) {
        timeline.replaceChildren(...state.timeline.map((e) => {
          const li = document.createElement("li");
          li.dataset.kind = e.kind;
          li.innerHTML = `<span class="muted">${escapeHtml(window.IoUV.clock(e.at))}</span> ${escapeHtml(describe(e))}`;
          return li;
        }));
      }
      node.dataset.deliveryState = state.state;
    }

    function describe(e) {
      const d = e.data || {};
      switch (e.kind) {
        case "requested": return "delivery requested";
        case "delivery_planned": return `${(d.trip_m / 1000).toFixed(2)} km, ${d.weight_kg} kg${d.over_water ? ", over water" : ""}`;
        case "assigned": return `${d.vehicle_name} reserved`;
        case "delivery_state": return d.text || d.to;
        case "native_mission_refused": return `the autopilot refused the mission (${d.reason}): the agent flies it step by step`;
        case "native_mission_started": return d.adopted ? "the agent is back and follows the mission the autopilot flies" : "the autopilot flies the mission itself: it finishes, or comes home, even without its agent";
        case "parcel_loaded": return "parcel on board";
        case "payload_released": return "parcel released at the drop-off";
        case "notice_sent": return `recipient told (${d.channel})`;
        case "vehicle_released": return `${d.vehicle_name} released: ${d.reason}`;
        case "state": return `session ${d.to}${d.reason ? ": " + d.reason : ""}`;
        default: return e.kind.replaceAll("_", " ");
      }
    }

    let afterFinal = 0;
    async function poll() {
      try {
        const response = await fetch(url, { headers: { Accept: "application/json" }, credentials: "same-origin" });
        if (response.ok) {
          state = await response.json();
          render();
        }
      } catch (e) { /* the next poll tries again */ }
      // Keep watching a little after the end: the vehicle is still going home.
      if (state.final) afterFinal += 1;
      if (afterFinal < 30) setTimeout(poll, 1000);
    }
    render();
    setTimeout(poll, 1000);
    window.iouvMap = { map, vehicles, state: () => state };
  }

  for (const node of document.querySelectorAll("[data-map-mode]")) {
    if (node.dataset.mapMode === "pick") pickPage(node);
    else livePage(node);
  }
})();
