// millsense dashboard: tiles, live plots and the reset exchange, with nothing but the browser.
// Live updates come as Server-Sent Events from /events (server.py); the reset runs the
// challenge-response of docs/zenoh.md here, so the token never leaves this page.
"use strict";

const RING = 600;          // revolutions kept per machine, as on the server (book.py)
const ALARMS_SHOWN = 50;
const LATENCY_KEPT = 50000;
const DRAW_EVERY_MS = 250; // plots are redrawn at most 4 times a second; the numbers at once
const LIMIT_LINES = 8;     // learned-limits warnings shown per tile
// The alarm levels that trip the interlock (pipeline/alarms.py; envelope alarms as [learning] says).
const TRIP_LEVELS = ["overload", "crash", "tool_breakage", "envelope_high", "envelope_low", "expected_high", "expected_low"];

const machines = new Map(); // name -> {tile, estimates, dirty, lastAlarm, hold}
let resetOffered = false;

// When each estimate landed on the page (ms since the epoch), beside the daemon's `t`:
// bench/dashboard_latency.py reads it to measure publication -> page.
window.millsenseLatency = [];

function $(root, sel) { return root.querySelector(sel); }
function fmt(v, digits, unit) {
  return (typeof v === "number" && isFinite(v)) ? v.toFixed(digits) + (unit ? " " + unit : "") : "–";
}

function tileOf(name) {
  let m = machines.get(name);
  if (m) return m;
  const node = document.getElementById("tile").content.firstElementChild.cloneNode(true);
  node.dataset.machine = name;
  $(node, ".name").textContent = name;
  const form = $(node, "form.reset");
  if (!resetOffered) form.dataset.off = "";
  form.addEventListener("submit", (ev) => { ev.preventDefault(); runReset(name, form); });
  const none = document.getElementById("none-yet");
  if (none) none.remove();
  const box = document.getElementById("machines");
  // Tiles in name order, so a screen reads the same every day.
  const after = [...box.children].find((c) => c.dataset.machine > name);
  box.insertBefore(node, after || null);
  m = { tile: node, estimates: [], dirty: true, lastAlarm: null, hold: null };
  machines.set(name, m);
  return m;
}

function setPresence(m, alive, since) {
  m.tile.classList.toggle("gone", !alive);
  $(m.tile, ".presence").textContent = alive ? "alive" : "gone" + (since ? " since " + new Date(since * 1000).toLocaleTimeString() : "");
}

function showEstimate(m, e) {
  const t = m.tile;
  $(t, ".f-rpm").textContent = fmt(e.spindle_rpm, 0, "rpm") + (e.cutting ? " cutting" : "");
  $(t, ".f-torque").textContent = e.valid === false ? "invalid (" + (e.invalid || "?") + ")" : fmt(e.torque_nm, 2, "N·m");
  $(t, ".f-force").textContent = fmt(e.force_n, 0, "N");
  $(t, ".f-depths").textContent = fmt(e.axial_depth_mm, 2) + " / " + fmt(e.radial_depth_mm, 2) + " mm"
    + (e.depth_status && e.depth_status !== "ok" ? " (" + e.depth_status + ")" : "");
  if ("program" in e) {
    const ctx = [e.program, e.tool, e.operation].map((v) => (v === null || v === undefined) ? "–" : v).join(" / ");
    $(t, ".f-context").textContent = ctx + (typeof e.process_rev === "number" ? " rev " + e.process_rev : "");
  }
  if (typeof e.feed_override_pct === "number") {
    let s = fmt(e.feed_override_pct, 0, "%");
    if (e.afc && e.afc.state && e.afc.state !== "off" && e.afc.state !== "unavailable") {
      s += " · AFC " + e.afc.state + " cmd " + fmt(e.afc.override_pct, 0, "%");
    }
    $(t, ".f-afc").textContent = s;
  }
}

function showStatus(m, s) {
  const t = m.tile;
  $(t, ".f-state").textContent = (s.state || "–") + (s.daq_link === "down" ? " · DAQ down" : "");
  $(t, ".f-interlock").textContent = s.interlock || "–";
  const alarm = typeof s.alarm === "string" ? s.alarm : (s.alarm && s.alarm.level) || null;
  if (alarm !== null) setAlarm(m, alarm);
  holdFromStatus(m, s);
  showLimits(m, s.learned_limits);
}

