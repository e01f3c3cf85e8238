// exolink dashboard page. The server decimates (25 frames/s by default); this file draws what
// arrives, once per animation frame, and sends commands as `exolink` command lines that the
// server parses with the CLI's own parser. No framework, no build step.
"use strict";

const $ = (sel) => document.querySelector(sel);
const $$ = (sel) => Array.from(document.querySelectorAll(sel));
const COLORS = ["#dc2626", "#2563eb", "#16a34a", "#f59e0b", "#7c3aed", "#0891b2"];

const S = {
  role: null, joints: [], windowS: 10, ws: null, triggers: [], lastTrigger: null,
  t: [], pos: [[], [], [], [], [], []], eff: [[], [], [], [], [], []], dirty: false,
  latestJs: null, pattern: null, patternPoints: null, patternFile: null, status: null,
  record: null,
};
// Read by the browser tests and the benchmark: updates drawn and CAN frame -> drawn latency.
window.exolinkStats = { frames: 0, drawn: 0, lat: [], errors: 0 };

// --- safety header ---------------------------------------------------------------------------

function notice(text, ok = false) {
  const n = $("#notice");
  n.textContent = text;
  n.className = "notice" + (ok ? " ok" : "");
  n.hidden = !text;
  if (ok) setTimeout(() => { if (n.textContent === text) n.hidden = true; }, 4000);
}

function showWatchdog(wd) {
  if (!wd || !wd.state) return;
  const b = $("#banner");
  const state = String(wd.state);
  b.className = "banner " + (["armed", "tripped"].includes(state) ? state : "disarmed");
  $("#wd-state").textContent = state.toUpperCase();
  const why = state === "armed" ? "" : [wd.reason, wd.detail].filter(Boolean).join(": ");
  $("#wd-why").textContent = why ? "(" + why + ")" : "";
}

// This page's token (the server puts a fresh one in each page it serves): every command and
// the live socket carry it, so a page from elsewhere, which cannot read it, cannot drive them.
let token = $("meta[name=exolink-token]").content;

// A token the server no longer knows (it was restarted): this page's own fresh copy gives a new
// one. Another site's page cannot do this: the server answers only to its own host names.
async function renewToken() {
  const r = await fetch("/", { cache: "no-store" });
  const html = new DOMParser().parseFromString(await r.text(), "text/html");
  token = html.querySelector("meta[name=exolink-token]").content;
}

async function post(url, body) {
  const send = () => fetch(url, {
    method: "POST",
    headers: { "Content-Type": "application/json", "X-Exolink-Token": token },
    body: JSON.stringify(body),
  });
  let r = await send();
  if (r.status === 403) {
    const refusal = await r.json();
    if (!refusal.stale_token) return refusal;
    await renewToken();  // refused, so nothing was done: once more with the new token
    r = await send();
  }
  return r.json();
}

async function estop() {
  try {
    const r = await post("/api/estop", {});
    if (r.ok) { showWatchdog(r.reply); notice("E-STOP sent: motors disabled", true); }
    else notice("E-STOP: " + r.error);
  } catch (e) { notice("E-STOP failed to reach the dashboard server: " + e); }
}

// Every command: the CLI's words; motion asks first; the answer or refusal is shown.
async function run(argv, where = null) {
  let r = await post("/api/command", { argv });
  if (r.confirm) {
    if (!(await confirmDialog(r.confirm))) { show(where, "not sent (cancelled)", false); return r; }
    r = await post("/api/command", { argv, confirmed: true });
  }
  const text = (r.command || "exolink " + argv.join(" ")) + "\n" +
    (r.ok ? "ok " + JSON.stringify(r.reply) : "refused: " + r.error);
  show(where, text, r.ok);
  if (r.ok && argv[0] !== "timing") notice(text.split("\n")[0] + ": ok", true);
  else if (!r.ok) notice("refused: " + r.error);
  return r;
}

function show(where, text, ok) {
  const el = where || $("#cmd-result");
  el.textContent = text;
  el.dataset.ok = ok ? "1" : "0";
}

function confirmDialog(text) {
  const d = $("#confirm");
  $("#confirm-text").textContent = text;
  return new Promise((resolve) => {
    d.addEventListener("close", () => resolve(d.returnValue === "yes"), { once: true });
    d.showModal();
  });
}

