/*
 * A flight record's replay (services/templates/services/replay.html): the track on the
 * map, a time slider over the telemetry samples, the gauges at that instant, and the
 * commands and events on a timeline. The record comes from the page's samples URL
 * (services.record_views.session_replay_samples) in pages after a cursor; while the
 * session is live it asks again every poll_ms, and a slider left at the end follows it.
 * Exposes window.IoUVReplay for tests: markerLatLng(), current(), times().
 */
(function () {
  "use strict";
  const M = window.IoUVMap;
  const config = M.jsonScript("replay-config");
  const root = document.getElementById("replay");
  const slider = root.querySelector("[data-replay-slider]");
  const timeOut = root.querySelector("[data-replay-time]");
  const status = root.querySelector("[data-replay-status]");
  const timeline = root.querySelector("[data-replay-timeline]");
  const video = root.querySelector("[data-replay-video-file]");
  const map = M.makeMap(root.querySelector("[data-replay-map]"), config.tiles);
  map.setView([0, 0], 2);

  const telemetry = []; // samples with a position, by time
  const entries = []; // commands, events and what was dropped, by time
  const line = L.polyline([], { color: "#f5a623", weight: 3 }).addTo(map);
  let marker = null;
  let cursor = 0;
  let framed = false;

  function fmt(value, digits, unit) {
    return value === null || value === undefined ? "–" : `${Number(value).toFixed(digits)} ${unit}`;
  }

  function clock(t) {
    return new Date(t * 1000).toISOString().slice(11, 23) + " UTC";
  }

  function show(index) {
    const sample = telemetry[index];
    if (!sample) return;
    const d = sample.data;
    const at = [d.lat, d.lon];
    if (!marker) marker = L.circleMarker(at, { radius: 7, color: "#fff", fillColor: "#e0245e", fillOpacity: 1 }).addTo(map);
    else marker.setLatLng(at);
    const gauges = {
      alt: fmt(d.alt, 1, "m"),
      speed: fmt(d.speed, 1, "m/s"),
      battery: fmt(d.battery, 0, "%"),
      mode: d.mode || "–",
      heading: fmt(d.heading, 0, "°"),
    };
    for (const [name, text] of Object.entries(gauges)) {
      root.querySelector(`[data-gauge="${name}"]`).textContent = text;
    }
    timeOut.textContent = clock(sample.t);
    for (const item of timeline.children) {
      item.classList.toggle("past", Number(item.dataset.t) <= sample.t);
    }
    if (video) showVideo(sample.t);
  }

  // The recorded video at instant t (Unix seconds): the stretch that started last before
  // t, at t minus its start (the SFU stamps each stretch's start on the wall clock, as
  // the vehicle stamps its samples).
  function showVideo(t) {
    const stretches = config.videos || [];
    let current = null;
    for (const s of stretches) if (s.started_at <= t) current = s;
    const note = root.querySelector("[data-replay-video-note]");
    if (!current) {
      video.hidden = true;
      if (note) note.textContent = "No video at this instant.";
      return;
    }
    video.hidden = false;
    if (note) note.textContent = "";
    const at = t - current.started_at;
    const seek = () => { video.currentTime = Math.min(at, video.duration || at); };
    if (video.dataset.src !== current.url) {
      video.dataset.src = current.url;
      video.src = current.url;
      video.addEventListener("loadedmetadata", seek, { once: true });
    } else if (video.readyState >= 1) {
      seek();
    }
  }

  function describe(sample) {
    const d = sample.data;
    if (sample.kind === "command") {
      const ack = d.ok ? "ok" : `refused${d.code ? ` (${d.code})` : ""}`;
      return `${d.source || "?"} · ${d.name} · ${ack}`;
    }
    if (sample.kind === "dropped") return `the vehicle dropped samples (${d.reason || "?"})`;
    return `event · ${d.event}`;
  }

  function nearest(t) {
    let best = 0;
    for (let i = 0; i < telemetry.length && telemetry[i].t <= t; i++) best = i;
    return best;
  }

  function addEntry(sample) {
    const item = document.createElement("li");
    item.dataset.t = String(sample.t);
    item.dataset.kind = sample.kind;
    const button = document.createElement("button");
    button.type = "button";
    button.className = "link";
    button.textContent = clock(sample.t);
    button.addEventListener("click", () => {
      slider.value = String(nearest(sample.t));
      show(Number(slider.value));
    });
    item.append(button, " ", describe(sample));
    timeline.append(item);
  }

  function take(samples) {
    const following = Number(slider.value) >= telemetry.length - 1;
    for (const sample of samples) {
      if (sample.kind === "telemetry") {
        if (sample.data.lat === null || sample.data.lat === undefined) continue;
        telemetry.push(sample);
        line.addLatLng([sample.data.lat, sample.data.lon]);
      } else {
        entries.push(sample);
        addEntry(sample);
      }
    }
    if (!telemetry.length) return;
    slider.max = String(telemetry.length - 1);
    slider.disabled = false;
    if (!framed) {
      framed = true;
      map.fitBounds(line.getBounds().pad(0.3), { maxZoom: 18 });
      slider.value = "0";
      show(0);
    } else if (following) {
      slider.value = slider.max;
      show(telemetry.length - 1);
    }
  }

  async function load() {
    let answer;
    do {
      const response = await fetch(`${config.samples_url}?after=${cursor}`, { credentials: "same-origin" });
      if (!response.ok) throw new Error(`the record could not be read (${response.status})`);
      answer = await response.json();
      cursor = answer.next;
      take(answer.samples);
    } while (answer.more);
    return answer.live;
  }

  async function run() {
    let live = true;
    while (live) {
      try {
        live = await load();
        status.textContent = live
          ? `Live: ${telemetry.length} positions so far, more every ${config.poll_ms / 1000} s`
          : `${telemetry.length} positions, ${entries.length} commands and events`;
        root.dataset.loaded = "true";
      } catch (error) {
        status.textContent = `${error.message}; trying again`;
      }
      if (live) await new Promise((resolve) => setTimeout(resolve, config.poll_ms));
    }
  }

  slider.addEventListener("input", () => show(Number(slider.value)));
  window.IoUVReplay = {
    markerLatLng: () => (marker ? [marker.getLatLng().lat, marker.getLatLng().lng] : null),
    current: () => telemetry[Number(slider.value)] || null,
    times: () => telemetry.map((sample) => sample.t),
  };
  run();
})();
