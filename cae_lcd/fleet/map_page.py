"""The fleet's live map (``GET /map``) and trajectory files (``GET /robots/{name}/trajectory``).

``/map`` is one static HTML page with inline JavaScript and SVG (no external script, font or CDN: the server may
have no internet). It holds no data: the browser polls the server's own JSON routes (``MAP_ROUTES``) every
``POLL_MS`` and redraws, on the x-z ground plane (KITTI's), each merged robot's corrected trajectory, its loop
edges (thin, grey) and the overlap edges between robots (dashed, red), so the picture follows keyframes as they
arrive. Its token comes from the address's fragment (``/map#token=TOKEN``; a fragment is never sent to a server)
or a field on the page; the admin token shows every robot, a robot's token its own trajectory.

The page's counters carry ``data-`` attributes (``#status``: robots, keyframes, loops, overlaps) so that a headless
browser can check what it drew against the API (``tests/fleet/test_map_page.py``).

``GET /robots/{name}/trajectory?format=tum|kitti`` (robot itself or admin) returns the corrected trajectory as a
file (``cae_lcd.fleet.export``).
"""

from __future__ import annotations

from typing import Any, Callable, Literal

from fastapi import APIRouter, Depends
from fastapi.responses import HTMLResponse, PlainTextResponse

from .export import corrected_trajectory, format_trajectory

__all__ = ["map_router", "MAP_ROUTES", "POLL_MS", "page_html"]

POLL_MS = 1500  #: how often the page polls the server, milliseconds
#: the JSON routes the page reads, by what it reads from them (``{name}``: each robot of ``/transforms``)
MAP_ROUTES = {"transforms": "/transforms", "overlaps": "/overlaps", "poses": "/robots/{name}/poses",
              "loops": "/robots/{name}/loops"}