$("#estop").addEventListener("click", estop);
document.addEventListener("keydown", (e) => { if (e.key === "Escape") { e.preventDefault(); estop(); } });
$("#arm").addEventListener("click", async () => {
  const r = await run(["arm"]);
  if (!r.ok) notice("Arm refused. Blockers:\n" + r.error.split(/;\s*/).join("\n"));
});
$("#disarm").addEventListener("click", () => run(["disarm"]));
$("#fire").addEventListener("click", () => run(["trigger", "fire"]));
for (const b of $$("button[data-argv]")) {
  b.addEventListener("click", () => run(JSON.parse(b.dataset.argv)));
}

// --- pages -----------------------------------------------------------------------------------

function route() {
  const page = (location.hash || "#live").slice(1);
  for (const s of $$(".page")) s.hidden = s.id !== "page-" + page;
  for (const a of $$("nav a")) a.classList.toggle("active", a.dataset.page === page);
  if (page === "live") resizePlots();
  if (page === "pattern") drawPattern();
}
window.addEventListener("hashchange", route);

// --- plots -----------------------------------------------------------------------------------

const plots = {};
window.exolinkPlots = plots;  // read by the browser tests

function triggerMarkers(u) {
  const ctx = u.ctx, { top, height } = u.bbox;
  ctx.save();
  ctx.strokeStyle = "#111"; ctx.setLineDash([4, 4]); ctx.lineWidth = 1;
  for (const t of S.triggers) {
    const x = u.valToPos(t, "x", true);
    if (x < u.bbox.left || x > u.bbox.left + u.bbox.width) continue;
    ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + height); ctx.stroke();
  }
  ctx.restore();
}

function makePlot(el, unit) {
  const series = [{}].concat(S.joints.map((j, i) => ({ label: j, stroke: COLORS[i], width: 1.5 })));
  return new uPlot({
    width: el.clientWidth || 600, height: 200, series,
    scales: { x: { time: true } }, axes: [{}, { label: unit, size: 50 }],
    legend: { live: false }, hooks: { draw: [triggerMarkers] },
  }, [[]].concat(S.joints.map(() => [])), el);
}

function setupPlots() {
  plots.angles = makePlot($("#plot-angles"), "deg");
  plots.torques = makePlot($("#plot-torques"), "N·m");
  const el = $("#plot-pattern");
  plots.pattern = new uPlot({
    width: el.clientWidth || 600, height: 220, scales: { x: { time: false } },
    series: [{ label: "point" }].concat(S.joints.map((j, i) => ({ label: j, stroke: COLORS[i] }))),
    legend: { live: false }, hooks: { draw: [patternMarker] },
  }, [[]].concat(S.joints.map(() => [])), el);
}

function resizePlots() {
  for (const [k, p] of Object.entries(plots)) {
    const el = $({
      angles: "#plot-angles", torques: "#plot-torques", pattern: "#plot-pattern",
      recording: "#plot-recording", maccepa: "#plot-maccepa",
    }[k]);
    if (el.clientWidth) p.setSize({ width: el.clientWidth, height: p.height });
  }
}
window.addEventListener("resize", resizePlots);
$("#window").addEventListener("change", (e) => { S.windowS = Number(e.target.value); S.dirty = true; });

function trim() {
  const cut = S.t.length ? S.t[S.t.length - 1] - 60 : 0;  // keep 60 s: the widest window
  let n = 0;
  while (n < S.t.length && S.t[n] < cut) n++;
  if (n) { S.t.splice(0, n); for (const a of S.pos.concat(S.eff)) a.splice(0, n); }
  S.triggers = S.triggers.filter((t) => t >= cut);
}

function windowed(arrs) {
  const last = S.t.length ? S.t[S.t.length - 1] : 0;
  let i = 0;
  while (i < S.t.length && S.t[i] < last - S.windowS) i++;
  return [S.t.slice(i)].concat(arrs.map((a) => a.slice(i)));
}

