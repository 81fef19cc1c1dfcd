"""The status page (``GET /`` of ``companion.service.web``): plain HTML and a few lines of
JavaScript, no framework, polling ``/status.json`` once a second. Text is set with textContent only
(nothing from the JSON is parsed as HTML). Laid out for a 1280 x 900 window: the numbers a pilot
reads first on top, the live view with the last decisions beside it (above the fold), the zones
below. The legend's colours are the figure's (``companion.replay.draw``, BGR there).
"""

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>companion: safe landing zones</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:sans-serif;margin:0.6em 1em;background:#111;color:#eee}
h1{font-size:1.3em;margin:0.2em 0}h2{font-size:1.05em;margin:0.4em 0}
#top{display:flex;gap:1em;align-items:flex-start}#view{flex:0 1 60%;min-width:0}#side{flex:1 1 40%;min-width:0}
img{width:100%;background:#333;min-height:120px}
table{border-collapse:collapse}td,th{padding:2px 8px;border-bottom:1px solid #444;text-align:right}
.bad{color:#f66}.ok{color:#6f6}.standby{color:#fc3}.shadow{color:#fc3}
#decisions{margin:0;padding-left:1.4em;font-size:0.9em}#decisions li{font-family:monospace}
.facts b{margin-right:0.8em}.legend span{margin-right:0.8em;white-space:nowrap}
</style></head><body>
<h1>companion <span id="shadow" class="shadow"></span></h1>
<p class="facts">Phase: <b id="phase">-</b> Health: <b id="health">-</b>
Mode: <b id="mode">-</b> <b id="armed">-</b>
Height: <b id="height">-</b>
Trigger: <b id="trigger">-</b> Handback: <b id="handback">-</b><br>
Zones: <b id="zone-count">-</b> Target: <b id="target">-</b>
Clearance at touchdown: <b id="clearance">-</b> <span id="rates"></span></p>
<div id="top"><div id="view">
<img id="live" src="/stream.mjpg" alt="live view">
<p class="legend">Live view: <span style="color:#ff0000">&#9632; people</span>
<span style="color:#dc00dc">&#9632; unlandable ground</span>
<span style="color:#00c800">&#9632; proposals</span>
<span style="color:#0050ff">&#9632; zones</span>
<span style="color:#ffe600">&#9632; target</span></p>
</div><div id="side">
<h2>Last decisions</h2><ol id="decisions"></ol>
</div></div>
<h2>Zones</h2>
<table id="zones"><thead><tr><th>id</th><th>north m</th><th>east m</th><th>radius m</th><th>age</th>
<th>clearance at touchdown m</th></tr></thead><tbody></tbody></table>
<script>
function txt(id, v) { document.getElementById(id).textContent = v; }
function num(v, d) { return v === null || v === undefined ? "-" : Number(v).toFixed(d); }
async function refresh() {
  try {
    const s = await (await fetch("/status.json", {cache: "no-store"})).json();
    txt("phase", s.phase);
    const h = document.getElementById("health");
    h.textContent = s.health.ok ? "ok" : s.health.reason;
    h.className = s.health.ok ? "ok" : s.health.standby ? "standby" : "bad";
    txt("shadow", s.shadow ? "SHADOW MODE: no commands sent" : "");
    const v = s.vehicle;
    txt("mode", v.mode === null ? "-" : v.mode);
    txt("armed", v.armed === null ? "" : v.armed ? "armed" : "disarmed");
    txt("height", v.height_m === null ? "-" : num(v.height_m, 1) + " m above home" +
        (v.height_agl_m === null ? "" : ", " + num(v.height_agl_m, 1) + " m above ground"));
    txt("trigger", v.trigger === null ? "none" : num(v.trigger.age_s, 0) + " s ago (" + v.trigger.reason + ")");
    txt("handback", v.handback === null ? "none" : v.handback);
    txt("zone-count", s.zones.length);
    txt("target", s.target === null ? "none" : "#" + s.target.id + " r " + num(s.target.r_m, 1) + " m");
    txt("clearance", s.target === null ? "-" : s.clearance_note !== null ? s.clearance_note :
        num(s.target.clearance_m, 1) + " m");
    txt("rates", num(s.fps, 1) + " frames/s, " + num(s.frame_ms, 0) + " ms/frame");
    const body = document.querySelector("#zones tbody");
    body.replaceChildren(...s.zones.map(z => {
      const tr = document.createElement("tr");
      const c = s.clearance_note !== null ? "n/a" : num(z.clearance_m, 1);
      for (const x of [z.id, num(z.north_m, 1), num(z.east_m, 1), num(z.r_m, 1), z.age, c]) {
        const td = document.createElement("td"); td.textContent = x; tr.appendChild(td);
      }
      return tr;
    }));
    const ol = document.getElementById("decisions");
    ol.replaceChildren(...s.decisions.slice(0, 12).map(d => {
      const li = document.createElement("li"); li.textContent = num(d.age_s, 0) + " s ago: " + d.text; return li;
    }));
  } catch (e) { txt("health", "no answer from the service"); }
}
refresh(); setInterval(refresh, 1000);
</script></body></html>
"""
