"""The live view: a page on 127.0.0.1 that shows what a command is doing while it runs.

A command publishes its state (what it does now, the latest annotated frame, numbers, a verdict) to a
``LiveView``; a small HTTP server in a thread serves one self-contained page that polls ``/state.json``
and ``/frame.jpg``. Nothing on the page comes from the internet.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

from selfview.procedures.commands._common import PORT, SECONDS_OR_ZERO

__all__ = ["LiveView", "ViewProgress", "add_view_arguments", "open_view", "viewing", "with_progress", "watch", "offline_state", "intrinsics_state", "tracked_frames", "decision_state"]


def add_view_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("live view", "a page in the browser on 127.0.0.1 showing the run as it goes")
    g.add_argument("--view", nargs="?", type=PORT, const=0, default=None, metavar="PORT",
                   help="serve the live view (a free port, or PORT); its address is printed on stderr")
    g.add_argument("--view-linger", type=SECONDS_OR_ZERO, default=0.0, metavar="S",
                   help="keep serving the final state S seconds after the command is done (default 0)")


def open_view(args, command: str) -> "LiveView | None":
    """A started ``LiveView`` when ``--view`` was given, else None."""
    port = getattr(args, "view", None)
    if port is None:
        return None
    from selfview.errors import ConfigError

    if not 0 <= port <= 65535:
        raise ConfigError(f"--view {port}: expected a port in 0..65535 (or no number for a free one)")
    if getattr(args, "view_linger", 0.0) < 0:
        raise ConfigError(f"--view-linger {args.view_linger}: expected seconds >= 0")
    return LiveView(command, port=port, linger_s=args.view_linger).start()


@contextlib.contextmanager
def viewing(args, command: str):
    """``open_view`` for a command's run: on an error the page says no-go with it; at the end the page
    lingers (``--view-linger``) and stops. Yields None without ``--view``."""
    view = open_view(args, command)
    try:
        yield view
    except BaseException as exc:
        if view is not None:
            view.verdict(False, f"{type(exc).__name__}: {exc}")
            view.update(doing=f"stopped: {exc}")
        raise
    finally:
        if view is not None:
            view.finish()


def with_progress(view: "LiveView | None", say):
    """A progress callback that prints (``say``) and shows the line on the page as what is done now."""
    if view is None:
        return say

    def both(msg: str) -> None:
        say(msg)
        view.doing(msg)

    return both


def watch(view: "LiveView | None", session, *also) -> None:
    """Show each step of ``session``'s engine on the page as it starts; ``also``: more ``on_step`` callables."""
    hooks = ([view.step] if view is not None else []) + [h for h in also if h is not None]

    def on_step(n, step):
        for h in hooks:
            h(n, step)

    if session.engine is not None and hooks:
        session.engine.on_step = on_step


class LiveView:
    """The state a command shows and the server that shows it. Thread-safe; every method is cheap."""

    def __init__(self, command: str, port: int = 0, linger_s: float = 0.0):
        self.command = command
        self.port = port
        self.linger_s = float(linger_s)
        self._lock = threading.Lock()
        self._jpeg = b""
        self._state = {"command": command, "doing": "starting", "seq": 0, "frame_seq": 0, "verdict": None,
                       "numbers": {}, "residuals": [], "series": None, "coverage": None, "done": False,
                       "updated": time.time()}
        self._server = None

    # --- what the command publishes ---------------------------------------------------------------
    def update(self, **kw) -> None:
        with self._lock:
            self._state.update(kw)
            self._state["seq"] += 1
            self._state["updated"] = time.time()

    def doing(self, text: str) -> None:
        self.update(doing=str(text))

    def step(self, n: int, step) -> None:
        """An engine step starting (``Engine.on_step``)."""
        self.doing(f"step {n}: {step.describe()}")

    def verdict(self, go: bool, why: str) -> None:
        self.update(verdict={"go": bool(go), "why": str(why)})

    def frame(self, image) -> None:
        """The latest picture (grey or BGR), sent to the page as JPEG."""
        import cv2

        ok, buf = cv2.imencode(".jpg", np.asarray(image), [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            with self._lock:
                self._jpeg = buf.tobytes()
                self._state["frame_seq"] += 1
            self.update()

    def point(self, key: str, value: dict, keep: int = 500) -> None:
        """Append one point to the series ``key`` (the monitor's change over time)."""
        with self._lock:
            s = self._state.get("series") or {"points": []}
            s.setdefault("points", []).append(value)
            del s["points"][:-keep]
            self._state["series"] = s
        self.update()

    def series_limits(self, **limits) -> None:
        """The plot's scale and dashed lines (``alarm_deg``, ``alarm_mm``, ``update_deg``, ``update_mm``, and
        ``names`` [scale line, dashed lines, what the scale is] for a plot other than the monitor's)."""
        with self._lock:
            s = self._state.get("series") or {"points": []}
            s["limits"] = dict(limits)
            self._state["series"] = s
        self.update()

    def state(self) -> dict:
        with self._lock:
            return json.loads(json.dumps(self._state, default=_plain))

    # --- serving ----------------------------------------------------------------------------------
    def start(self) -> "LiveView":
        view = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                path = self.path.split("?")[0]
                if path == "/":
                    body, ctype = _PAGE.encode(), "text/html; charset=utf-8"
                elif path == "/state.json":
                    body, ctype = json.dumps(view.state()).encode(), "application/json"
                elif path == "/frame.jpg":
                    with view._lock:
                        body = view._jpeg
                    ctype = "image/jpeg"
                    if not body:
                        self.send_error(404, "no frame yet")
                        return
                else:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *a):  # the command's stderr is for the operator
                pass

        from selfview.errors import ConfigError

        try:
            self._server = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        except OSError as exc:
            raise ConfigError(f"--view {self.port}: cannot serve on 127.0.0.1 ({exc}); give another port or none") from exc
        self._server.daemon_threads = True
        self.port = self._server.server_address[1]
        threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True,
                         name="selfview-view").start()
        print(f"view: {self.url}", file=sys.stderr, flush=True)
        return self

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def finish(self) -> None:
        """The command is done: show it, serve ``linger_s`` more seconds (Ctrl-C ends it early), stop."""
        self.update(done=True)
        try:
            end = time.monotonic() + self.linger_s
            while time.monotonic() < end:
                time.sleep(min(0.1, max(0.0, end - time.monotonic())))
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None