_PAGE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>cae-lcd fleet map</title>
<style>
body{font:14px system-ui,sans-serif;margin:12px;background:#fafafa;color:#222}
#map{background:#fff;border:1px solid #ccc;width:100%;height:78vh}
#status span{margin-right:1.2em} .err{color:#b00}
</style></head><body>
<div><b>cae-lcd fleet map</b> &middot; x-z ground plane, global frame &middot;
<input id="token" type="password" placeholder="token" size="28"> <span id="updated"></span></div>
<div id="status" data-robots="0" data-keyframes="0" data-loops="0" data-overlaps="0" data-polls="0"></div>
<svg id="map" xmlns="http://www.w3.org/2000/svg"></svg>
<script>
"use strict";
const ROUTES = __ROUTES__, POLL_MS = __POLL_MS__;
const COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf"];
const tokenBox = document.getElementById("token");
tokenBox.value = new URLSearchParams(location.hash.slice(1)).get("token") || "";
async function get(path) {
  const r = await fetch(path, {headers: {"Authorization": "Bearer " + tokenBox.value}});
  if (!r.ok) throw new Error(path + ": " + r.status);
  return r.json();
}
function el(tag, attrs, parent) {
  const e = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const k in attrs) e.setAttribute(k, attrs[k]);
  parent.appendChild(e); return e;
}
async function load() {
  const robots = Object.keys(await get(ROUTES.transforms)).sort();
  const overlaps = await get(ROUTES.overlaps), poses = {}, edges = [];
  for (const name of robots) {
    try {
      poses[name] = await get(ROUTES.poses.replace("{name}", encodeURIComponent(name)));
      edges.push(...await get(ROUTES.loops.replace("{name}", encodeURIComponent(name))));
    } catch (e) { /* another robot's data: this token cannot read it */ }
  }
  return {robots: Object.keys(poses), poses, edges, overlaps};
}
function draw(d) {
  const svg = document.getElementById("map"); svg.replaceChildren();
  const at = {}, pts = [];
  for (const name of d.robots) for (const p of d.poses[name]) {
    const xy = [p.pose[0][3], -p.pose[2][3]]; at[name + "/" + p.keyframe] = xy; pts.push(xy);
  }
  if (!pts.length) return {keyframes: 0, loops: 0, overlaps: 0};
  const xs = pts.map(p => p[0]), ys = pts.map(p => p[1]);
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const pad = 0.05 * Math.max(x1 - x0, y1 - y0, 1);
  svg.setAttribute("viewBox", [x0 - pad, y0 - pad, x1 - x0 + 2 * pad, y1 - y0 + 2 * pad].join(" "));
  const w = 0.004 * Math.max(x1 - x0, y1 - y0, 1), seen = new Set(); let loops = 0, overlaps = 0;
  d.robots.forEach((name, i) => {
    const line = d.poses[name].map(p => at[name + "/" + p.keyframe].join(",")).join(" ");
    const g = el("g", {id: "robot-" + name, "data-keyframes": d.poses[name].length}, svg);
    el("polyline", {points: line, fill: "none", stroke: COLOURS[i % COLOURS.length], "stroke-width": 2.5 * w}, g);
    const last = at[name + "/" + d.poses[name][d.poses[name].length - 1].keyframe];
    el("text", {x: last[0] + 2 * w, y: last[1] + 14 * w * i, "font-size": 12 * w, fill: COLOURS[i % COLOURS.length]}, g)
      .textContent = name;
  });
  for (const e of d.edges) {
    const a = at[e.a.join("/")], b = at[e.b.join("/")], key = [e.a, e.b].join("|");
    if (!a || !b || seen.has(key)) continue;
    seen.add(key); e.kind === "overlap" ? overlaps++ : loops++;
    el("line", {x1: a[0], y1: a[1], x2: b[0], y2: b[1], "stroke-width": w, class: "edge-" + e.kind,
      stroke: e.kind === "overlap" ? "#d00" : "#888", "stroke-dasharray": e.kind === "overlap" ? 3 * w : "none"}, svg);
    if (e.kind === "overlap") for (const p of [a, b]) el("circle", {cx: p[0], cy: p[1], r: 1.6 * w, fill: "none",
      stroke: "#d00", "stroke-width": 0.6 * w}, svg);
  }
  return {keyframes: pts.length, loops, overlaps};
}
async function poll() {
  const status = document.getElementById("status"), updated = document.getElementById("updated");
  try {
    const d = await load(), n = draw(d);
    Object.assign(status.dataset, {robots: d.robots.length, keyframes: n.keyframes, loops: n.loops,
                                   overlaps: n.overlaps, polls: +status.dataset.polls + 1});
    const swatches = d.robots.map((r, i) => `<b style="color:${COLOURS[i % COLOURS.length]}">&#9632; ${r}</b>`);
    status.innerHTML = `<span>robots ${d.robots.length}: ${swatches.join(" ")}</span>` +
      `<span>keyframes ${n.keyframes}</span>` +
      `<span style="color:#888">loop edges ${n.loops}</span><span style="color:#d00">overlap edges ${n.overlaps} ` +
      `(dashed, circled keyframes)</span>` +
      `<span>accepted overlaps ${d.overlaps.length}</span>`;
    updated.textContent = "updated " + new Date().toLocaleTimeString(); updated.className = "";
  } catch (e) { updated.textContent = String(e.message); updated.className = "err"; }
  setTimeout(poll, POLL_MS);
}
poll();
</script></body></html>
"""


def page_html() -> str:
    """The map page's HTML (the routes and the polling period filled in)."""
    import json

    return _PAGE.replace("__ROUTES__", json.dumps(MAP_ROUTES)).replace("__POLL_MS__", str(POLL_MS))


def map_router(service: Any, caller: Callable[..., str], owner_or_admin: Callable[[str, str], None],
               responses: dict[int | str, dict[str, Any]] | None = None) -> APIRouter:
    """``GET /map`` (no token: the page holds no data) and ``GET /robots/{name}/trajectory`` (robot itself or admin).

    Args:
        service: the server's ``FleetService``.
        caller: the server's token dependency (token -> caller name).
        owner_or_admin: the server's access check (the same 404 for an unknown robot and another robot's).
        responses: the refusals the server documents for every route (OpenAPI ``responses``).
    """
    router = APIRouter()
    html = page_html()

    @router.get("/map", response_class=HTMLResponse, include_in_schema=False)
    def fleet_map() -> str:
        return html

    # the refusals are JSON like every route's (``responses``); the trajectory itself is plain text
    text = {200: {"content": {"text/plain": {"schema": {"type": "string"}}}, "description": "the trajectory"}}

    @router.get("/robots/{name}/trajectory", responses={**(responses or {}), **text})
    def trajectory(name: str, format: Literal["tum", "kitti"] = "tum", wait: bool = False,
                   who: str = Depends(caller)) -> PlainTextResponse:
        owner_or_admin(name, who)
        return PlainTextResponse(format_trajectory(*corrected_trajectory(service, name, wait), format))

    return router
