/*
 * A flight record's replay (services/templates/services/replay.html): each vehicle's
 * track on the map with its marker, one time slider over every vehicle's telemetry,
 * each vehicle's gauges at that instant, and the commands and events on a timeline.
 * The record comes from the page's samples URL
 * (services.web.record_views.session_replay_samples) in pages after a cursor; while
 * the session is live it asks again every poll_ms, and a slider left at the end
 * follows it.
 *
 * The slider's steps are the telemetry samples with a position of every vehicle, in
 * time order; at a step's instant t each vehicle is shown at its last position at or
 * before t. A vehicle with no position yet at t has no marker (its gauges say so):
 * a marker at its first position would claim it was there before its record says
 * anything of it (a boat still in harbour while the drone searches).
 *
 * Exposes window.IoUVReplay for tests: markerLatLng() (the first vehicle's marker),
 * current() (the sample at the slider's step), times() (the steps' instants),
 * markers() ({vehicle name: [lat, lon]} of the markers shown).
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
  const gauges = root.querySelector("[data-replay-gauges]");
  const video = root.querySelector("[data-replay-video-file]");
  const map = M.makeMap(root.querySelector("[data-replay-map]"), config.tiles);
  map.setView([0, 0], 2);

  // A colour per vehicle, in the page's order; the first is the one-vehicle page's.
  const PALETTE = ["#f5a623", "#2f81f7", "#e0245e", "#3fb950", "#a371f7", "#00bcd4"];
  const GAUGES = ["at", "alt", "speed", "battery", "mode", "heading"];

  const positions = []; // every vehicle's samples with a position, by time: the slider's steps
  const entries = []; // commands, events and what was dropped, by time: { sample, item }
  const vehicles = new Map(); // id -> vehicle (see vehicleOf), in the page's order
  const names = new Map((config.vehicles || []).map((v) => [v.id, v.name]));
  let cursor = 0;
  let started = false;
  let framedVehicles = 0;

  function fmt(value, digits, unit) {
    return value === null || value === undefined ? "–" : `${Number(value).toFixed(digits)} ${unit}`;
  }

  function clock(t) {
    return new Date(t * 1000).toISOString().slice(11, 23) + " UTC";
  }

  function hasPosition(sample) {
    return sample.data.lat !== null && sample.data.lat !== undefined;
  }

  // The index in ``list`` (sorted by .t) after the last item at or before t.
  function upperBound(list, t, key = (item) => item.t) {
    let lo = 0;
    let hi = list.length;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (key(list[mid]) <= t) lo = mid + 1;
      else hi = mid;
    }
    return lo;
  }

  // Put ``item`` into ``list`` after every item of its time or earlier (a vehicle's
  // samples and the timeline arrive in order, so this appends, unless another
  // vehicle's batch arrives late); returns where it went.
  function insertByTime(list, item, key) {
    const at = upperBound(list, key ? key(item) : item.t, key);
    list.splice(at, 0, item);
    return at;
  }

  // A vehicle of the page: its track, its marker and label once it has a position at
  // the slider's instant, its column of gauges. Made for the vehicles the page was
  // given, in their order, and for any other one the record holds as it turns up.
  function vehicleOf(id) {
    let v = vehicles.get(id);
    if (v) return v;
    const color = PALETTE[vehicles.size % PALETTE.length];
    v = {
      id,
      name: names.get(id) || `vehicle ${id}`,
      color,
      samples: [], // its positions, by time
      line: L.polyline([], { color, weight: 3, className: "replay-track" }).addTo(map),
      dot: null,
      tag: null,
      cells: {},
    };
    const head = document.createElement("th");
    head.scope = "col";
    head.dataset.gaugeVehicle = id;
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = color;
    head.append(swatch, v.name);
    gauges.tHead.rows[0].append(head);
    for (const gauge of GAUGES) {
      const cell = document.createElement("td");
      cell.dataset.gauge = gauge;
      cell.dataset.gaugeVehicle = id;
      cell.textContent = "–";
      gauges.querySelector(`[data-gauge-row="${gauge}"]`).append(cell);
      v.cells[gauge] = cell;
    }
    vehicles.set(id, v);
    nameEntries();
    return v;
  }

  // The vehicle at instant t, ``sample`` being its position then (null: none yet).
  function place(v, sample) {
    if (!sample) {
      if (v.dot) {
        v.dot.remove();
        v.tag.remove();
        v.dot = v.tag = null;
      }
      for (const gauge of GAUGES) v.cells[gauge].textContent = "–";
      v.cells.at.textContent = "no position yet";
      return;
    }
    const d = sample.data;
    const at = [d.lat, d.lon];
    if (!v.dot) {
      v.dot = L.circleMarker(at, {
        radius: 7, color: "#fff", fillColor: v.color, fillOpacity: 1, className: "replay-marker",
      }).addTo(map);
      v.dot.getElement().dataset.replayVehicle = v.id;
      v.tag = M.labels(map).add(at, M.escapeHtml(v.name), { group: "vehicle", radius: 7 });
      v.tag.element.style.borderColor = v.color;
      v.tag.element.dataset.replayVehicle = v.id;
    } else {
      v.dot.setLatLng(at);
      v.tag.setLatLng(at);
    }
    const text = {
      at: clock(sample.t),
      alt: fmt(d.alt, 1, "m"),
      speed: fmt(d.speed, 1, "m/s"),
      battery: fmt(d.battery, 0, "%"),
      mode: d.mode || "–",
      heading: fmt(d.heading, 0, "°"),
    };
    for (const gauge of GAUGES) v.cells[gauge].textContent = text[gauge];
  }

  // Every vehicle at the slider's step ``index``: the step's own sample for its
  // vehicle (two samples of one vehicle may share an instant), the last position at or
  // before that instant for the others.
  function placeAll(index) {
    const step = positions[index];
    for (const v of vehicles.values()) {
      if (step.vehicle === v.id) place(v, step);
      else place(v, v.samples[upperBound(v.samples, step.t) - 1] || null);
    }
  }

  function show(index) {
    const step = positions[index];
    if (!step) return;
    placeAll(index);
    timeOut.textContent = clock(step.t);
    for (const entry of entries) entry.item.classList.toggle("past", entry.sample.t <= step.t);
    if (video) showVideo(step.t);
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

  // The timeline names each entry's vehicle once the page shows more than one.
  function nameEntries() {
    const several = vehicles.size > 1;
    for (const { sample, item } of entries) {
      item.querySelector("[data-replay-vehicle]").textContent = several
        ? `${vehicles.get(sample.vehicle).name} · `
        : "";
    }
  }

  function addEntry(sample) {
    const v = vehicleOf(sample.vehicle);
    const item = document.createElement("li");
    item.dataset.t = String(sample.t);
    item.dataset.kind = sample.kind;
    const button = document.createElement("button");
    button.type = "button";
    button.className = "link";
    button.textContent = clock(sample.t);
    button.addEventListener("click", () => {
      slider.value = String(Math.max(0, upperBound(positions, sample.t) - 1));
      show(Number(slider.value));
    });
    const who = document.createElement("span");
    who.dataset.replayVehicle = sample.vehicle;
    who.textContent = vehicles.size > 1 ? `${v.name} · ` : "";
    item.append(button, " ", who, describe(sample));
    const entry = { sample, item };
    const at = insertByTime(entries, entry, (e) => e.sample.t);
    const next = entries[at + 1];
    timeline.insertBefore(item, next ? next.item : null);
  }

  // Frame every track: on the first positions, and again when a vehicle's first
  // positions arrive (a second vehicle's may be far from the first's).
  function frame() {
    const drawn = [...vehicles.values()].filter((v) => v.samples.length);
    if (drawn.length <= framedVehicles) return;
    framedVehicles = drawn.length;
    const bounds = L.latLngBounds([]);
    for (const v of drawn) bounds.extend(v.line.getBounds());
    map.fitBounds(bounds.pad(0.3), { maxZoom: 18 });
  }

  function take(answer) {
    for (const [id, name] of Object.entries(answer.vehicles || {})) {
      if (!names.has(id)) names.set(id, name);
    }
    const following = Number(slider.value) >= positions.length - 1;
    const held = positions[Number(slider.value)] || null;
    for (const sample of answer.samples) {
      if (sample.kind !== "telemetry") {
        addEntry(sample);
        continue;
      }
      if (!hasPosition(sample)) continue;
      const v = vehicleOf(sample.vehicle);
      insertByTime(positions, sample);
      if (insertByTime(v.samples, sample) === v.samples.length - 1) {
        v.line.addLatLng([sample.data.lat, sample.data.lon]);
      } else {
        v.line.setLatLngs(v.samples.map((s) => [s.data.lat, s.data.lon]));
      }
    }
    if (!positions.length) return;
    slider.max = String(positions.length - 1);
    slider.disabled = false;
    frame();
    if (!started) {
      started = true;
      slider.value = "0";
      show(0);
    } else if (following) {
      slider.value = slider.max;
      show(positions.length - 1);
    } else if (held) {
      // Scrubbed back: the slider stays on the instant it was put on, though another
      // vehicle's earlier positions may have come in before it, which then show.
      slider.value = String(positions.indexOf(held));
      placeAll(Number(slider.value));
    }
  }

  async function load() {
    let answer;
    do {
      const response = await fetch(`${config.samples_url}?after=${cursor}`, { credentials: "same-origin" });
      if (!response.ok) throw new Error(`the record could not be read (${response.status})`);
      answer = await response.json();
      cursor = answer.next;
      take(answer);
    } while (answer.more);
    return answer.live;
  }

  function counted() {
    const drawn = [...vehicles.values()].filter((v) => v.samples.length).length;
    return drawn > 1 ? `${positions.length} positions of ${drawn} vehicles` : `${positions.length} positions`;
  }

  async function run() {
    let live = true;
    while (live) {
      try {
        live = await load();
        status.textContent = live
          ? `Live: ${counted()} so far, more every ${config.poll_ms / 1000} s`
          : `${counted()}, ${entries.length} commands and events`;
        root.dataset.loaded = "true";
      } catch (error) {
        status.textContent = `${error.message}; trying again`;
      }
      if (live) await new Promise((resolve) => setTimeout(resolve, config.poll_ms));
    }
  }

  for (const v of config.vehicles || []) vehicleOf(v.id);
  slider.addEventListener("input", () => show(Number(slider.value)));
  window.IoUVReplay = {
    markerLatLng: () => {
      const first = [...vehicles.values()].find((v) => v.samples.length);
      const dot = first && first.dot;
      return dot ? [dot.getLatLng().lat, dot.getLatLng().lng] : null;
    },
    current: () => positions[Number(slider.value)] || null,
    times: () => positions.map((sample) => sample.t),
    markers: () => Object.fromEntries(
      [...vehicles.values()].filter((v) => v.dot).map((v) => [v.name, [v.dot.getLatLng().lat, v.dot.getLatLng().lng]]),
    ),
  };
  run();
})();