// ---------------------------------------------------------------------------- the held feed
// The tile follows the latched interlock, not the alarm: an overload clears 0.2 s after the hold
// took the load off, and the machine stays held until a reset and the DAQ's own STATUS saying so
// (status.interlock_detail.daq_feed_hold). Same rules as pipeline/status.py, hold_of.
function holdOfStatus(s) {
  const d = (s.interlock_detail && typeof s.interlock_detail === "object") ? s.interlock_detail : {};
  const since = typeof d.since === "number" ? d.since : null;
  if (s.interlock === "feed_hold") return { reason: (typeof d.reason === "string" && d.reason) || "latched", since };
  if (s.interlock === "held_by_device") {
    return { reason: "by the DAQ, not set by this run" + (d.watchdog_tripped ? " (its watchdog tripped)" : ""), since };
  }
  if (d.daq_feed_hold === true) return { reason: "release not yet confirmed by the DAQ", since };
  return null;
}

function holdFromStatus(m, s) {
  const hold = holdOfStatus(s);
  // A status older than the alarm that showed the hold does not release it (they travel apart).
  // (An alarm's t is its sample's time; a status built within 1 s of it may predate the trip's decision.)
  if (!hold && m.hold && m.hold.alarmT !== null && typeof s.t === "number" && s.t < m.hold.alarmT + 1.0) return;
  m.hold = hold ? { ...hold, alarmT: null } : null;
  showHold(m);
}

function holdFromAlarm(m, a) {
  // An alarm sent while the daemon holds the feed says so before the next status does.
  if (a.interlock !== "feed_hold" || m.hold) return;
  const t = typeof a.t === "number" ? a.t : null;
  // The interlock's reason for a trip (runtime/interlock.py trip_reason): the alarm, its value and the limit crossed.
  const side = (a.level === "envelope_low" || a.level === "expected_low") ? " < " : " > ";
  const trip = TRIP_LEVELS.includes(a.level); // a warning or a clear sent while held: held, not why
  const reason = trip ? a.level + " " + a.quantity + " " + shown(a.value) + side + shown(a.limit) : "latched";
  m.hold = { reason, since: t, alarmT: t };
  showHold(m);
}

function shown(x) {
  // a number as the interlock's reason shows it (runtime/interlock.py `_shown`): to 3 decimals, a whole one with ".0"
  if (typeof x !== "number" || !isFinite(x)) return String(x);
  const r = Math.round(x * 1000) / 1000;
  return Number.isInteger(r) ? r.toFixed(1) : String(r);
}

function showHold(m) {
  const line = $(m.tile, ".f-held");
  m.tile.classList.toggle("held", !!m.hold);
  if (!m.hold) { line.hidden = true; line.textContent = ""; return; }
  line.hidden = false;
  line.textContent = "feed held: " + m.hold.reason
    + (m.hold.since !== null ? ", since " + new Date(m.hold.since * 1000).toLocaleTimeString() : "");
}

// Learned limits set aside (learning afresh) or with envelope_low off: a warning line on the tile.
// `learned_limits` is absent from older daemons' status: nothing shown then.
function showLimits(m, ll) {
  const box = $(m.tile, ".f-limits");
  const lines = [];
  if (ll && typeof ll === "object") {
    for (const e of Array.isArray(ll.set_aside) ? ll.set_aside : []) {
      const key = e && typeof e === "object" ? e.key : e;
      if (typeof key === "string") lines.push("limits set aside: " + key + " (learning afresh)"
        + (e && typeof e.reason === "string" && e.reason ? ": " + e.reason : ""));
    }
    for (const key of Array.isArray(ll.low_off) ? ll.low_off : []) {
      if (typeof key === "string") lines.push("envelope_low off: " + key);
    }
  }
  const more = lines.length - LIMIT_LINES;  // a daemon with many keys: the tile stays readable
  if (more > 0) lines.splice(LIMIT_LINES, lines.length, "… and " + more + " more (millsense limits list)");
  box.hidden = lines.length === 0;
  box.textContent = lines.join("\n");
}