def _plain(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    return str(o)


# --- what the commands show -------------------------------------------------------------------------
def offline_state(view: LiveView, image, result, *, tcp_sigma_mm=None, rms_limit_px: float = 0.5) -> None:
    """An off-line calibration on the page: the annotated frame, each disc's residual in px and in mm on the
    plate, the figures, and a verdict (go when every fingertip corner was found and the residual is small)."""
    from selfview.procedures.results import draw_offline, offline_residuals

    view.frame(draw_offline(image, result))
    rows = offline_residuals(result)
    s = result.summary()
    H = result.calibration.C_H_G
    numbers = {"f [px]": s["f"], "kappa [px^-2]": s["kappa"], "residual rms [px]": s["rms_px"],
               "residual max [px]": s["max_px"], "discs used": s["discs_used"],
               "corners found": ", ".join(s["corners_found"]), "PCC residual [mm]": s["pcc_rms_mm"],
               "TCP x [mm]": H[0, 3], "TCP y [mm]": H[1, 3], "TCP z [mm]": H[2, 3]}
    if tcp_sigma_mm is not None:
        numbers["TCP 1-sigma x y z [mm]"] = " ".join(f"{v:.4f}" for v in tcp_sigma_mm)
    view.update(numbers=numbers, residuals=rows)
    missing = 6 - len(s["corners_found"])
    if missing:
        view.verdict(False, f"{missing} fingertip corner(s) not found: C_H_G rests on fewer points")
    elif s["rms_px"] > rms_limit_px:
        view.verdict(False, f"disc residual rms {s['rms_px']:.3f} px above {rms_limit_px} px: check focus and light")
    else:
        view.verdict(True, f"all 6 corners, {s['discs_used']} discs, residual rms {s['rms_px']:.3f} px "
                           f"(max {s['max_px']:.3f} px)")


def intrinsics_state(view: LiveView, res) -> None:
    """A camera measured from several views (``selfview.intrinsics``) on the page: its figures, the stop
    rule's state and a verdict (go when the rule is met and the two halves of the views agree)."""
    xc = res.cross_check
    sr = res.stop_rule
    view.update(numbers={"f [px]": res.camera.f, "kappa [px^-2]": res.camera.kappa, "cx [px]": res.camera.cx,
                         "cy [px]": res.camera.cy, "aspect": res.camera.aspect, "views used": res.views_used,
                         "residual rms [px]": res.rms_px,
                         "stop rule: sigma centre [px]": f"{sr['sigma_centre_px']:.3f} (limit {sr['limit_centre_px']})",
                         "stop rule: sigma aspect [%]": f"{sr['sigma_aspect_pct']:.4f} (limit {sr['limit_aspect_pct']})"})
    view.verdict(bool(sr["met"]) and not (xc.get("done") and not xc.get("agree")),
                 "stop rule met" + ("" if not xc.get("done") else ", halves agree" if xc.get("agree") else
                                    ", but the halves DISAGREE") if sr["met"] else
                 "stop rule not met: " + sr.get("advice", ""))


def tracked_frames(view: LiveView, calibration, cell):
    """``CellSession.monitor``'s ``on_frame``: each tracked frame on the page, the fingers' silhouette and
    corners drawn where the current C_H_G puts them."""
    from selfview.calfile import load_calibration
    from selfview.pcc import jaw_gap_of
    from selfview.procedures.results import draw_tracked

    cal = load_calibration(calibration)
    pG = cal.points_G[cal.state]
    boxes = cell.gripper.finger_boxes_G(jaw_gap_of(pG))
    return lambda img, ft, H: view.frame(draw_tracked(img, cal.camera, H, pG, ft, boxes=boxes))


def decision_state(view: LiveView, rec: dict, limits) -> None:
    """One monitor decision on the page: a point of the camera's change over time against the limits."""
    view.doing(f"frame {rec.get('frame')}: {rec.get('action')}")
    view.point("monitor", {"frame": rec.get("frame"), "delta_deg": rec.get("delta_deg"), "d_mm": rec.get("d_mm"),
                           "action": rec.get("action")})
    with view._lock:
        view._state["series"]["limits"] = {
            "update_deg": limits.update_limit.angle_deg, "update_mm": limits.update_limit.shift_mm,
            "alarm_deg": limits.alarm_limit.angle_deg, "alarm_mm": limits.alarm_limit.shift_mm}
    view.update(numbers={"frame": rec.get("frame"), "decision": rec.get("action"), "delta [deg]": rec.get("delta_deg"),
                         "d [mm]": rec.get("d_mm"), "rms [px]": rec.get("rms_px"),
                         "fingertips": rec.get("fingertips", "")})
    if rec.get("action") == "alarm":
        view.verdict(False, f"alarm at frame {rec.get('frame')}: {rec.get('reason')}")
    else:
        view.verdict(True, f"frame {rec.get('frame')}: {rec.get('action')} ({rec.get('reason')})")


class ViewProgress:
    """``Engine.on_step`` for the views of ``CellSession.intrinsics_views``: one line per view with the time
    left for the views (from the time per view so far), and on the live view each picture as it comes with
    the plate's discs found in it and the picture's coverage by all the views so far."""

    def __init__(self, say, views: int, engine, cell, view=None, grid: int = 4):
        import time

        self.say, self.views, self.engine, self.cell, self.view, self.grid = say, views, engine, cell, view, grid
        self.t0 = time.monotonic()
        self.pending = None
        self.covered = set()
        self.canvas = None

    def __call__(self, n, step) -> None:
        import time

        if self.pending:
            self._show(self.pending)
            self.pending = None
        if step.kind == "grab" and (step.name or "").startswith("view"):
            i = int(step.name[4:])
            el = time.monotonic() - self.t0
            self.say(f"view {i} of {self.views}: at its pose, grabbing; elapsed {el:.1f} s, "
                     f"views left ~{el / i * (self.views - i):.0f} s")
            self.pending = step.name if self.view is not None else None

    def _show(self, name) -> None:
        import cv2
        import numpy as np

        from selfview.discs import detect_discs
        from selfview.errors import ImageError

        img = self.engine.results.get(name)
        if img is None:
            return
        big = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        if self.canvas is None:
            self.canvas = np.zeros_like(big)
        try:
            uv = detect_discs(img, self.cell.plate, camera=self.cell.camera.guess()).uv
        except ImageError as exc:
            self.view.doing(f"{name}: no plate found ({exc})")
            uv = np.zeros((0, 2))
        h, w = img.shape
        for u, v in uv:
            cv2.circle(big, (int(u), int(v)), 6, (0, 200, 0), 2, cv2.LINE_AA)
            cv2.circle(self.canvas, (int(u), int(v)), 3, (0, 200, 255), -1, cv2.LINE_AA)
            self.covered.add((min(int(u * self.grid / w), self.grid - 1), min(int(v * self.grid / h), self.grid - 1)))
        shown = cv2.addWeighted(big, 1.0, self.canvas, 0.8, 0)
        self.view.frame(shown)
        self.view.update(coverage={"views taken": int(name[4:]), "of": self.views, "discs in this view": len(uv),
                                   f"cells of a {self.grid}x{self.grid} grid with discs": len(self.covered)})


_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>selfview live view</title>
<style>
body{font-family:sans-serif;margin:0;background:#222;color:#eee}
#verdict{padding:12px 16px;font-size:22px;font-weight:bold;background:#555}
#verdict.go{background:#1b7f2a}#verdict.nogo{background:#b0201a}
#doing{padding:6px 16px;background:#333;font-family:monospace}
main{display:flex;flex-wrap:wrap;gap:12px;padding:12px}
#frame{max-width:760px;width:100%;background:#000}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #555;padding:2px 6px;text-align:right}
th{background:#333}section{min-width:320px}h2{font-size:15px;margin:8px 0 4px}
svg{background:#111}
</style></head><body>
<div id="verdict">waiting for a verdict</div>
<div id="doing">connecting</div>
<main><section><img id="frame" alt="latest frame"></section>
<section><h2 id="cmd">figures</h2><table id="numbers"></table>
<div id="plotbox" hidden><h2>change of the camera over time</h2><svg id="plot" width="420" height="200"></svg></div>
<div id="coveragebox" hidden><h2>coverage of the picture</h2><table id="coverage"></table></div>
<div id="residualbox" hidden><h2>residuals per point</h2><table id="residuals"></table></div></section></main>
<script>
let lastFrame=-1;
function fmt(v){return typeof v==="number"?(Number.isInteger(v)?String(v):Math.abs(v)>=1e-3||v===0?v.toFixed(4):v.toExponential(3)):String(v)}
function rows(t,obj){t.innerHTML="";for(const k in obj){const r=t.insertRow();r.insertCell().textContent=k;
 r.insertCell().textContent=fmt(obj[k]);}}
function plot(s){const svg=document.getElementById("plot");svg.innerHTML="";if(!s||!s.points)return;
 const L=s.limits||{},P=s.points,W=420,H=200,n=Math.max(P.length,2),x=i=>10+i*(W-20)/(n-1);
 const top=Math.max(1.2,...P.map(p=>Math.max((p.delta_deg||0)/L.alarm_deg,(p.d_mm||0)/L.alarm_mm)))*1.05;
 const y=v=>H-10-(v/top)*(H-30);let h="";
 const N=L.names||["alarm limit","update limit","the alarm limit"];
 const lines=[[1,"#ff4040",`${N[0]} ${L.alarm_deg} deg / ${L.alarm_mm} mm`],
  [L.update_deg/L.alarm_deg,"#e0c000",`${N[1]} ${L.update_deg} deg`],[L.update_mm/L.alarm_mm,"#c08000",`${N[1]} ${L.update_mm} mm`]];
 for(const [v,c,t] of lines)h+=`<line x1="0" x2="${W}" y1="${y(v)}" y2="${y(v)}" stroke="${c}" stroke-dasharray="4"/>`+
   `<text x="${W-200}" y="${y(v)-3}" fill="${c}" font-size="11">${t}</text>`;
 for(const [k,c,a] of [["delta_deg","#6cf",L.alarm_deg],["d_mm","#f8a",L.alarm_mm]])
  h+=`<polyline fill="none" stroke="${c}" points="${P.map((p,i)=>x(i)+","+y((p[k]||0)/a)).join(" ")}"/>`;
 h+=`<text x="4" y="12" font-size="11"><tspan fill="#6cf">rotation</tspan> <tspan fill="#f8a">shift</tspan>`+
  `<tspan fill="#ccc"> as a fraction of ${N[2]}, ${P.length} frames</tspan></text>`;svg.innerHTML=h;}
async function poll(){let s;try{s=await (await fetch("state.json",{cache:"no-store"})).json();}
 catch(e){document.getElementById("doing").textContent="the command has ended; this is its last state";
  setTimeout(poll,1000);return;}
 try{
 document.getElementById("cmd").textContent="selfview "+s.command;
 document.getElementById("doing").textContent=(s.done?"finished; last step: ":"now: ")+s.doing;
 const v=document.getElementById("verdict");
 if(s.verdict){v.className=s.verdict.go?"go":"nogo";v.textContent=(s.verdict.go?"GO: ":"NO-GO: ")+s.verdict.why;}
 rows(document.getElementById("numbers"),s.numbers);plot(s.series);
 document.getElementById("plotbox").hidden=!s.series;document.getElementById("coveragebox").hidden=!s.coverage;
 document.getElementById("residualbox").hidden=!s.residuals.length;
 if(s.coverage)rows(document.getElementById("coverage"),s.coverage);
 const t=document.getElementById("residuals");t.innerHTML="";if(s.residuals.length){const h=t.insertRow();
  for(const k of Object.keys(s.residuals[0])){const c=document.createElement("th");c.textContent=k;h.appendChild(c);}
  for(const r of s.residuals){const tr=t.insertRow();for(const k in r)tr.insertCell().textContent=fmt(r[k]);}}
 if(s.frame_seq!==lastFrame&&s.frame_seq>0){lastFrame=s.frame_seq;
  document.getElementById("frame").src="frame.jpg?"+s.frame_seq;}
}catch(e){document.getElementById("doing").textContent="page error: "+e;}
setTimeout(poll,250);}
poll();
</script></body></html>
"""
