// hwgw's page: the status every 2 s from /api/status, the listed ports' values as they
// change from /api/live (Server-Sent Events), a plot of each, and, when the deployment
// allows it, a form that sets a listed port with the deployment's token.
"use strict";

const HISTORY = 300; // samples kept per plot
const series = new Map(); // port -> [{t, v}]

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

function row(cells) {
  const tr = el("tr");
  for (const c of cells) {
    if (c instanceof Node) { const td = el("td"); td.appendChild(c); tr.appendChild(td); }
    else if (typeof c === "number") tr.appendChild(el("td", fmt(c), "num"));
    else tr.appendChild(el("td", c === null || c === undefined ? "" : String(c)));
  }
  return tr;
}

function fmt(x) {
  if (typeof x !== "number") return String(x);
  if (Number.isInteger(x)) return String(x);
  return x.toPrecision(6);
}

function fill(id, rows) {
  const body = document.querySelector("#" + id + " tbody");
  body.replaceChildren(...rows);
}

function counters(obj) {
  return el("div", Object.entries(obj || {}).map(([k, v]) =>
    k + " " + (typeof v === "object" ? JSON.stringify(v) : v)).join("\n"), "counters");
}

function showStatus(s) {
  const h = document.getElementById("health");
  h.textContent = s.health === "ok" ? "healthy" : s.health;
  h.className = "badge " + (s.health === "ok" ? "ok" : "bad");
  document.getElementById("updated").textContent = "status at " + new Date().toLocaleTimeString();
  fill("devices", s.devices.map(d => {
    const st = el("span", d.status, d.status);
    return row([d.name, d.interface, st, d.age_s === null ? "" : d.age_s, d.last_error]);
  }));
  fill("components", s.components.map(c => row([c.name, c.state, c.steps, c.overruns,
    c.step_mean_us, c.lateness_p99_us, c.healthy ? "yes" : "no", c.realtime ? "yes" : "no"])));
  fill("cards", s.cards.map(c => row([c.name, c.driver, c.bus, counters(c.counters),
    c.outputs.written, c.outputs.watchdog_trips])));
  fill("servers", (s.servers || []).map(v => row([v.name, v.bus, counters(v.counters)])));
  histograms(s.components);
}

// Each periodic component's lateness: bucket i counts wake-ups 2^i..2^(i+1) ns late.
function histograms(components) {
  const box = document.getElementById("histograms");
  const parts = [];
  for (const c of components) {
    const h = c.lateness_histogram || [];
    const total = h.reduce((a, b) => a + b, 0);
    if (total === 0) continue;
    const wrap = el("div", undefined, "hist");
    wrap.appendChild(el("span", c.name + " (" + total + " wake-ups, p99 " + fmt(c.lateness_p99_us) + " µs)"));
    const cv = el("canvas");
    cv.width = 320; cv.height = 120;
    drawHistogram(cv, h);
    wrap.appendChild(cv);
    parts.push(wrap);
  }
  box.replaceChildren(...parts);
}

function drawHistogram(cv, h) {
  const g = cv.getContext("2d");
  const first = Math.max(0, h.findIndex(n => n > 0) - 1);
  const shown = h.slice(first);
  const max = Math.max(...shown.map(n => Math.log10(n + 1)), 1);
  const w = (cv.width - 10) / Math.max(shown.length, 1);
  g.fillStyle = "#1565c0";
  shown.forEach((n, i) => {
    const bh = (Math.log10(n + 1) / max) * (cv.height - 24);
    g.fillRect(5 + i * w, cv.height - 16 - bh, Math.max(w - 2, 1), bh);
  });
  g.fillStyle = "#455a64";
  g.font = "10px sans-serif";
  g.fillText(label(first), 2, cv.height - 4);
  g.fillText(label(first + shown.length), cv.width - 42, cv.height - 4);
}

function label(i) {
  const ns = Math.pow(2, i);
  if (ns >= 1e6) return (ns / 1e6).toPrecision(3) + " ms";
  if (ns >= 1e3) return (ns / 1e3).toPrecision(3) + " µs";
  return ns + " ns";
}

async function refresh() {
  try {
    const r = await fetch("/api/status", { cache: "no-store" });
    if (r.ok) showStatus(await r.json());
  } catch (e) {
    document.getElementById("health").textContent = "unreachable";
  }
}

function plot(cv, points) {
  const g = cv.getContext("2d");
  g.clearRect(0, 0, cv.width, cv.height);
  const ys = points.map(p => p.v).filter(v => typeof v === "number");
  if (ys.length < 2) return;
  let lo = Math.min(...ys), hi = Math.max(...ys);
  if (hi === lo) { hi += 1; lo -= 1; }
  g.strokeStyle = "#1565c0";
  g.beginPath();
  points.forEach((p, i) => {
    const x = (i / (HISTORY - 1)) * cv.width;
    const y = cv.height - 2 - ((p.v - lo) / (hi - lo)) * (cv.height - 4);
    if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
  });
  g.stroke();
}

function numeric(v) {
  if (typeof v === "number") return v;
  if (typeof v === "boolean") return v ? 1 : 0;
  return undefined;
}

async function live() {
  const r = await fetch("/api/ports", { cache: "no-store" });
  if (!r.ok) return;
  const info = await r.json();
  const body = document.querySelector("#live tbody");
  const cells = new Map();
  for (const p of info.ports) {
    const name = p.component + "." + p.port;
    const value = el("td", "…", "num");
    value.id = "value-" + name;
    const cv = el("canvas");
    cv.width = 300; cv.height = 40;
    const tr = el("tr");
    tr.appendChild(el("td", name));
    tr.appendChild(value);
    const td = el("td"); td.appendChild(cv); tr.appendChild(td);
    body.appendChild(tr);
    cells.set(name, { value, cv });
    series.set(name, []);
  }
  if (info.ports.length === 0) document.getElementById("live-section").hidden = true;
  const writable = info.ports.filter(p => p.input);
  if (info.writes && writable.length > 0) setForm(writable);
  const events = new EventSource("/api/live");
  events.onmessage = (m) => {
    const values = JSON.parse(m.data).values;
    for (const [name, v] of Object.entries(values)) {
      const c = cells.get(name);
      if (!c) continue;
      c.value.textContent = typeof v === "object" && v !== null ? JSON.stringify(v) : fmt(v);
      const s = series.get(name);
      const n = numeric(v);
      if (n !== undefined) { s.push({ v: n }); if (s.length > HISTORY) s.shift(); plot(c.cv, s); }
    }
  };
}

function setForm(ports) {
  const form = document.getElementById("set-form");
  const select = document.getElementById("set-port");
  for (const p of ports) {
    const o = el("option", p.component + "." + p.port);
    o.value = JSON.stringify(p);
    select.appendChild(o);
  }
  form.hidden = false;
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const p = JSON.parse(select.value);
    const text = document.getElementById("set-value").value;
    let value;
    try { value = JSON.parse(text); } catch (e) { value = text; }
    const token = document.getElementById("set-token").value;
    const out = document.getElementById("set-result");
    out.textContent = "…";
    const r = await fetch("/api/set", {
      method: "POST",
      headers: { "content-type": "application/json", "authorization": "Bearer " + token },
      body: JSON.stringify({ component: p.component, port: p.port, value: value }),
    });
    const answer = await r.json().catch(() => ({}));
    out.textContent = r.ok ? "set" : "refused: " + (answer.error || r.status);
    out.dataset.status = String(r.status);
  });
}

document.addEventListener("DOMContentLoaded", () => {
  refresh();
  setInterval(refresh, 2000);
  live();
});