function draw() {
  requestAnimationFrame(draw);
  if (!S.dirty) return;
  S.dirty = false;
  const js = S.latestJs;
  if (js && !$("#page-live").hidden) {
    plots.angles.setData(windowed(S.pos));
    plots.torques.setData(windowed(S.eff));
  }
  if (js) {
    const rows = $$("#joints tbody tr");
    js.pos_deg.forEach((v, i) => {
      if (!rows[i]) return;
      rows[i].children[1].textContent = v.toFixed(1);
      rows[i].children[2].textContent = (js.eff_nm[i] ?? 0).toFixed(2);
    });
    const st = window.exolinkStats;
    st.drawn++;
    if (js.stamp_ns !== S.drawnStamp) {
      S.drawnStamp = js.stamp_ns;
      st.lat.push(Date.now() - js.stamp_ns / 1e6);
      if (st.lat.length > 20000) st.lat.splice(0, 10000);
    }
  }
  sinceTrigger();
}

function sinceTrigger() {
  if (S.lastTrigger == null) return;
  $("#since-trigger").textContent = ((Date.now() - S.lastTrigger / 1e6) / 1000).toFixed(1) + " s";
}
setInterval(sinceTrigger, 200);

// --- live data -------------------------------------------------------------------------------

function onLive(m) {
  window.exolinkStats.frames++;
  if (m.js) {
    S.latestJs = m.js;
    S.t.push(m.js.stamp_ns / 1e9);
    m.js.pos_deg.forEach((v, i) => S.pos[i].push(v));
    m.js.eff_nm.forEach((v, i) => S.eff[i].push(v));
    trim();
    S.dirty = true;
  }
  if (m.fs) {
    for (const s of $$("#feet span")) s.classList.toggle("on", !!m.fs[s.dataset.k]);
    $("#battery").textContent = m.fs.battery_volts.toFixed(2);
    $("#battery-raw").textContent = m.fs.battery_raw;
  }
  if (m.maccepa) {
    S.maccepa = Object.assign(S.maccepa || {}, m.maccepa);
    $("#maccepa").innerHTML = "";
    const dl = document.createElement("dl");
    dl.className = "kv";
    for (const [k, v] of Object.entries(S.maccepa).sort()) {
      const vals = Object.entries(v).filter(([f]) => !["stamp_ns", "board"].includes(f))
        .map(([f, x]) => f + " " + x).join("  ");
      kv(dl, k, vals);
    }
    $("#maccepa").appendChild(dl);
    maccepaPoints(m.maccepa);
  }
  if (m.rates) S.rates = m.rates;
}

// The thesis' positionsGraph: each MACCEPA board's link 2 and lever arm over the last 10 s.
const MAC = { boards: [], t: [], cols: [] };

function maccepaPoints(update) {
  const boards = Object.keys(update).filter((k) => k.endsWith("/state")).sort();
  if (!boards.length) return;
  for (const b of boards) {
    if (!MAC.boards.includes(b)) {  // a new board: start the plot again with its two lines
      MAC.boards.push(b); MAC.boards.sort();
      MAC.t = []; MAC.cols = MAC.boards.flatMap(() => [[], []]);
      if (plots.maccepa) { plots.maccepa.destroy(); delete plots.maccepa; }
    }
  }
  const stamp = update[boards[0]].stamp_ns / 1e9;
  MAC.t.push(stamp);
  MAC.boards.forEach((b, i) => {
    const v = update[b] || (S.maccepa || {})[b] || {};
    MAC.cols[2 * i].push(v.link_deg ?? null);
    MAC.cols[2 * i + 1].push(v.lever_deg ?? null);
  });
  while (MAC.t.length && MAC.t[0] < stamp - 10) { MAC.t.shift(); for (const c of MAC.cols) c.shift(); }
  const el = $("#plot-maccepa");
  if (!plots.maccepa) {
    const series = [{}].concat(MAC.boards.flatMap((b, i) => [
      { label: b.split("/")[0] + " link", stroke: COLORS[(2 * i) % 6] },
      { label: b.split("/")[0] + " lever", stroke: COLORS[(2 * i + 1) % 6], dash: [5, 3] },
    ]));
    plots.maccepa = new uPlot({
      width: el.clientWidth || 300, height: 160, series, scales: { x: { time: true } },
      axes: [{}, { label: "deg", size: 45 }], legend: { live: false },
    }, [MAC.t].concat(MAC.cols), el);
  } else if (!$("#page-live").hidden) {
    plots.maccepa.setData([MAC.t].concat(MAC.cols));
  }
}

function kv(dl, k, v) {
  const dt = document.createElement("dt"), dd = document.createElement("dd");
  dt.textContent = k; dd.textContent = v ?? "-";
  dl.append(dt, dd);
}