function setAlarm(m, level) {
  const hot = level && level !== "clear" && level !== "none" && level !== "ok";
  m.tile.classList.toggle("alarm", hot && level !== "warning");
  m.tile.classList.toggle("warning", level === "warning");
  $(m.tile, ".f-alarm").textContent = level || "–";
}

function showAlarm(m, a) {
  setAlarm(m, a.level);
  if (a.interlock) $(m.tile, ".f-interlock").textContent = a.interlock;
  holdFromAlarm(m, a);
  addAlarmLine(a);
}

// What an alarm line says after its level: a clear names what it ends, never "value > limit".
function alarmWords(a) {
  if (!a.quantity) return "";
  if (a.level === "clear") {
    const parts = [];
    if (a.was) parts.push("was " + a.was);
    if (typeof a.limit === "number" && isFinite(a.limit)) parts.push("limit " + fmt(a.limit, 2));
    return " " + a.quantity + (parts.length ? " (" + parts.join(", ") + ")" : "");
  }
  if (typeof a.value !== "number" && typeof a.limit !== "number") return " " + a.quantity; // daq_lost: no number
  // the physics' expected band (issue 41): its one-line reason says what was expected and what was measured
  if ((a.level === "expected_high" || a.level === "expected_low") && typeof a.reason === "string") return " " + a.reason;
  const side = (a.level === "envelope_low" || a.level === "expected_low") ? " < " : " > ";
  return " " + a.quantity + " " + fmt(a.value, 2) + side + fmt(a.limit, 2);
}

function addAlarmLine(a) {
  const list = document.getElementById("alarms");
  const li = document.createElement("li");
  li.className = a.level === "clear" ? "clear" : "hot";
  const when = typeof a.t === "number" ? new Date(a.t * 1000).toLocaleTimeString() : "";
  const lvl = document.createElement("span");
  lvl.className = "lvl";
  lvl.textContent = a.level;
  li.append(when + " " + a.machine + " ", lvl, alarmWords(a) + (a.interlock ? " · " + a.interlock : ""));
  list.prepend(li);
  while (list.children.length > ALARMS_SHOWN) list.lastElementChild.remove();
}

function showProcess(m, p) {
  $(m.tile, ".f-process").textContent = (p.key || "–") + " " + (p.verdict || "") + (typeof p.energy_ratio === "number" ? " energy ×" + p.energy_ratio.toFixed(2) : "");
  if (typeof p.tool_wear_pct === "number") $(m.tile, ".f-wear").textContent = fmt(p.tool_wear_pct, 1, "%") + " (tool " + p.tool + ", " + p.tool_processes + " processes)";
}

function addEstimate(m, e) {
  const last = m.estimates[m.estimates.length - 1];
  if (last && typeof e.t === "number" && e.t <= last.t) return; // already here (a snapshot after a reconnect)
  m.estimates.push(e);
  if (m.estimates.length > RING) m.estimates.splice(0, m.estimates.length - RING);
  m.dirty = true;
}

function apply(u) {
  const m = tileOf(u.machine);
  if (u.kind === "estimate") {
    addEstimate(m, u.payload);
    showEstimate(m, u.payload);
    const lat = window.millsenseLatency;
    lat.push([u.machine, u.payload.rev, u.payload.t, Date.now()]);
    if (lat.length > LATENCY_KEPT) lat.splice(0, lat.length - LATENCY_KEPT);
  } else if (u.kind === "alarm") showAlarm(m, u.payload);
  else if (u.kind === "status") showStatus(m, u.payload);
  else if (u.kind === "process") showProcess(m, u.payload);
  else if (u.kind === "alive") setPresence(m, true);
  else if (u.kind === "gone") setPresence(m, false, u.t);
}

function applySnapshot(snap) {
  for (const s of snap.machines) {
    const m = tileOf(s.machine);
    setPresence(m, s.alive, s.gone_since);
    for (const e of s.estimates) addEstimate(m, e);
    if (s.estimates.length) showEstimate(m, s.estimates[s.estimates.length - 1]);
    if (s.status) showStatus(m, s.status);
    if (s.process) showProcess(m, s.process);
    if (s.alarms.length) setAlarm(m, s.alarms[s.alarms.length - 1].level);
  }
  document.getElementById("alarms").textContent = "";
  for (const a of snap.recent_alarms) addAlarmLine(a);
}

