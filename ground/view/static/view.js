// NAC's view: the run's frames (positions in local metres, probes, iterations, link capacities, events) drawn
// at a cursor time, live (Server-Sent Events) or replayed (all frames at once, then play/pause/scrub).
// Ids and names come from files and links: they index Maps only, never plain objects (a vehicle named
// "__proto__", "constructor" or "toString" draws like any other), and reach the page as text or escaped.
"use strict";

const SVGNS = "http://www.w3.org/2000/svg";
const COLORS = ["#2471a3", "#d35400", "#27ae60", "#8e44ad", "#c0392b", "#16a085", "#b7950b", "#5d6d7e"];
const TRAIL_S = 60, RATE_WINDOW_S = 60;
const view = {
  info: null, roles: new Map(), pos: new Map(), probes: new Map(), packs: new Map(), caps: [], its: [], events: [],
  t0: Infinity,
  t1: -Infinity, cursor: 0, follow: true, playing: false, speed: 10, lastSeq: -1, bounds: null, dirty: true,
  color: new Map(), notes: [],  // notes: what the page itself had to say (a ?at= it could not take as given)
};
window.nacView = view;

const $ = (id) => document.getElementById(id);
function el(tag, attrs, parent) {
  const node = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}
function insertByTime(list, frame) {  // frames mostly arrive in order: append, else insert in place
  let i = list.length;
  while (i > 0 && list[i - 1].t > frame.t) i--;
  list.splice(i, 0, frame);
}
function at(list, t) {  // the last frame at or before t
  let lo = 0, hi = list.length - 1, best = -1;
  while (lo <= hi) {
    const mid = (lo + hi) >> 1;
    if (list[mid].t <= t) { best = mid; lo = mid + 1; } else hi = mid - 1;
  }
  return best < 0 ? null : list[best];
}
const esc = (text) => String(text).replace(/[&<>"']/g, (c) => "&#" + c.charCodeAt(0) + ";");  // names come from files and links
function colorOf(id) {
  if (!view.color.has(id)) view.color.set(id, COLORS[view.color.size % COLORS.length]);
  return view.color.get(id);
}
const roleOf = (id) => { const v = view.roles.get(id); return (v && typeof v.role === "string") ? v.role : "?"; };
function setInfo(info) {  // the state's vehicles, as a Map: their ids are keys only there
  view.info = info;
  view.roles = new Map(Object.entries(info.vehicles || {}));
}
const missionsOf = (info) => Object.entries((info && info.missions) || {});

function ingestPositions(f) {  // a batch of one vehicle's positions, as columns: one object per position
  if (!view.pos.has(f.v)) view.pos.set(f.v, []);
  const list = view.pos.get(f.v);
  for (let j = 0; j < f.t.length; j++) {
    const p = { v: f.v, t: f.t[j], e: f.e[j], n: f.n[j], u: f.u[j], hdg: f.hdg[j], mode: f.mode[j], armed: f.armed[j],
                batt: f.batt[j], seq: f.seq[j], tot: f.tot[j], tb: f.tb[j] };
    view.t0 = Math.min(view.t0, p.t);
    view.t1 = Math.max(view.t1, p.t);
    insertByTime(list, p);
    grow(p.e, p.n);
  }
}
function ingest(frames) {
  for (const f of frames) {
    view.lastSeq = Math.max(view.lastSeq, f.s);
    if (f.k === "pos") { ingestPositions(f); continue; }
    view.t0 = Math.min(view.t0, f.t);
    view.t1 = Math.max(view.t1, f.t);
    if (f.k === "probe") {
      const key = JSON.stringify([f.a, f.b]);
      if (!view.probes.has(key)) view.probes.set(key, []);
      insertByTime(view.probes.get(key), f);
    }
    else if (f.k === "pw") {  // a vehicle's two packs: flight (fs) and companion (cs), state of charge in %
      if (!view.packs.has(f.v)) view.packs.set(f.v, []);
      insertByTime(view.packs.get(f.v), f);
    }
    else if (f.k === "cap") insertByTime(view.caps, f);
    else if (f.k === "it") insertByTime(view.its, f);
    else if (f.k === "ev") insertByTime(view.events, f);
  }
  if (view.follow) view.cursor = view.t1;
  view.dirty = true;
}
function grow(e, n) {
  const b = view.bounds || (view.bounds = { e0: e, e1: e, n0: n, n1: n });
  b.e0 = Math.min(b.e0, e); b.e1 = Math.max(b.e1, e); b.n0 = Math.min(b.n0, n); b.n1 = Math.max(b.n1, n);
}

// ---- the map --------------------------------------------------------------------------------------------
function niceStep(span) {
  const raw = span / 8, p = Math.pow(10, Math.floor(Math.log10(raw)));
  return [1, 2, 5, 10].map((m) => m * p).find((s) => s >= raw);
}
function layoutMap() {
  const b = view.bounds || { e0: -10, e1: 10, n0: -10, n1: 10 };
  const span = Math.max(b.e1 - b.e0, b.n1 - b.n0, 20), pad = span * 0.12;
  const box = [b.e0 - pad, -(b.n1 + pad), b.e1 - b.e0 + 2 * pad, b.n1 - b.n0 + 2 * pad];
  const key = box.map((v) => v.toFixed(1)).join(" ");
  view.textM = Math.max(box[2], box[3]) / 45;
  view.box = box;
  if (key === view.mapKey) return;
  view.mapKey = key;
  $("map").setAttribute("viewBox", key);
  const grid = $("grid");
  grid.replaceChildren();
  const step = niceStep(Math.max(box[2], box[3]));
  const big = Math.max(box[2], box[3]);  // the page may be wider or taller than the box: grid beyond it too
  const g = [box[0] - big, box[1] - big, box[2] + 2 * big, box[3] + 2 * big];
  for (let e = Math.ceil(g[0] / step) * step; e < g[0] + g[2]; e += step)
    el("line", { x1: e, x2: e, y1: g[1], y2: g[1] + g[3], class: "gridline" + (Math.abs(e) < 1e-9 ? " major" : ""), "vector-effect": "non-scaling-stroke" }, grid);
  for (let n = Math.ceil(-(g[1] + g[3]) / step) * step; n < -g[1]; n += step)
    el("line", { x1: g[0], x2: g[0] + g[2], y1: -n, y2: -n, class: "gridline" + (Math.abs(n) < 1e-9 ? " major" : ""), "vector-effect": "non-scaling-stroke" }, grid);
  const x = box[0] + step * 0.3, y = box[1] + box[3] - step * 0.3;
  el("line", { x1: x, x2: x + step, y1: y, y2: y, class: "scale", "stroke-width": 3, "vector-effect": "non-scaling-stroke" }, grid);
  view.scaleBox = [x, y - view.textM * 1.2, step, view.textM * 1.4];  // labels keep off the scale bar
  const label = el("text", { x: x, y: y - view.textM * 0.4, class: "scale-label", "font-size": view.textM * 0.8 }, grid);
  label.textContent = step + " m";
  const missions = $("missions");
  missions.replaceChildren();
  for (const [vid, points] of missionsOf(view.info)) {
    if (!points.length) continue;
    el("polyline", { points: points.map((p) => p[0] + "," + -p[1]).join(" "), class: "mission", stroke: colorOf(vid), "vector-effect": "non-scaling-stroke" }, missions);
    for (const p of points) el("circle", { cx: p[0], cy: -p[1], r: view.textM * 0.25, class: "waypoint" }, missions);
  }
}

function probeAt(a, b, t) { const list = view.probes.get(JSON.stringify([a, b])); return list ? at(list, t) : null; }
function capacityAt(a, b, t) {
  const cap = at(view.caps, t);
  if (!cap || !cap.a) return null;
  for (let i = 0; i < cap.a.length; i++)
    if ((cap.a[i] === a && cap.b[i] === b) || (cap.a[i] === b && cap.b[i] === a)) return cap.bps[i];
  return null;
}
const mbit = (bps) => (bps / 1e6).toFixed(1);

function drawMap(t) {
  layoutMap();
  const vehicles = $("vehicles"), trails = $("trails"), links = $("links");
  vehicles.replaceChildren(); trails.replaceChildren(); links.replaceChildren();
  const here = new Map();
  for (const [vid, list] of view.pos) {
    const p = at(list, t);
    if (!p) continue;
    here.set(vid, p);
    const trail = list.filter((q) => q.t <= t && q.t >= t - TRAIL_S);
    el("polyline", { points: trail.map((q) => q.e + "," + -q.n).join(" "), class: "trail", stroke: colorOf(vid), "vector-effect": "non-scaling-stroke" }, trails);
  }
  const seen = visibleBox(), taken = view.scaleBox ? [view.scaleBox] : [];  // boxes [x, y, w, h], map units, y down
  const master = [...view.roles.keys()].find((v) => roleOf(v) === "master");
  const linkLines = master !== undefined && here.has(master)  // the links' lines, which labels keep off ...
    ? [...here].filter(([vid]) => vid !== master).map(([, p]) => [here.get(master), p, LINK_WEIGHT]) : [];
  const segments = [...linkLines, ...pathSegments(t)];  // ... and, less strictly, the trails and mission legs
  for (const [vid, p] of here) {
    const g = el("g", { class: "vehicle" + (p.armed === false ? " disarmed" : ""), id: "vehicle-" + vid, "data-id": vid, "data-e": p.e, "data-n": p.n, "data-t": p.t, "data-tb": p.tb,
                        transform: `translate(${p.e},${-p.n})` }, vehicles);
    const s = view.textM * 0.9, size = view.textM;
    el("polygon", { points: `0,${-s} ${s * 0.6},${s * 0.7} 0,${s * 0.35} ${-s * 0.6},${s * 0.7}`, class: "body", fill: colorOf(vid), transform: `rotate(${p.hdg || 0})`, "vector-effect": "non-scaling-stroke" }, g);
    const text = `${vid} (${roleOf(vid)}) ${p.mode || ""}`, w = textWidth(text, size);
    // right of the vehicle, left, above or below: where it overlaps the least of the labels placed, crosses the
    // fewest links and stays on the visible map (the first that does best)
    const spots = [[s * 1.1, -size * 0.5], [-s * 1.1 - w, -size * 0.5], [-w / 2, -s * 1.2 - size], [-w / 2, s * 1.1]];
    let best = spots[0], bestCost = Infinity;
    for (const [dx, dy] of spots) {
      const cost = labelCost([p.e + dx, -p.n + dy, w, size], taken, seen, segments);
      if (cost < bestCost - 1e-9) { best = [dx, dy]; bestCost = cost; }
    }
    const label = el("text", { x: best[0], y: best[1] + size * 0.8, "font-size": size }, g);
    label.textContent = text;
    taken.push([p.e + best[0], -p.n + best[1], w, size]);
  }
  if (linkLines.length) {
    for (const [vid, p] of here) {
      if (vid === master) continue;
      const probe = probeAt(master, vid, t), cap = capacityAt(master, vid, t);
      const out = (probe && !probe.ok) || cap === 0;
      const m = here.get(master);
      el("line", { x1: m.e, y1: -m.n, x2: p.e, y2: -p.n, class: "link" + (out ? " out" : ""), "data-worker": vid, "data-state": out ? "out" : "up", "stroke-width": 2, "vector-effect": "non-scaling-stroke" }, links);
      const text = (out ? "out of range" : probe ? mbit(probe.bps) + " Mbit/s" : "no probe yet") + (cap != null ? " (model " + mbit(cap) + ")" : "");
      const size = view.textM * 0.8, spot = linkLabelSpot(m, p, textWidth(text, size), size, taken, seen, segments);
      const label = el("text", { x: spot[0] + spot[2] / 2, y: spot[1] + size * 0.8, "text-anchor": "middle", class: "link-label", "font-size": size }, links);
      label.textContent = text;
      taken.push(spot);
    }
  }
  return here;
}
// A label's width in map units: sans-serif averages about 0.55 em a character.
const textWidth = (text, size) => text.length * size * 0.55;
// The map's visible extent in map units (the page is often wider or taller than the data's box), [x, y, w, h].
function visibleBox() {
  const svg = $("map"), r = svg.getBoundingClientRect(), ctm = svg.getScreenCTM();
  if (!ctm || !r.width || !r.height) return view.box || [-1e9, -1e9, 2e9, 2e9];
  const inverse = ctm.inverse(), corner = (x, y) => new DOMPoint(x, y).matrixTransform(inverse);
  const a = corner(r.left, r.top), b = corner(r.right, r.bottom);
  return [a.x, a.y, b.x - a.x, b.y - a.y];
}
// Where a link's label goes: beside the link (never across it), at the place along it, and on the side, where it
// overlaps the least of the labels already placed and stays on the visible map.
function linkLabelSpot(m, p, w, size, taken, seen, segments) {
  const x1 = m.e, y1 = -m.n, x2 = p.e, y2 = -p.n, length = Math.hypot(x2 - x1, y2 - y1) || 1;
  const nx = -(y2 - y1) / length, ny = (x2 - x1) / length;  // a unit normal, in map units (y down)
  let best = null, bestCost = Infinity;
  for (const along of [0.5, 0.35, 0.65, 0.2, 0.8]) {
    for (const side of [1, -1]) {
      // the box's centre off the line by half its own extent across the line, plus a margin
      const reach = Math.abs(nx) * w / 2 + Math.abs(ny) * size / 2 + size * 0.3;
      const cx = x1 + (x2 - x1) * along + side * nx * reach, cy = y1 + (y2 - y1) * along + side * ny * reach;
      const box = [cx - w / 2, cy - size / 2, w, size], cost = labelCost(box, taken, seen, segments);
      if (cost < bestCost - 1e-9) { best = box; bestCost = cost; }
    }
  }
  return best;
}
// A label's cost in map units squared: what it covers of the labels placed, what of it is off the visible map, and
// each line through it, its length inside times the label's height times the line's weight (a link struck through
// costs three times a trail or a mission leg).
const LINK_WEIGHT = 3, PATH_WEIGHT = 1;
function labelCost(box, taken, seen, segments) {
  const area = box[2] * box[3], height = box[3];
  return taken.reduce((sum, b) => sum + overlap(box, b), 0) + area - overlap(box, seen) +
         segments.reduce((sum, [a, b, weight]) => sum + insideLength(box, a, b) * height * weight, 0);
}
// The trails drawn (every few points: their shape, cheaply) and the missions' legs, as [a, b, PATH_WEIGHT].
function pathSegments(t) {
  const out = [];
  for (const list of view.pos.values()) {
    const trail = list.filter((q) => q.t <= t && q.t >= t - TRAIL_S).filter((q, k, all) => k % 5 === 0 || k === all.length - 1);
    for (let k = 1; k < trail.length; k++) out.push([trail[k - 1], trail[k], PATH_WEIGHT]);
  }
  for (const [, points] of missionsOf(view.info))
    for (let k = 1; k < points.length; k++)
      out.push([{ e: points[k - 1][0], n: points[k - 1][1] }, { e: points[k][0], n: points[k][1] }, PATH_WEIGHT]);
  return out;
}
// The length of the line from a to b inside box (Liang-Barsky clipping; map units, y down).
function insideLength(box, a, b) {
  const x0 = a.e, y0 = -a.n, dx = b.e - a.e, dy = -(b.n - a.n);
  let lo = 0, hi = 1;
  for (const [p, q] of [[-dx, x0 - box[0]], [dx, box[0] + box[2] - x0], [-dy, y0 - box[1]], [dy, box[1] + box[3] - y0]]) {
    if (p === 0) { if (q < 0) return 0; continue; }
    const r = q / p;
    if (p < 0) lo = Math.max(lo, r); else hi = Math.min(hi, r);
    if (lo > hi) return 0;
  }
  return (hi - lo) * Math.hypot(dx, dy);
}
function overlap(a, b) {
  const w = Math.min(a[0] + a[2], b[0] + b[2]) - Math.max(a[0], b[0]);
  const h = Math.min(a[1] + a[3], b[1] + b[3]) - Math.max(a[1], b[1]);
  return w > 0 && h > 0 ? w * h : 0;
}

// ---- panels and charts ------------------------------------------------------------------------------------
function drawPanels(t, here) {
  const rows = [...new Set([...view.roles.keys(), ...view.pos.keys()])].sort().map((vid) => {
    const p = here.get(vid) || {};
    const total = p.tot;  // MISSION_CURRENT's total, as the agent logged it
    const packs = view.packs.has(vid) ? at(view.packs.get(vid), t) : null;  // the energy meter's, when metered
    const companion = packs && packs.cs != null ? packs.cs + " %" : "-";
    return `<tr data-id="${esc(vid)}"><td style="color:${colorOf(vid)}">${esc(vid)}</td><td>${esc(roleOf(vid))}</td><td>${esc(p.mode || "-")}</td>` +
           `<td>${p.armed == null ? "-" : p.armed ? "armed" : "disarmed"}</td><td>${p.batt == null ? "-" : p.batt + " %"}</td>` +
           `<td>${companion}</td>` +
           `<td>${p.seq == null ? "-" : p.seq + (total ? "/" + total : "")}</td></tr>`;
  });
  $("fleet").tBodies[0].innerHTML = rows.join("");
  const done = view.its.filter((it) => it.t <= t);
  const last = done[done.length - 1];
  const perMin = perSimulatedMinute(done);
  $("job").innerHTML = last
    ? `<span id="iterations" data-count="${done.length}">${done.length}</span> iterations, ${perMin.toFixed(0)} per minute; ` +
      `workers present ${last.n}/${last.of}; training cost ${last.cost == null ? "-" : last.cost.toPrecision(4)}`
    : `<span id="iterations" data-count="0">0</span> iterations yet`;
  // a training cost only where the task has one (linreg): matmul's iterations carry none, and get no empty chart
  const costs = done.filter((it) => it.cost != null).map((it) => [it.t, it.cost]);
  $("cost-chart").hidden = !view.its.some((it) => it.cost != null);
  chart($("cost-chart"), [{ color: "#1d2430", points: costs }], t, "training cost");
  const series = [...view.probes.values()].map((list) => ({
    color: colorOf(list[0].b), label: list[0].b,
    points: list.filter((p) => p.t <= t).map((p) => [p.t, p.bps / 1e6]),
  }));
  chart($("tp-chart"), series, t, "Mbit/s");
  $("tp-legend").innerHTML = series.map((s) => `<span style="color:${s.color}">&#9632; ${esc(s.label)}</span>`).join("");
}
// Iterations per minute of the run's own clock: a sped-up run's iterations carry their simulated start (ts), so
// the count over a wall-clock window is divided by the simulated time it spans; a vehicle's carry none (wall time).
// The pace over the last RATE_WINDOW_S simulated seconds, as the report and the progress line count it over the
// whole job (nac_onboard.compute.iteration.iterations_per_min): iterations over the span from the first one's
// start to the last one's end. Records without simulated times (a real vehicle's): a count over wall seconds.
function perSimulatedMinute(done) {
  if (!done.length) return 0;
  if (done.every((it) => it.ts != null && it.dur != null)) {
    const last = done[done.length - 1], end = last.ts + last.dur;
    const recent = done.filter((it) => it.ts >= end - RATE_WINDOW_S);
    const span = end - recent[0].ts;
    return span > 0 ? recent.length * 60 / span : 0;
  }
  const t = done[done.length - 1].t;
  return done.filter((it) => it.t > t - RATE_WINDOW_S).length * (60 / RATE_WINDOW_S);
}
function chart(canvas, series, t, unit) {
  const ctx = canvas.getContext("2d"), w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  const all = series.flatMap((s) => s.points);
  if (!all.length || !isFinite(view.t0)) return;
  const tMin = view.t0, tMax = Math.max(t, tMin + 1);
  const yMax = Math.max(...all.map((p) => p[1]), 1e-9) * 1.1;
  ctx.fillStyle = "#46505e"; ctx.font = "10px sans-serif";
  ctx.fillText(yMax.toPrecision(3) + " " + unit, 2, 10);
  for (const s of series) {
    ctx.strokeStyle = s.color; ctx.beginPath();
    s.points.forEach(([pt, v], i) => {
      const x = ((pt - tMin) / (tMax - tMin)) * (w - 4) + 2, y = h - 2 - (v / yMax) * (h - 14);
      if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    ctx.stroke();
  }
}

// ---- time: the cursor, the timeline, play ---------------------------------------------------------------
function drawTimeline() {
  if (!isFinite(view.t0)) { $("cursor-label").textContent = "waiting for the first record"; return; }
  const slider = $("cursor"), span = Math.max(view.t1 - view.t0, 0);
  slider.max = span.toFixed(1);
  slider.value = (view.cursor - view.t0).toFixed(1);
  // the timeline is the wall clock the records were written on; a sped-up run says so, and its simulated seconds
  const speedup = view.info && view.info.speedup;
  $("cursor-label").textContent = `${(view.cursor - view.t0).toFixed(1)} s of ${span.toFixed(1)} s` +
    (speedup && speedup !== 1 ? ` wall clock (run at ${speedup}x: about ${((view.cursor - view.t0) * speedup).toFixed(0)} s simulated)` : "");
  const ms = view.cursor * 1000;  // a Date holds +-8.64e15 ms: a t_s past that is not a time of day
  $("clock").textContent = Math.abs(ms) <= 8.64e15 ? new Date(ms).toISOString().replace("T", " ").slice(0, 21) + " UTC" : "";
  const ticks = $("ticks");
  if (ticks.dataset.count !== String(view.events.length) || ticks.dataset.span !== span.toFixed(1)) {
    ticks.dataset.count = view.events.length; ticks.dataset.span = span.toFixed(1);
    ticks.setAttribute("viewBox", `0 0 ${Math.max(span, 1)} 1`);
    ticks.replaceChildren();
    for (const ev of view.events) {
      const tick = el("rect", { x: ev.t - view.t0, y: 0, width: Math.max(span, 1) / 400, height: 1, fill: ev.fault ? "#c0392b" : "#7f8c8d" }, ticks);
      el("title", {}, tick).textContent = ev.text;
    }
  }
}
function draw() {
  if (view.dirty) {
    view.dirty = false;
    const here = drawMap(view.cursor);
    drawPanels(view.cursor, here);
    drawTimeline();
  }
}
let lastFrame = null;
function tick(now) {
  requestAnimationFrame(tick);  // first: a drawing error must not stop the page
  if (view.playing && lastFrame != null) {
    view.cursor = Math.min(view.cursor + ((now - lastFrame) / 1000) * view.speed, view.t1);
    if (view.cursor >= view.t1 && !view.info.live) { view.playing = false; $("play").textContent = "play"; }
    view.dirty = true;
  }
  lastFrame = now;
  draw();  // at most once per animation frame, whatever the number of records that arrived
}
function seek(t) { view.follow = false; view.cursor = Math.max(view.t0, Math.min(t, view.t1)); view.dirty = true; draw(); }
view.seek = seek;

function showNotes(info) {
  const notes = [...view.notes, ...info.missing.map((m) => "missing: " + m), ...info.problems];
  $("notes-summary").textContent = notes.length ? `${notes.length} thing(s) missing or damaged` : "nothing missing";
  $("notes-list").innerHTML = notes.map((n) => `<li>${esc(n)}</li>`).join("");
}

async function getJSON(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: ${response.status} ${(await response.text()).slice(0, 200)}`);
  return [await response.json(), response];
}
async function fetchRecords() {  // every frame, a bounded page at a time (the server says when more follow)
  const all = [];
  let after = -1;
  for (;;) {
    const [frames, response] = await getJSON("/api/records?after=" + after);
    for (const f of frames) all.push(f);
    if (!frames.length || response.headers.get("X-More-Records") !== "yes") return all;
    after = frames[frames.length - 1].s;
  }
}
function startAt(text) {  // ?at=end or seconds from the start, as a cursor inside the run (and what was changed)
  const given = JSON.stringify(text.slice(0, 40));
  if (text === "end") return [view.t1, null];
  const s = /^\s*$/.test(text) ? NaN : Number(text);
  const span = view.t1 - view.t0;
  if (!Number.isFinite(s)) return [view.t0, `?at=${given}: expected seconds from the run's start or "end"; showing the start`];
  if (s < 0) return [view.t0, `?at=${given}: before the run's start; showing the start`];
  if (s > span) return [view.t1, `?at=${given}: after the run's end (${span.toFixed(1)} s); showing the end`];
  return [view.t0 + s, null];
}

async function start() {
  const records = fetchRecords();  // both at once: a replay's records are most of the wait
  setInfo((await getJSON("/api/state"))[0]);
  $("title").textContent = view.info.title;
  $("mode").textContent = view.info.live ? "live" : "replay";
  $("mode").classList.toggle("live", view.info.live);
  showNotes(view.info);
  for (const [, points] of missionsOf(view.info)) points.forEach((q) => grow(q[0], q[1]));
  ingest(await records);
  const query = new URLSearchParams(location.search);
  const start = query.get("at");  // ?at=end or seconds from the start
  const snapshot = query.has("snapshot");  // no stream: what is there now (a screenshot's headless browser
  // waits for the network to be idle, which an open stream never is)
  if ((!view.info.live || start !== null) && isFinite(view.t0)) {
    view.follow = false;
    const [cursor, note] = start === null ? [view.t0, null] : startAt(start);
    view.cursor = cursor;
    if (note) { view.notes.push(note); showNotes(view.info); }
  }
  $("cursor").addEventListener("input", (e) => seek(view.t0 + parseFloat(e.target.value)));
  $("play").addEventListener("click", () => {
    view.playing = !view.playing; view.follow = false;
    if (view.playing && view.cursor >= view.t1) view.cursor = view.t0;
    $("play").textContent = view.playing ? "pause" : "play";
  });
  $("speed").addEventListener("change", (e) => { view.speed = parseFloat(e.target.value); });
  $("follow").addEventListener("click", () => { view.follow = true; view.playing = false; view.cursor = view.t1; view.dirty = true; });
  if (view.info.live && !snapshot) {
    const stream = new EventSource("/api/stream?after=" + view.lastSeq);
    stream.addEventListener("records", (e) => ingest(JSON.parse(e.data)));
    stream.addEventListener("end", () => stream.close());
    setInterval(async () => {  // missions and notes change as files appear
      const [info] = await getJSON("/api/state");
      const missionsChanged = JSON.stringify(info.missions) !== JSON.stringify(view.info.missions);
      setInfo(info); showNotes(info);
      if (missionsChanged) {
        for (const [, points] of missionsOf(info)) points.forEach((q) => grow(q[0], q[1]));
        view.mapKey = null; view.dirty = true;
      }
    }, 2000);
  }
  view.dirty = true;
  draw();  // the slider has its range before anyone can scrub it
  document.body.dataset.ready = "1";
  requestAnimationFrame(tick);
}
start().catch((err) => {  // said on the page, never a page left "loading"
  $("mode").textContent = "error";
  $("notes-summary").textContent = "the view could not load: " + err.message;
  document.body.dataset.error = err.message;
});