function onStatus(m) {
  if (m.error) {
    // A stale "ARMED" is worse than none: without an answer the state is unknown.
    $("#conn").textContent = "appliance: " + m.error;
    $("#banner").className = "banner unknown";
    $("#wd-state").textContent = "NO ANSWER FROM THE APPLIANCE";
    $("#wd-why").textContent = "(" + m.error + ")";
    return;
  }
  const s = m.status;
  if (!s) return;
  S.status = s;
  $("#conn").textContent = "online";
  showWatchdog(s.watchdog);
  const bus = $("#bus");
  bus.innerHTML = "";
  const wd = s.watchdog, b = s.bus;
  kv(bus, "bus", `${b.interface}:${b.channel} ${b.state || "n/a"}`);
  kv(bus, `${b.pulse || "pulse"} silent`, b.pulse_silent_s == null ? "-" : b.pulse_silent_s + " s");
  kv(bus, "joint_states", ((S.rates || {}).joint_states ?? "-") + " Hz");
  kv(bus, "watchdog trips", wd.trips);
  kv(bus, "read lag max", wd.read_lag_max_ms + " ms");
  kv(bus, "malformed", Object.values(wd.malformed || {}).reduce((a, x) => a + x, 0));
  kv(bus, "socket drops", wd.socket_dropped ?? "n/a");
  for (const n of s.nodes) {
    if (n.receive) kv(bus, n.name + " rx", `dropped ${n.receive.dropped ?? "n/a"} late ${n.receive.late} lag max ${n.receive.lag_max_ms} ms`);
  }
  kv(bus, "trigger", `${s.trigger.source} count ${s.trigger.count}`);
  if (s.clock) {  // the board's time against this laptop's (exolink clock sync sets it)
    const c = s.clock;
    kv(bus, "clock", `${c.source}, ${c.offset_ms >= 0 ? "+" : ""}${c.offset_ms} ms (+- ${c.error_ms})` +
      (c.warning ? ` WARNING: ${c.warning}` : ""));
    bus.lastChild.classList.toggle("warn", !!c.warning);
  }
  if (s.trigger.last_ns && S.lastTrigger == null) { S.lastTrigger = s.trigger.last_ns; }
  $("#trigger-count").textContent = s.trigger.count;
  renderNodes(s.nodes);
}

function onTrigger(m) {
  S.lastTrigger = m.stamp_ns;
  S.triggers.push(m.stamp_ns / 1e9);
  $("#trigger-count").textContent = m.count;
  S.dirty = true;
}

// --- nodes -----------------------------------------------------------------------------------

function renderNodes(nodes) {
  const tb = $("#nodes tbody");
  const sel = $("#log-node");
  if (sel.options.length !== nodes.length) {
    sel.innerHTML = "";
    for (const n of nodes) sel.add(new Option(n.name, n.name));
  }
  const rows = nodes.map((n) => {
    const tr = document.createElement("tr");
    tr.dataset.node = n.name;
    const state = n.enabled === false ? "disabled" : n.state;
    const cells = [n.name + (n.critical ? "*" : ""), state, n.pid ?? "-", n.restarts,
      n.heartbeat_age_s ?? "-", n.cpu_s ?? "-", n.rss_mb ?? "-", n.health || "-"];
    cells.forEach((c, i) => {
      const td = document.createElement("td");
      td.textContent = c;
      if (i === 1) td.className = "state-" + state;
      if (i >= 2 && i <= 6) td.classList.add("num");
      tr.appendChild(td);
    });
    const td = document.createElement("td");
    for (const action of ["restart", "stop", "start"]) {
      const b = document.createElement("button");
      b.textContent = action; b.className = "cmd admin small"; b.dataset.action = action;
      b.addEventListener("click", () => run([action, n.name]));
      td.appendChild(b);
    }
    tr.appendChild(td);
    return tr;
  });
  tb.replaceChildren(...rows);
  applyRole();
}

