/*
 * The survey's map (static/js/map-base.js gives the map itself).
 *
 *   - the request page ("pick"): each click adds a corner of the area, in order around
 *     it (the last joins the first); "Undo" takes the last one back, "Start over" all;
 *     the corners go into the form's hidden field as [[lat, lon], ...];
 *   - the survey's page ("live"): the area, the planned photo lines, each photo's
 *     footprint as it reaches the platform (the coverage growing), the drone where it
 *     is, and the mosaic laid over the map once made; kept current by polling the
 *     state's JSON.
 */
(function () {
  "use strict";

  const { makeMap, labels, stationMarkers, reachAreas, requestView, escapeHtml, jsonScript } =
    window.IoUVMap;
  const COLORS = { area: "#d29922", line: "#9fb3c8", photo: "#3fb950", drone: "#a371f7" };

  /* The area of a polygon of [lat, lon] corners, in m² (flat, around its first corner). */
  function areaM2(points) {
    if (points.length < 3) return 0;
    const [lat0] = points[0];
    const k = Math.cos((lat0 * Math.PI) / 180);
    const xy = points.map(([lat, lon]) => [lon * k * 111320, lat * 110540]);
    let total = 0;
    for (let i = 0; i < xy.length; i++) {
      const [x1, y1] = xy[i];
      const [x2, y2] = xy[(i + 1) % xy.length];
      total += x1 * y2 - x2 * y1;
    }
    return Math.abs(total) / 2;
  }

  // --- the request page: draw the area -------------------------------------------------
  function pickPage(node) {
    const config = jsonScript("map-config") || {};
    const map = makeMap(node, config.tiles);
    requestView(map, config, 600);
    reachAreas(map, config.reach);
    stationMarkers(map, config.stations || []);
    const field = document.querySelector("input[name=polygon]");
    const info = document.querySelector("[data-pick-info]");
    const layer = L.layerGroup().addTo(map);
    let points = [];
    try {
      const given = JSON.parse(field.value || "null");
      if (Array.isArray(given)) points = given;
    } catch (e) { /* nothing drawn yet */ }

    function update() {
      layer.clearLayers();
      for (const p of points) {
        L.circleMarker(p, {
          radius: 5, color: COLORS.area, weight: 2, fillOpacity: 0.8, className: "corner-marker",
        }).addTo(layer);
      }
      if (points.length >= 3) {
        L.polygon(points, {
          color: COLORS.area, weight: 2, fillOpacity: 0.15, className: "survey-area",
        }).addTo(layer);
      } else if (points.length === 2) {
        L.polyline(points, { color: COLORS.area, weight: 2 }).addTo(layer);
      }
      field.value = points.length ? JSON.stringify(points) : "";
      info.textContent = !points.length ? "No corner yet."
        : points.length < 3 ? `${points.length} corner${points.length > 1 ? "s" : ""}: at least 3.`
        : `${points.length} corners, about ${Math.round(areaM2(points)).toLocaleString("en")} m².`;
    }
    map.on("click", (e) => {
      points = [...points, [Number(e.latlng.lat.toFixed(7)), Number(e.latlng.lng.toFixed(7))]];
      update();
    });
    document.querySelector("[data-undo]")?.addEventListener("click", () => {
      points = points.slice(0, -1);
      update();
    });
    document.querySelector("[data-clear]")?.addEventListener("click", () => {
      points = [];
      update();
    });
    update();
    window.iouvMap = { map, points: () => points };
  }

  // --- the survey's page: watch it live ------------------------------------------------
  function livePage(node) {
    let state = jsonScript("survey-data");
    const map = makeMap(node, jsonScript("map-tiles"));
    // The view first: Leaflet cannot draw a path on a map without one.
    map.fitBounds(L.latLngBounds(state.polygon).pad(0.3));
    L.polygon(state.polygon, {
      color: COLORS.area, weight: 2, fillOpacity: 0.05, className: "survey-area",
    }).addTo(map);
    const linesLayer = L.layerGroup().addTo(map);
    const photosLayer = L.layerGroup().addTo(map);
    const shown = new Set();
    const drones = new Map();
    const stations = new Set();
    let planned = false;
    let mosaic = null;
    const url = node.dataset.stateUrl;

    function render() {
      if (state.plan && !planned) {
        planned = true;
        for (const [start, end] of state.plan.lines) {
          L.polyline([start, end], {
            color: COLORS.line, weight: 1.5, dashArray: "4 4", className: "survey-line",
          }).addTo(linesLayer);
        }
      }
      for (const photo of state.photos) {
        if (shown.has(photo.name)) continue;
        shown.add(photo.name);
        L.polygon(photo.corners, {
          color: COLORS.photo, weight: 1, fillOpacity: 0.12, className: "photo-footprint",
        }).addTo(photosLayer);
      }
      if (state.mosaic && !mosaic) {
        const [south, west, north, east] = state.mosaic.bounds;
        mosaic = L.imageOverlay(state.mosaic.url, [[south, west], [north, east]], {
          className: "survey-mosaic", opacity: 1,
        }).addTo(map);
        mosaic.bringToFront();
        photosLayer.eachLayer((layer) => layer.setStyle({ fillOpacity: 0 }));
      }
      for (const v of state.vehicles) {
        if (!stations.has(v.station.name)) {
          stations.add(v.station.name);
          stationMarkers(map, [v.station]);
        }
        if (v.lat == null || v.lon == null) continue;
        let entry = drones.get(v.id);
        if (!entry) {
          entry = {
            dot: L.circleMarker([v.lat, v.lon], {
              radius: 8, color: COLORS.drone, weight: 3, fillColor: COLORS.drone,
              fillOpacity: 0.8, className: "vehicle-marker",
            }).addTo(map),
            tag: labels(map).add([v.lat, v.lon], escapeHtml(v.name), { group: "vehicle" }),
          };
          drones.set(v.id, entry);
        }
        entry.dot.setLatLng([v.lat, v.lon]);
        entry.tag.setLatLng([v.lat, v.lon]);
        entry.dot.setStyle({ opacity: v.active ? 1 : 0.4, fillOpacity: v.active ? 0.8 : 0.2 });
        entry.dot.getElement()?.setAttribute("data-vehicle", v.name);
      }
      panel();
    }

    function panel() {
      const set = (sel, text) => {
        for (const el of document.querySelectorAll(`${sel}:not([data-map-mode])`)) el.textContent = text;
      };
      set("[data-survey-status]", state.status || state.state_label);
      set("[data-survey-state]", state.state_label);
      set("[data-photo-count]", state.photo_count
        ? `${state.photos.length} of ${state.photo_count} received` : "not planned yet");
      set("[data-coverage]", state.coverage == null ? "–" : `${Math.round(state.coverage * 100)} %`);
      const link = document.querySelector("[data-mosaic]");
      if (link && state.mosaic && !link.querySelector("a")) {
        link.innerHTML = `<a href="${escapeHtml(state.mosaic.kmz)}" data-kmz download>KMZ for GIS</a>`
          + ` · <a href="${escapeHtml(state.mosaic.url)}" target="_blank" rel="noopener">picture</a>`;
      }
      const tag = document.querySelector("[data-session-state]");
      if (tag && tag.textContent !== state.session.state) {
        tag.textContent = state.session.state;
        tag.className = `tag state-${state.session.state}`;
      }
      const cancel = document.querySelector("[data-cancel-form]");
      if (cancel && (state.final || state.session.state === "ended")) cancel.remove();
      else if (cancel && state.consequence) cancel.dataset.consequence = state.consequence;
      const list = document.querySelector("[data-survey-vehicles]");
      if (list) {
        list.replaceChildren(...state.vehicles.map((v) => {
          const li = document.createElement("li");
          const battery = v.battery != null ? ` · ${Math.round(v.battery)}%` : "";
          li.textContent = `${v.name}${v.active ? "" : " (released)"} · ${v.status.replace("_", " ")}${battery}`;
          return li;
        }));
      }
      const timeline = document.querySelector("[data-survey-timeline]");
      if (timeline && state.timeline) {
        timeline.replaceChildren(...state.timeline.map((e) => {
          const li = document.createElement("li");
          li.dataset.kind = e.kind;
          li.innerHTML = `<span class="muted">${escapeHtml(window.IoUV.clock(e.at))}</span> ${escapeHtml(describe(e))}`;
          return li;
        }));
      }
      node.dataset.surveyState = state.state;
      node.dataset.photos = String(state.photos.length);
    }

    function describe(e) {
      const d = e.data || {};
      switch (e.kind) {
        case "requested": return "survey requested";
        case "survey_planned": return `${Math.round(d.area_m2).toLocaleString("en")} m² at ${d.gsd_cm} cm a pixel`;
        case "assigned": return `${d.vehicle_name} reserved`;
        case "survey_state": return d.text || d.to;
        case "survey_flown": {
          const missed = (d.missed || []).length;
          return `the lines flown: ${d.taken} photos taken${missed ? `, ${missed} missed` : ""}`;
        }
        case "native_mission_refused": return `the autopilot refused the lines (${d.reason}): the agent flies them place to place`;
        case "native_mission_started": return d.adopted ? "the agent is back and follows the lines the autopilot flies" : "the autopilot flies the lines itself: it finishes, or comes home, even without its agent";
        case "photo_missed": return `photo ${d.index + 1} missed: ${d.why}`;
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
      // Keep watching a little after the end: the drone is still going home.
      if (state.final) afterFinal += 1;
      if (afterFinal < 30) setTimeout(poll, 1000);
    }
    render();
    setTimeout(poll, 1000);
    window.iouvMap = { map, state: () => state, mosaic: () => mosaic };
  }

  for (const node of document.querySelectorAll("[data-map-mode]")) {
    if (node.dataset.mapMode === "pick") pickPage(node);
    else livePage(node);
  }
})();
