/*
 * The portal's map basics (Leaflet, vendored in static/vendor): what every map page
 * of every service kind shares. Exposes window.IoUVMap:
 *
 *   makeMap(node, tiles)       a map with the configured tiles, else a lat/lon grid
 *                              (the portal works on a closed network), and a scale
 *   stationMarkers(map, list)  the stations, named
 *   label(html)                a text marker icon
 *   escapeHtml(text), jsonScript(id), distanceM([lat, lon], [lat, lon])
 */
(function () {
  "use strict";

  function jsonScript(id) {
    const node = document.getElementById(id);
    return node ? JSON.parse(node.textContent) : null;
  }

  function makeMap(node, tiles) {
    const map = L.map(node, { attributionControl: Boolean(tiles), zoomSnap: 0.5 });
    if (tiles) {
      L.tileLayer(tiles, { maxZoom: 19, attribution: "map tiles" }).addTo(map);
    } else {
      graticule(map);
    }
    L.control.scale({ imperial: false }).addTo(map);
    return map;
  }

  /* A lat/lon grid, redrawn at a spacing that suits the zoom. */
  function graticule(map) {
    const layer = L.layerGroup().addTo(map);
    const steps = [0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10];
    function draw() {
      layer.clearLayers();
      const b = map.getBounds();
      const span = Math.max(b.getNorth() - b.getSouth(), b.getEast() - b.getWest());
      const step = steps.find((s) => span / s <= 10) || 10;
      const style = { color: "#1f3b57", weight: 1, interactive: false };
      for (let lat = Math.ceil(b.getSouth() / step) * step; lat <= b.getNorth(); lat += step) {
        L.polyline([[lat, b.getWest()], [lat, b.getEast()]], style).addTo(layer);
        L.marker([lat, b.getWest()], {
          interactive: false,
          icon: L.divIcon({ className: "grid-label", html: lat.toFixed(4), iconAnchor: [-4, 12] }),
        }).addTo(layer);
      }
      for (let lon = Math.ceil(b.getWest() / step) * step; lon <= b.getEast(); lon += step) {
        L.polyline([[b.getSouth(), lon], [b.getNorth(), lon]], style).addTo(layer);
      }
    }
    map.on("moveend zoomend resize", draw);
    map.whenReady(draw);
  }

  function label(text) {
    return L.divIcon({ className: "map-label", html: text, iconAnchor: [-8, 8] });
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
      L.marker([s.lat, s.lon], { icon: label(escapeHtml(s.name)), interactive: false }).addTo(map);
    }
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

  window.IoUVMap = { makeMap, stationMarkers, label, escapeHtml, jsonScript, distanceM };
})();