async function loadLogs() {
  const node = $("#log-node").value;
  const r = await (await fetch(`/api/logs?node=${encodeURIComponent(node)}&lines=200`)).json();
  const pre = $("#logs");
  pre.textContent = r.ok ? r.lines.join("\n") || "(no output)" : "refused: " + r.error;
  pre.scrollTop = pre.scrollHeight;
}
$("#log-load").addEventListener("click", loadLogs);
$("#params-load").addEventListener("click", async () => {
  const node = $("#log-node").value;
  const r = await (await fetch(`/api/params?node=${encodeURIComponent(node)}`)).json();
  $("#logs").textContent = r.ok ? JSON.stringify(r.params, null, 2) : "refused: " + r.error;
});
$("#f-param").addEventListener("submit", async (e) => {
  e.preventDefault();
  const f = e.target, node = $("#log-node").value;
  const r = await run(["params", node, "--set", val(f, "key"), val(f, "value")], $("#logs"));
  if (r.ok) $("#logs").textContent = `${node}.${r.reply.key} = ${JSON.stringify(r.reply.value)}`;
});
// Follow: the recent lines once, then each new line as the node writes it (over the socket).
async function follow() {
  const on = $("#log-follow").checked;
  if (on) await loadLogs();  // first, so a streamed line is never overwritten by the fetch
  if (S.ws && S.ws.readyState === 1) S.ws.send(JSON.stringify({ t: "follow", node: on ? $("#log-node").value : null }));
}
$("#log-follow").addEventListener("change", follow);
$("#log-node").addEventListener("change", () => { if ($("#log-follow").checked) follow(); });

function onLog(m) {
  if (!$("#log-follow").checked || m.node !== $("#log-node").value) return;
  const pre = $("#logs");
  const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
  pre.textContent += "\n" + m.line;
  if (pre.textContent.length > 200000) pre.textContent = pre.textContent.slice(-100000);
  if (atEnd) pre.scrollTop = pre.scrollHeight;
}

// --- commands --------------------------------------------------------------------------------

function val(form, name) { return form.elements[name].value.trim(); }

$("#f-joint").addEventListener("submit", (e) => {
  e.preventDefault();
  const f = e.target;
  const argv = ["send", "joint", val(f, "joint"), val(f, "mode"), val(f, "value") || "0"];
  if (val(f, "stiffness")) argv.push("--stiffness", val(f, "stiffness"));
  run(argv);
});
$("#f-limits").addEventListener("submit", (e) => {
  e.preventDefault();
  const f = e.target, argv = ["send", "limits"];
  if (val(f, "min")) argv.push("--min", val(f, "min"));
  if (val(f, "max")) argv.push("--max", val(f, "max"));
  run(argv);
});
$("#f-maccepa").addEventListener("submit", (e) => {
  e.preventDefault();
  const f = e.target, kind = val(f, "kind"), argv = ["maccepa", val(f, "board"), kind];
  if (kind === "setpoint" || kind === "duty") argv.push(val(f, "value"));
  if (kind === "gains") for (const g of ["kp", "ki", "kd"]) if (val(f, g)) argv.push("--" + g, val(f, g));
  if (kind === "setpoint" || kind === "gains") argv.push("--controller", val(f, "controller"));
  run(argv);
});

// --- pattern ---------------------------------------------------------------------------------

$("#speed").addEventListener("input", (e) => { $("#speed-v").textContent = e.target.value; });
$("#pattern-speed").addEventListener("click", () => run(["pattern", "speed", $("#speed").value]));
$("#pattern-select").addEventListener("click", () => {
  const js = $$("#pattern-joints input:checked").map((c) => c.value);
  if (!js.length) { notice("select at least one joint"); return; }
  run(["pattern", "select", ...js]);
});
$("#pattern-disable").addEventListener("click", () => {
  const js = $$("#pattern-joints input:checked").map((c) => c.value);
  if (!js.length) { notice("tick the joints to disable"); return; }
  run(["pattern", "disable", ...js]);
});
$("#timing").addEventListener("click", async () => {
  const out = $("#timing-result");
  out.textContent = "measuring...";
  const r = await run(["timing", "70", "--seconds", "2", "--dlc", "6"], $("#cmd-result"));
  out.innerHTML = "";
  if (!r.ok) { kv(out, "refused", r.error); return; }
  const t = r.reply;
  for (const k of ["n", "mean_period_ms", "expected_ms", "mean_dev_ms", "p99_dev_ms", "max_dev_ms"]) kv(out, k, t[k]);
});