// ---------------------------------------------------------------------------- plots
function plot(canvas, series, band) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, pad = 2;
  ctx.clearRect(0, 0, w, h);
  const n = Math.max(1, ...series.map((s) => s.values.length));
  let lo = Infinity, hi = -Infinity;
  const seen = (v) => { if (typeof v === "number" && isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); } };
  series.forEach((s) => s.values.forEach(seen));
  if (band) { band.low.forEach(seen); band.high.forEach(seen); }
  if (!isFinite(lo)) return;
  if (hi - lo < 1e-9) { hi += 1; lo -= 1; }
  const x = (i) => pad + (w - 2 * pad) * (n === 1 ? 1 : i / (n - 1));
  const y = (v) => h - pad - (h - 2 * pad) * (v - lo) / (hi - lo);
  if (band) { // the learned envelope: a filled band where both edges are known
    ctx.fillStyle = "#c8e6c9";
    for (let i = 1; i < n; i++) {
      const a = [band.low[i - 1], band.high[i - 1], band.low[i], band.high[i]];
      if (a.every((v) => typeof v === "number")) {
        ctx.beginPath();
        ctx.moveTo(x(i - 1), y(a[1])); ctx.lineTo(x(i), y(a[3])); ctx.lineTo(x(i), y(a[2])); ctx.lineTo(x(i - 1), y(a[0]));
        ctx.closePath(); ctx.fill();
      }
    }
  }
  for (const s of series) {
    ctx.strokeStyle = s.color; ctx.lineWidth = 1.5; ctx.beginPath();
    let pen = false;
    s.values.forEach((v, i) => {
      if (typeof v !== "number") { pen = false; return; }
      if (pen) ctx.lineTo(x(i), y(v)); else ctx.moveTo(x(i), y(v));
      pen = true;
    });
    ctx.stroke();
  }
  ctx.fillStyle = "#555"; ctx.font = "10px sans-serif";
  ctx.fillText(hi.toPrecision(3), 4, 11); ctx.fillText(lo.toPrecision(3), 4, h - 4);
}

function drawDirty() {
  for (const m of machines.values()) {
    if (!m.dirty) continue;
    m.dirty = false;
    const es = m.estimates, col = (k) => es.map((e) => e[k]);
    const band = es.some((e) => typeof e.envelope_high_nm === "number")
      ? { low: col("envelope_low_nm"), high: col("envelope_high_nm") } : null;
    plot($(m.tile, ".p-torque"), [{ values: col("torque_nm"), color: "#d84315" }], band);
    plot($(m.tile, ".p-force"), [{ values: col("force_n"), color: "#37474f" }]);
    plot($(m.tile, ".p-depths"), [{ values: col("axial_depth_mm"), color: "#1565c0" }, { values: col("radial_depth_mm"), color: "#8e24aa" }]);
  }
}

// ---------------------------------------------------------------------------- the reset
const enc = new TextEncoder();
function hex(bytes) { return [...new Uint8Array(bytes)].map((b) => b.toString(16).padStart(2, "0")).join(""); }

async function hmacHex(token, lines) {
  // HMAC-SHA256 keyed with the token's UTF-8 bytes over the lines joined by "\n" (docs/zenoh.md).
  const key = await crypto.subtle.importKey("raw", enc.encode(token), { name: "HMAC", hash: "SHA-256" }, false, ["sign"]);
  return hex(await crypto.subtle.sign("HMAC", key, enc.encode(lines.join("\n"))));
}

async function relay(machine, body) {
  const r = await fetch("/api/reset/" + encodeURIComponent(machine), {
    method: "POST", headers: { "Content-Type": "application/json", "X-Millsense": "reset" }, body: JSON.stringify(body),
  });
  const answer = await r.json();
  if (!answer.ok) throw new Error(answer.error || "the dashboard refused");
  return answer.replies;
}

