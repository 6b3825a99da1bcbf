/*
 * The portal's map basics (Leaflet, vendored in static/vendor): what every map page
 * of every service kind shares. Exposes window.IoUVMap:
 *
 *   makeMap(node, tiles)       a map with the configured XYZ tiles; without them (the
 *                              portal works on a closed network) the packaged land mask
 *                              (/map/land.geo.json): sea and land inside its regions,
 *                              a lat/lon grid over the unknown elsewhere; and a scale
 *   labels(map)                the map's labels, placed so that no two overlap:
 *                              add(latlng, html, options) -> { setLatLng, setHtml, remove }
 *   stationMarkers(map, list)  the stations, named
 *   reachAreas(map, reach)     where the vehicles that can serve a request reach from
 *                              their stations (services.feasibility.reach_map), faintly
 *   requestView(map, config, aroundM)  a request map's first view: the station that
 *                              serves it, framing aroundM metres each way (no more than
 *                              its vehicles reach)
 *   escapeHtml(text), jsonScript(id), distanceM([lat, lon], [lat, lon])
 */
(function () {
  "use strict";

  /* Where the platform serves the land mask (services/urls.py). */
  const LAND_URL = "/map/land.geo.json";
  const OSM = '© <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors';
  const COLORS = { sea: "#12406a", land: "#6b6a45", coast: "#a39e6a", grid: "#3a4656" };

  function jsonScript(id) {
    const node = document.getElementById(id);
    return node ? JSON.parse(node.textContent) : null;
  }

  function makeMap(node, tiles) {
    const map = L.map(node, { attributionControl: false, zoomSnap: 0.5 });
    // Our own control, without Leaflet's prefix: the data's credit is what must show.
    map.attributionControl = L.control.attribution({ prefix: false }).addTo(map);
    L.control.scale({ imperial: false }).addTo(map);
    const labelLayer = labels(map);
    if (tiles) {
      L.tileLayer(tiles, { maxZoom: 19, attribution: `Map ${OSM}` }).addTo(map);
    } else {
      node.classList.add("map-offline");
      landLayer(map);
      graticule(map, labelLayer);
    }
    // The page may grow the map's box after it is made (a side panel filling up):
    // Leaflet has to be told, or it keeps drawing for the old size.
    if (window.ResizeObserver) new ResizeObserver(() => map.invalidateSize()).observe(node);
    return map;
  }

  // --- offline: the packaged land mask ------------------------------------------------
  let landData = null;
  function landMask() {
    if (!landData) {
      landData = fetch(LAND_URL, { credentials: "same-origin" })
        .then((response) => (response.ok ? response.json() : null))
        .catch(() => null);
    }
    return landData;
  }

  /* Inside each region of the mask the sea is one colour and the land another; outside
   * them the map stays the grid on a neutral ground: unknown, not sea. Drawn in a pane
   * under the overlays, so areas, paths and markers stay on top. */
  function landLayer(map) {
    const pane = map.createPane("iouv-land");
    pane.style.zIndex = "250";
    pane.style.pointerEvents = "none";
    landMask().then((data) => {
      if (!data || !Array.isArray(data.features)) return;
      const common = { pane: "iouv-land", interactive: false, fillOpacity: 1 };
      for (const feature of data.features) {
        const [south, west, north, east] = feature.properties.bbox;
        L.rectangle([[south, west], [north, east]], {
          ...common, stroke: false, fillColor: COLORS.sea, className: "map-sea",
        }).addTo(map);
        L.geoJSON(feature, {
          ...common,
          style: () => ({ ...common, color: COLORS.coast, weight: 1, fillColor: COLORS.land, className: "map-land" }),
        }).addTo(map);
      }
      map.attributionControl.addAttribution(`${OSM}, ODbL`);
      map.getContainer().dataset.land = "ready";
      map.fire("iouv:land");
    });
  }

  /* A lat/lon grid, redrawn at a spacing that suits the zoom; its labels along the top
   * and right edges, placed by the labels layer (so never under a control). */
  function graticule(map, labelLayer) {
    const layer = L.layerGroup().addTo(map);
    let tags = [];
    const steps = [0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10];
    function draw() {
      layer.clearLayers();
      for (const tag of tags) tag.remove();
      tags = [];
      const b = map.getBounds();
      const span = Math.max(b.getNorth() - b.getSouth(), b.getEast() - b.getWest());
      const step = steps.find((s) => span / s <= 10) || 10;
      const digits = Math.max(0, Math.ceil(-Math.log10(step)));
      const style = { color: COLORS.grid, weight: 1, interactive: false, className: "grid-line" };
      const grid = { priority: -1, group: "grid", radius: 0, className: "grid-label" };
      for (let lat = Math.ceil(b.getSouth() / step) * step; lat <= b.getNorth(); lat += step) {
        L.polyline([[lat, b.getWest()], [lat, b.getEast()]], style).addTo(layer);
        // Right-aligned just above the line, at the east edge.
        tags.push(labelLayer.add([lat, b.getEast()], lat.toFixed(digits), {
          ...grid, candidates: (w, h) => [[-w - 4, -h - 1]],
        }));
      }
      for (let lon = Math.ceil(b.getWest() / step) * step; lon <= b.getEast(); lon += step) {
        L.polyline([[b.getSouth(), lon], [b.getNorth(), lon]], style).addTo(layer);
        // Just right of the line, at the north edge.
        tags.push(labelLayer.add([b.getNorth(), lon], lon.toFixed(digits), {
          ...grid, candidates: () => [[3, 2]],
        }));
      }
    }
    map.on("moveend resize", draw);
    map.whenReady(draw);
  }

  // --- labels that never overlap ------------------------------------------------------
  /* Every label of a map goes through one layer, which after each move, zoom, resize
   * or change places them greedily, highest priority first: each takes the first of a
   * few spots around its point that is inside the map and overlaps no placed label, no
   * marked point and no map control. A label with no free spot is hidden, and counted
   * ("+1") on the nearest shown label of its kind, which names it in its tooltip. */
  const PRIORITY = { grid: -1, station: 1, pin: 2, vehicle: 3, alert: 4 };

  function labels(map) {
    if (map.iouvLabels) return map.iouvLabels;
    const entries = new Set();
    let order = 0;
    let scheduled = false;
    let zooming = false; // a zoom animates: places unknown until it ends

    function schedule() {
      if (scheduled) return;
      scheduled = true;
      // Once the current script task is done, before the page is painted.
      queueMicrotask(place);
    }

    function add(latlng, html, options = {}) {
      const group = options.group || "label";
      const entry = {
        html: String(html),
        text: textOf(html),
        latlng: L.latLng(latlng),
        group,
        priority: options.priority ?? PRIORITY[group] ?? 0,
        radius: options.radius ?? 8,
        candidates: options.candidates || null,
        order: order++,
        count: 0,
        names: [],
      };
      entry.marker = L.marker(entry.latlng, {
        interactive: false,
        keyboard: false,
        icon: L.divIcon({
          className: options.className || "map-label",
          html: entry.html,
          iconSize: null,
          iconAnchor: [0, 0],
        }),
      }).addTo(map);
      const el = entry.marker.getElement();
      el.dataset.labelGroup = group;
      el.style.visibility = "hidden"; // until placed
      entries.add(entry);
      schedule();
      return {
        element: el,
        setLatLng(point) {
          const next = L.latLng(point);
          if (next.equals(entry.latlng)) return;
          entry.latlng = next;
          entry.marker.setLatLng(next);
          schedule();
        },
        setHtml(text) {
          if (String(text) === entry.html) return;
          entry.html = String(text);
          entry.text = textOf(text);
          entry.count = -1; // redrawn on the next placement
          schedule();
        },
        remove() {
          if (!entries.delete(entry)) return;
          map.removeLayer(entry.marker);
          schedule();
        },
      };
    }

    function render(entry) {
      const el = entry.marker.getElement();
      const more = entry.count > 0 ? ` <span class="label-more">+${entry.count}</span>` : "";
      el.innerHTML = entry.html + more;
      el.title = entry.count > 0 ? entry.names.join(", ") : "";
      entry.shown = { html: entry.html, count: entry.count };
    }

    function spots(entry, w, h) {
      if (entry.candidates) return entry.candidates(w, h);
      const g = entry.radius + 3;
      const d = Math.round(g * 0.7);
      const far = g + 14;
      return [
        [g, -h / 2], [-g - w, -h / 2], [-w / 2, -g - h], [-w / 2, g],
        [d, -d - h], [d, d], [-d - w, -d - h], [-d - w, d],
        [far, -h / 2], [-far - w, -h / 2], [-w / 2, -far - h], [-w / 2, far],
      ];
    }

    function hits(a, b) {
      return a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h;
    }

    function place() {
      scheduled = false;
      // Placed on the first view, and after a zoom: while Leaflet animates one, the
      // labels slide with the map and their places are not yet known.
      if (!map._loaded || zooming) return;
      const container = map.getContainer();
      const box = container.getBoundingClientRect();
      const size = { w: container.clientWidth, h: container.clientHeight };
      const controls = [...container.querySelectorAll(".leaflet-control")].map((c) => {
        const r = c.getBoundingClientRect();
        return { x: r.left - box.left - 2, y: r.top - box.top - 2, w: r.width + 4, h: r.height + 4 };
      }).filter((r) => r.w > 4 && r.h > 4);
      const list = [...entries].filter((e) => e.marker.getElement());
      // Where Leaflet puts each marker: its layer point rounded to a pixel.
      for (const e of list) e.point = map.layerPointToContainerPoint(map.latLngToLayerPoint(e.latlng).round());
      const dots = list.filter((e) => e.radius > 0).map((e) => ({
        x: e.point.x - e.radius, y: e.point.y - e.radius, w: 2 * e.radius, h: 2 * e.radius,
      }));
      list.sort((a, b) => b.priority - a.priority || a.order - b.order);
      // The counts change the labels' widths, so place again until they settle.
      for (let pass = 0; pass < 4; pass++) {
        for (const e of list) {
          if (!e.shown || e.shown.html !== e.html || e.shown.count !== e.count) render(e);
        }
        const placed = [];
        for (const e of list) {
          const el = e.marker.getElement();
          // Whole pixels, rounded up: the box as drawn, never smaller.
          const drawn = el.getBoundingClientRect();
          const w = Math.ceil(drawn.width);
          const h = Math.ceil(drawn.height);
          e.rect = null;
          const inside = e.point.x >= 0 && e.point.y >= 0 && e.point.x <= size.w && e.point.y <= size.h;
          for (const spot of inside ? spots(e, w, h) : []) {
            const [dx, dy] = spot.map(Math.round);
            const r = { x: e.point.x + dx, y: e.point.y + dy, w, h };
            if (r.x < 1 || r.y < 1 || r.x + w > size.w - 1 || r.y + h > size.h - 1) continue;
            // A pixel apart at least: boxes that touch read as one.
            const apart = { x: r.x - 1, y: r.y - 1, w: w + 2, h: h + 2 };
            if (controls.some((c) => hits(r, c)) || placed.some((p) => hits(apart, p.rect))) continue;
            if (dots.some((d) => hits(r, d))) continue;
            e.rect = r;
            e.offset = [dx, dy];
            placed.push(e);
            break;
          }
        }
        // Hidden labels are counted on the nearest shown one of their kind nearby.
        const counts = new Map();
        for (const e of list) {
          if (e.rect || e.group === "grid") continue;
          let best = null;
          let bestD = 60;
          for (const p of placed) {
            if (p.group !== e.group) continue;
            const dist = Math.hypot(p.point.x - e.point.x, p.point.y - e.point.y);
            if (dist < bestD) { best = p; bestD = dist; }
          }
          if (best) counts.set(best, [...(counts.get(best) || []), e]);
        }
        let settled = true;
        for (const e of list) {
          const hidden = counts.get(e) || [];
          const names = hidden.map((h) => h.text);
          if (hidden.length !== e.count || names.join() !== e.names.join()) settled = false;
          e.count = hidden.length;
          e.names = names;
        }
        if (settled || pass === 3) {
          if (!settled) for (const e of list) { e.count = e.shown.count; } // keep the measured text
          break;
        }
      }
      for (const e of list) {
        const el = e.marker.getElement();
        if (e.rect) {
          el.style.marginLeft = `${e.offset[0]}px`;
          el.style.marginTop = `${e.offset[1]}px`;
          el.style.visibility = "";
          el.dataset.placed = "true";
        } else {
          el.style.visibility = "hidden";
          el.dataset.placed = "false";
        }
      }
      container.classList.remove("labels-zooming");
      container.dataset.labelsPlaced = String(Number(container.dataset.labelsPlaced || 0) + 1);
    }

    // Hidden while a zoom animates (they would pile up as the map shrinks), shown again
    // once placed at the new zoom.
    map.on("zoomstart", () => {
      zooming = true;
      map.getContainer().classList.add("labels-zooming");
    });
    map.on("zoomend", () => {
      zooming = false;
    });
    map.on("zoomend moveend resize viewreset", schedule);
    map.whenReady(schedule);
    map.iouvLabels = { add, place: schedule };
    return map.iouvLabels;
  }

  /* A label's plain text, for the tooltip of the label it is counted on (parsed in an
   * inert template: nothing in it loads or runs). */
  function textOf(html) {
    const template = document.createElement("template");
    template.innerHTML = String(html);
    return template.content.textContent;
  }

  function escapeHtml(text) {
    const div = document.createElement("div");
    div.textContent = String(text);
    return div.innerHTML;
  }

  function stationMarkers(map, stations) {
    for (const s of stations || []) {
      L.circleMarker([s.lat, s.lon], {
        radius: 6, color: "#e6edf3", weight: 2, fillOpacity: 0.2, className: "station-marker",
      }).addTo(map);
      labels(map).add([s.lat, s.lon], escapeHtml(s.name), { group: "station", radius: 6 });
    }
  }

  /* Circles around the stations, as far as each vehicle that can serve the request
   * goes and comes back on a full battery: not interactive, so a tap inside one still
   * picks a point. */
  function reachAreas(map, reach) {
    for (const r of reach || []) {
      const circle = L.circle([r.lat, r.lon], {
        radius: r.radius_m, color: "#3fb950", weight: 1.5, dashArray: "6 6", fillOpacity: 0.05,
        interactive: false, className: "reach-area",
      }).addTo(map);
      const path = circle.getElement();
      if (path) {
        path.dataset.reach = r.vehicle;
        path.dataset.radius = String(r.radius_m);
      }
    }
  }

  function requestView(map, config, aroundM) {
    const stations = (config && config.stations) || [];
    if (!stations.length) {
      map.setView([0, 0], 2);
      return;
    }
    const first = stations[0];
    const reaches = ((config && config.reach) || [])
      .filter((r) => r.station === first.name)
      .map((r) => r.radius_m);
    const half = Math.max(300, Math.min(aroundM, ...reaches));
    map.fitBounds(L.latLng(first.lat, first.lon).toBounds(2 * half));
  }

  /* Great-circle distance in metres. */
  function distanceM(a, b) {
    const R = 6371008.8;
    const rad = Math.PI / 180;
    const dLat = (b[0] - a[0]) * rad;
    const dLon = (b[1] - a[1]) * rad;
    const h = Math.sin(dLat / 2) ** 2 + Math.cos(a[0] * rad) * Math.cos(b[0] * rad) * Math.sin(dLon / 2) ** 2;
    return 2 * R * Math.asin(Math.sqrt(h));
  }

  window.IoUVMap = {
    makeMap, labels, stationMarkers, reachAreas, requestView, escapeHtml, jsonScript, distanceM,
  };
})();