function onPattern(p) {
  S.pattern = p;
  const dl = $("#pattern-state");
  dl.innerHTML = "";
  kv(dl, "state", p.state + (p.reason ? ` (${p.reason})` : ""));
  kv(dl, "point", `${p.index} / ${p.length}`);
  kv(dl, "speed", `${p.speed} (${p.period_ms} ms)`);
  kv(dl, "joints", (p.selected || []).join(", ") || "-");
  kv(dl, "operator", p.operator || "-");
  kv(dl, "timing", p.timing || "-");
  if (!S.patternChecksSet) {
    for (const c of $$("#pattern-joints input")) c.checked = (p.selected || []).includes(c.value);
    $("#speed").value = p.speed; $("#speed-v").textContent = p.speed;
    S.patternChecksSet = true;
  }
  if (p.file !== S.patternFile) {
    S.patternFile = p.file;
    $("#pattern-file").textContent = p.file;
    fetch("/api/pattern/points?file=" + encodeURIComponent(p.file)).then((r) => r.json())
      .then((r) => { S.patternPoints = r.ok ? r.points : null; drawPattern(); });
  } else drawPattern();
}

function patternMarker(u) {
  if (!S.pattern) return;
  const x = u.valToPos(S.pattern.index, "x", true);
  const ctx = u.ctx;
  ctx.save(); ctx.strokeStyle = "#111"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(x, u.bbox.top); ctx.lineTo(x, u.bbox.top + u.bbox.height); ctx.stroke();
  ctx.restore();
}

function drawPattern() {
  if (!plots.pattern || $("#page-pattern").hidden) return;
  resizePlots();
  const pts = S.patternPoints;
  if (!pts) { plots.pattern.redraw(); return; }
  const sel = new Set((S.pattern && S.pattern.selected) || []);
  const data = [pts.map((_, i) => i)].concat(S.joints.map((j, k) => pts.map((r) => (sel.has(j) ? r[k] : null))));
  plots.pattern.setData(data);
}

// --- recording -------------------------------------------------------------------------------

$("#rec-start").addEventListener("click", () => {
  const argv = ["record", "start"];
  for (const l of $("#labels").value.split(/\s+/).filter(Boolean)) argv.push("--label", l);
  run(argv);
});

function onRecord(r) {
  S.record = r;
  const dl = $("#rec-state");
  dl.innerHTML = "";
  if (r.error && !r.state) { kv(dl, "recorder", r.error); return; }
  kv(dl, "state", r.state + (r.error ? ` (${r.error})` : ""));
  kv(dl, "file", r.file || "-");
  kv(dl, "size", ((r.size || 0) / 1048576).toFixed(2) + " MiB");
  kv(dl, "messages", `${r.written}/${r.received} dropped ${r.dropped}`);
  if (r.card) {  // the recorder stops reserve MiB before the card is full
    const left = r.hours_left == null ? "hours left: n/a" : `${r.hours_left.toFixed(1)} h left at this rate`;
    kv(dl, "card", `${(r.card.free / 1048576).toFixed(0)} MiB free of ${(r.card.total / 1048576).toFixed(0)} MiB, ${left}`);
  }
  const ul = $("#rec-files");
  const files = r.files || [];
  if (ul.dataset.files === JSON.stringify(files)) return;
  ul.dataset.files = JSON.stringify(files);
  ul.replaceChildren(...files.map((f) => {
    const li = document.createElement("li"), a = document.createElement("a");
    a.href = "/api/recordings/download?file=" + encodeURIComponent(f);
    a.textContent = f;
    const b = document.createElement("button");
    b.textContent = "plot"; b.className = "small plot-file";
    b.addEventListener("click", () => plotRecording(f));
    // C3D for the gait lab (exolink export --c3d): served where the gaitlab extra is installed
    const c = document.createElement("a");
    c.href = "/api/recordings/c3d?file=" + encodeURIComponent(f);
    c.textContent = "C3D"; c.className = "c3d-file";
    c.title = "joints, foot switches, battery, MACCEPA as analogs; gait and trigger events";
    li.append(a, " ", b, " ", c);
    return li;
  }));
}