function say(out, text, good) {
  out.textContent = text;
  out.className = "reset-result " + (good ? "ok" : "bad");
}

async function runReset(machine, form) {
  const input = $(form, ".reset-token"), out = $(form, ".reset-result"), button = $(form, ".reset-go");
  const token = input.value; // lives only in this call: never stored, never sent
  input.value = "";
  button.disabled = true;
  try {
    say(out, "asking " + machine + "…", true);
    say(out, await resetExchange(machine, token), true);
  } catch (err) {
    say(out, err.message, false);
  } finally {
    button.disabled = false;
  }
}

async function resetExchange(machine, token) {
  const cn = hex(crypto.getRandomValues(new Uint8Array(32)));
  const replies = await relay(machine, { step: "challenge", client_nonce: cn });
  if (!replies.length) throw new Error("no daemon answered on millsense/" + machine + "/cmd/reset");
  const refused = replies.find((r) => !r.ok);
  if (refused) throw new Error(machine + " refused: " + ((refused.body && refused.body.error) || "no reason"));
  const good = replies.map((r) => r.body).filter((b) => b && b.step === "challenge" && b.machine === machine
    && b.command === "reset" && ["token", "open"].includes(b.policy) && /^[0-9a-f]{64}$/.test(b.server_nonce || ""));
  if (good.length !== replies.length) throw new Error("the answer is not a millsense challenge: nothing was sent");
  if (new Set(good.map((b) => b.server_nonce)).size > 1) throw new Error("several programs answer as " + machine + ": nothing was sent");
  const ch = good[0], sn = ch.server_nonce, policy = ch.policy;
  if (ch.paused_s) throw new Error(machine + " refuses commands for " + ch.paused_s + " s more (failed proofs); reset at the machine");
  if (policy === "token" && !token) throw new Error(machine + " needs the reset token: type it");
  if (policy === "open" && token) throw new Error(machine + " says commands are open to anyone, yet a token was typed: not the daemon you expect? Nothing was sent");
  const prove = { step: "prove", client_nonce: cn, server_nonce: sn, args: {} };
  if (policy === "token") prove.mac = await hmacHex(token, ["millsense-cmd-v1", "reset", machine, sn, cn, "{}"]);
  const answers = await relay(machine, prove);
  if (!answers.length) throw new Error("no answer to the proof: the reset may or may not have run; watch the interlock");
  for (const a of answers) {
    const b = a.body;
    if (!b || typeof b.result !== "string") {
      if (b && b.error) throw new Error(machine + " refused: " + b.error);
      continue;
    }
    if (policy === "token") {
      const expected = await hmacHex(token, ["millsense-reply-v1", "reset", machine, sn, cn, b.result]);
      if (b.server_mac !== expected) throw new Error("the answer failed the daemon's MAC: the outcome is unknown (a wrong token, or not the real daemon); watch the interlock, and see audit.log at the machine");
    }
    const result = JSON.parse(b.result);
    if (!a.ok || result.ok === false) throw new Error(machine + " declined: " + (result.error || "no reason"));
    return machine + ": " + (result.interlock || "reset done") + (policy === "open" ? " (unverified: policy open)" : " (verified)");
  }
  throw new Error("the answer is not a millsense command reply");
}

// ---------------------------------------------------------------------------- start
async function start() {
  try {
    const info = await (await fetch("/api/info")).json();
    resetOffered = info.reset_offered && window.isSecureContext && !!(window.crypto && crypto.subtle);
  } catch (err) { resetOffered = false; }
  if (!resetOffered) {
    document.getElementById("secure-note").textContent =
      "Reset not offered: it needs HTTPS (--cert, --key) or localhost, where the browser allows its cryptography.";
  }
  const link = document.getElementById("link");
  const events = new EventSource("/events");
  events.onopen = () => { link.textContent = "live"; link.className = "link up"; };
  events.onerror = () => { link.textContent = "reconnecting…"; link.className = "link down"; };
  events.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.kind === "snapshot") applySnapshot(msg);
    else if (msg.kind === "batch") msg.updates.forEach(apply);
  };
  setInterval(drawDirty, DRAW_EVERY_MS);
}

start();