async function plotRecording(file) {
  $("#rec-plot-file").textContent = "loading " + file;
  const r = await (await fetch("/api/recordings/plot?file=" + encodeURIComponent(file))).json();
  if (!r.ok) { $("#rec-plot-file").textContent = "cannot plot: " + r.error; return; }
  $("#rec-plot-file").textContent = `${file}: ${r.t.length} points, ${r.triggers_s.length} triggers`;
  const el = $("#plot-recording");
  if (plots.recording) plots.recording.destroy();
  const marks = (u) => {
    const ctx = u.ctx;
    ctx.save(); ctx.strokeStyle = "#111"; ctx.setLineDash([4, 4]);
    for (const t of r.triggers_s) {
      const x = u.valToPos(t, "x", true);
      ctx.beginPath(); ctx.moveTo(x, u.bbox.top); ctx.lineTo(x, u.bbox.top + u.bbox.height); ctx.stroke();
    }
    ctx.restore();
  };
  plots.recording = new uPlot({
    width: el.clientWidth || 600, height: 220, scales: { x: { time: false } },
    series: [{ label: "s" }].concat(r.joints.map((j, i) => ({ label: j, stroke: COLORS[i] }))),
    axes: [{ label: "s since start" }, { label: "deg", size: 50 }],
    legend: { live: false }, hooks: { draw: [marks] },
  }, [r.t].concat(r.pos_deg), el);
}

// --- roles -----------------------------------------------------------------------------------

function applyRole() {
  // What this login may do (exolink.roles): .cmd needs operator, .admin needs admin; E-STOP any.
  const rank = { observer: 0, operator: 1, admin: 2 }[S.role] ?? 0;
  for (const b of $$(".cmd")) {
    const need = b.classList.contains("admin") ? 2 : 1;
    b.disabled = rank < need;
    b.title = rank < need ? `this login is ${S.role}: needs ${need === 2 ? "admin" : "operator"} (E-STOP works)` : "";
  }
  for (const f of $$("form.card")) for (const el of f.elements) el.disabled = rank < 1;
  for (const el of $("#f-param").elements) el.disabled = rank < 2;
}

// --- connection ------------------------------------------------------------------------------

function onHello(m) {
  S.role = m.role;
  S.joints = m.joints;
  $("#device").textContent = `${m.device} (${m.at})`;
  $("#role").textContent = m.role;
  if (!plots.angles) {
    $("#joints tbody").replaceChildren(...m.joints.map((j, i) => {
      const tr = document.createElement("tr");
      tr.innerHTML = `<td style="color:${COLORS[i]}">■ ${j}</td><td class="num">-</td><td class="num">-</td>`;
      return tr;
    }));
    for (const sel of $$(".joint-select")) for (const j of m.joints) sel.add(new Option(j, j));
    $("#pattern-joints").replaceChildren(...m.joints.map((j) => {
      const l = document.createElement("label");
      l.innerHTML = `<input type="checkbox" value="${j}"> ${j}`;
      return l;
    }));
    setupPlots();
  }
  applyRole();
  if (m.watchdog) showWatchdog(m.watchdog);
  if (m.status) onStatus({ status: m.status });
  if (m.trigger) { S.lastTrigger = m.trigger.stamp_ns; $("#trigger-count").textContent = m.trigger.count; }
  if (m.pattern) onPattern(m.pattern);
  if (m.record) onRecord(m.record);
  route();
}

async function connect() {
  if (S.ws) {  // a reconnect: the server may have been restarted, with tokens of its own
    try { await renewToken(); } catch (e) { setTimeout(connect, 1000); return; }
  }
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host +
    "/ws?token=" + encodeURIComponent(token));
  S.ws = ws;
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    switch (m.t) {
      case "hello": onHello(m); break;
      case "live": onLive(m); break;
      case "status": onStatus(m); break;
      case "watchdog": showWatchdog(m); break;
      case "trigger": onTrigger(m); break;
      case "pattern": onPattern(m); break;
      case "record": onRecord(m); break;
      case "log": onLog(m); break;
      case "notice": notice(m.text); break;
    }
  };
  ws.onopen = () => { $("#conn").textContent = "online"; if ($("#log-follow").checked) follow(); };
  ws.onclose = () => {
    $("#conn").textContent = "offline: reconnecting";
    $("#banner").className = "banner unknown";
    $("#wd-state").textContent = "NO CONNECTION TO THE DASHBOARD SERVER";
    $("#wd-why").textContent = "";
    setTimeout(connect, 1000);
  };
}

requestAnimationFrame(draw);
connect();
