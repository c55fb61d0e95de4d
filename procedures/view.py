"""The live view: a page on 127.0.0.1 that shows what a command is doing while it runs, and its controls.

A command publishes its state (what it does now, the latest annotated frame, numbers, a verdict, a log)
to a ``LiveView``; a small HTTP server in a thread serves one self-contained page that polls
``/state.json`` and ``/frame.jpg``, and ``/live.jpg`` (the camera's current frame, ``selfview.procedures.livefeed``)
with the run's token. Nothing on the page comes from the internet. GET never changes anything: the page's
controls (STOP, the alarm's acknowledge, the buttons a command asks with, such as TAKE THIS VIEW) POST to
``/action`` with the run's token, which only the page served by this run holds; a request naming another
host (DNS rebinding) is refused.
"""

from __future__ import annotations

import contextlib
import hmac
import json
import secrets
import signal
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

__all__ = ["LiveView", "ViewProgress", "open_view", "viewing", "with_progress", "watch", "offline_state", "intrinsics_state", "tracked_frames", "decision_state"]


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
        self._live_jpeg = b""  # the camera's current frame (``live_frame``); the one kept, so memory is bounded
        self._state = {"command": command, "doing": "starting", "seq": 0, "frame_seq": 0, "verdict": None,
                       "numbers": {}, "residuals": [], "series": None, "coverage": None, "done": False,
                       "log": [], "alarm": None, "stop_requested": False, "bars": None, "views": [], "ask": None, "live": None, "updated": time.time()}
        self._server = None
        self.token = secrets.token_urlsafe(24)  # per run; only the page this run serves holds it
        self._actions = {"stop": self._stop, "acknowledge": self._acknowledge}

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

    def alarm(self, why: str) -> None:
        """An alarm the operator is asked to acknowledge on the page (the verdict says no-go)."""
        self.verdict(False, why)
        self.update(alarm={"why": str(why), "acknowledged": False})

    def log(self, row: dict, keep: int = 500) -> None:
        """One row of the run's log (the monitor's decision per frame), newest last."""
        with self._lock:
            self._state["log"].append(row)
            del self._state["log"][:-keep]
        self.update()

    # --- the page's controls (run in the server's thread) -----------------------------------------
    def ask(self, prompt: str, buttons, *, select_views: bool = False, timeout_s: float = 600.0, cancel=None):
        """Offer ``buttons`` [(action, label)] on the page under ``prompt`` and wait for the operator's click
        (STOP and Ctrl-C still end the run); with ``select_views`` the page's per-view table offers a reject
        box per view, sent with the click as ``reject`` (view names). Returns (action, {"reject": [...]}),
        or None when nobody answered within ``timeout_s`` or ``cancel`` (an event: the run is stopping) was set."""
        done = threading.Event()
        box = {}

        def answer(name):
            def fn(payload):
                box.update(action=name, reject=[str(v) for v in (payload.get("reject") or [])][:1000])
                done.set()
                return f"{name} requested"
            return fn

        names = [a for a, _ in buttons]
        for a in names:
            self._actions[a] = answer(a)
        self.update(ask={"prompt": str(prompt), "buttons": [{"action": a, "label": lb} for a, lb in buttons],
                         "select": "views" if select_views else None})
        try:
            end = time.monotonic() + timeout_s
            while not done.wait(0.1):
                if time.monotonic() > end or (cancel is not None and cancel.is_set()):
                    return None
        finally:
            for a in names:
                self._actions.pop(a, None)
            self.update(ask=None)
        return box["action"], {"reject": box["reject"]}

    def _stop(self, payload=None) -> str:
        """STOP: the run stops as on Ctrl-C (``procedures.engine``: ABORT to the robot, the valve safe, the
        devices closed, exit 130); a signal is how another thread reaches the main thread's cleanup."""
        sig = signal.SIGINT if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN else signal.SIGTERM
        self.update(stop_requested=True, doing="STOP pressed on the page: stopping the robot")
        print("view: STOP pressed on the page", file=sys.stderr, flush=True)
        signal.pthread_kill(threading.main_thread().ident, sig)
        return "stopping: ABORT to the robot, the valve safe"

    def _acknowledge(self, payload=None) -> str:
        with self._lock:
            alarm = self._state.get("alarm")
        if not alarm:
            return "no alarm to acknowledge"
        self.update(alarm={**alarm, "acknowledged": True, "at": time.strftime("%H:%M:%S")})
        print(f"view: alarm acknowledged on the page ({alarm['why']})", file=sys.stderr, flush=True)
        return "alarm acknowledged"

    def frame(self, image) -> None:
        """The latest picture (grey or BGR), sent to the page as JPEG."""
        import cv2

        ok, buf = cv2.imencode(".jpg", np.asarray(image), [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            with self._lock:
                self._jpeg = buf.tobytes()
                self._state["frame_seq"] += 1
            self.update()

    def live_frame(self, image, info: dict) -> None:
        """The camera's current frame (``selfview.procedures.livefeed``: drawn, BGR) as JPEG at ``/live.jpg``, and
        ``info`` (what was found in it) as the state's ``live``; only the latest frame is kept."""
        import cv2

        ok, buf = cv2.imencode(".jpg", np.asarray(image), [cv2.IMWRITE_JPEG_QUALITY, 80])
        if not ok:
            return
        with self._lock:
            self._live_jpeg = buf.tobytes()
            seq = ((self._state.get("live") or {}).get("seq") or 0) + 1
            self._state["live"] = {**info, "on": True, "seq": seq}
        self.update()

    def live_state(self, **info) -> None:
        """The live feed's state without a new frame (a grab error, paused, ended: ``on`` False hides it)."""
        with self._lock:
            self._state["live"] = {**(self._state.get("live") or {"seq": 0}), **info}
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
            def _local(self) -> bool:
                """Refuse a request that names another host (a page elsewhere reaching 127.0.0.1 by DNS rebinding)."""
                if self.headers.get("Host") in (f"127.0.0.1:{view.port}", f"localhost:{view.port}"):
                    return True
                self.send_error(403, "not this host")
                return False

            def _token(self) -> bool:
                """The run's token in the request's header (only the page this run served holds it)."""
                if hmac.compare_digest(self.headers.get("X-Selfview-Token", ""), view.token):
                    return True
                self.send_error(403, "missing or wrong token: use the page this run serves")
                return False

            def do_POST(self):  # noqa: N802 (http.server's name)
                if not self._local():
                    return
                if self.path != "/action":
                    self.send_error(404)
                    return
                if not self._token():
                    return
                try:
                    n = min(int(self.headers.get("Content-Length", "0")), 65536)
                    payload = json.loads(self.rfile.read(n) or b"{}")
                    name = payload.get("action")
                    fn = view._actions[name]
                except (ValueError, KeyError, AttributeError, TypeError):
                    self.send_error(400, "expected {\"action\": NAME} with one of the page's actions")
                    return
                body = json.dumps({"action": name, "said": fn(payload)}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self):  # noqa: N802 (http.server's name)
                if not self._local():
                    return
                path = self.path.split("?")[0]
                if path == "/":
                    body, ctype = _PAGE.replace("__TOKEN__", view.token).encode(), "text/html; charset=utf-8"
                elif path == "/state.json":
                    body, ctype = json.dumps(view.state()).encode(), "application/json"
                elif path in ("/frame.jpg", "/live.jpg"):  # live: the camera now, for this run's page only (its token)
                    live = path == "/live.jpg"
                    if live and not self._token():
                        return
                    with view._lock:
                        body = view._live_jpeg if live else view._jpeg
                    ctype = "image/jpeg"
                    if not body:
                        self.send_error(404, "no live frame yet" if live else "no frame yet")
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
def offline_state(view: LiveView, image, assessed) -> None:
    """An off-line calibration on the page (``assessed``: ``selfview.api.PictureCalibration``): the annotated
    frame, each disc's residual in px and in mm on the plate (against the centres the fit used), the
    figures with the TCP's sigma, and the calibration's verdict (``selfview.api.assess_offline``)."""
    from selfview.procedures.results import draw_offline, offline_residuals

    result = assessed.offline
    view.frame(draw_offline(image, result))
    rows = offline_residuals(result)
    s = result.summary()
    H = result.calibration.C_H_G
    numbers = {"f [px]": s["f"], "kappa [px^-2]": s["kappa"], "residual rms [px]": s["rms_px"],
               "residual max [px]": s["max_px"], "discs used": s["discs_used"],
               "corners found": ", ".join(s["corners_found"]), "PCC residual [mm]": s["pcc_rms_mm"],
               "TCP x [mm]": H[0, 3], "TCP y [mm]": H[1, 3], "TCP z [mm]": H[2, 3],
               "TCP 1-sigma x y z [mm]": " ".join(f"{v:.4f}" for v in assessed.tcp_sigma_mm)}
    view.update(numbers=numbers, residuals=rows)
    view.verdict(assessed.go, assessed.reason)


def intrinsics_state(view: LiveView, res, plate=None, rejected=()) -> None:
    """A camera measured from several views (``selfview.estimation.intrinsics``) on the page: its figures, the stop
    rule's state, a row per view (used or why not), the views' coverage bars (with the ``plate``) and a
    verdict (go when the rule is met and the two halves of the views agree)."""
    xc = res.cross_check
    sr = res.stop_rule
    view.update(numbers={"f [px]": res.camera.f, "kappa [px^-2]": res.camera.kappa, "cx [px]": res.camera.cx,
                         "cy [px]": res.camera.cy, "aspect": res.camera.aspect, "views used": res.views_used,
                         "residual rms [px]": res.rms_px,
                         "stop rule: sigma centre [px]": f"{sr['sigma_centre_px']:.3f} (limit {sr['limit_centre_px']})",
                         "stop rule: sigma aspect [%]": f"{sr['sigma_aspect_pct']:.4f} (limit {sr['limit_aspect_pct']})"})
    view.update(views=[{"view": v.name, "discs": v.discs, "dropped": v.dropped, "rms [px]": v.rms_px,
                            "tilt [deg]": v.tilt_deg, "distance [mm]": v.distance_mm, "used": "yes"} for v in res.views]
                + [{"view": sk["name"], "discs": 0, "dropped": 0, "rms [px]": None, "tilt [deg]": None,
                    "distance [mm]": None, "used": f"no: {sk['reason']}"} for sk in res.skipped]
                + [{"view": nm, "discs": 0, "dropped": 0, "rms [px]": None, "tilt [deg]": None,
                    "distance [mm]": None, "used": "no: rejected on the page"} for nm in rejected],
                bars=view_coverage(res, plate) if plate is not None else None)
    view.verdict(bool(sr["met"]) and not (xc.get("done") and not xc.get("agree")),
                 "stop rule met" + ("" if not xc.get("done") else ", halves agree" if xc.get("agree") else
                                    ", but the halves DISAGREE") if sr["met"] else
                 "stop rule not met: " + sr.get("advice", ""))


#: What the views should span for full bars: the plate's discs over 60 % of the picture's width and height
#: (5th to 95th percentile of every view's discs), the plate's distance over 25 % of its mean, a tilt of
#: 30 deg (the centre and the aspect need tilted views).
COVERAGE_GOALS = {"x": 0.6, "y": 0.6, "size": 0.25, "tilt": 30.0}


def view_coverage(res, plate) -> dict:
    """Coverage bars of a set of views (``selfview.estimation.intrinsics`` result) of ``plate`` (``selfview.files.cell``'s):
    ``coverage_bars`` of the disc centres the fitted poses put in the picture and of the fitted poses."""
    from selfview.maths.geometry import transform_points

    cam = res.camera
    if not res.views:
        return {}
    pW = plate.disc_centres_W()
    uv = np.vstack([cam.project(transform_points(np.asarray(v.C_H_W, float), pW)) for v in res.views])
    return coverage_bars(uv, cam.width, cam.height, [v.C_H_W for v in res.views])


def coverage_bars(uv, width: int, height: int, poses) -> dict:
    """Coverage bars of views: x, y the span of the plate points ``uv`` (N, 2) of every view in a
    ``width`` x ``height`` picture (5th to 95th percentile) over its width and height, size the span of the
    plate's distance over its mean, tilt the largest tilt [deg] (``poses``: each view's ``C_H_W``,
    ``selfview.estimation.intrinsics.view_tilt_distance``); each {value, goal, fraction (0..1)}. The stop
    rule decides; the bars say which kind of view would help."""
    from selfview.estimation.intrinsics import view_tilt_distance

    if not len(poses):
        return {}
    uv = np.asarray(uv, float).reshape(-1, 2)
    uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)]
    span = (np.percentile(uv, 95, axis=0) - np.percentile(uv, 5, axis=0)) if len(uv) else np.zeros(2)
    td = np.array([view_tilt_distance(H) for H in poses])
    vals = {"x": float(span[0] / width), "y": float(span[1] / height),
            "size": float(np.ptp(td[:, 1]) / td[:, 1].mean()), "tilt": float(td[:, 0].max())}
    return {k: {"value": vals[k], "goal": g, "fraction": float(min(1.0, vals[k] / g))} for k, g in COVERAGE_GOALS.items()}


def tracked_frames(view: LiveView, calibration, cell):
    """``CellSession.monitor``'s ``on_frame``: each tracked frame on the page, the fingers' silhouette and
    corners drawn where the current C_H_G puts them."""
    from selfview.files.calfile import load_calibration
    from selfview.estimation.pcc import jaw_gap_of
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
    view.log({"frame": rec.get("frame"), "decision": rec.get("action"), "method": rec.get("method") or "",
              "delta [deg]": rec.get("delta_deg"), "d [mm]": rec.get("d_mm"), "rms [px]": rec.get("rms_px"),
              "TCP 1-sigma z [mm]": (rec.get("tcp_sigma_mm") or [None] * 3)[2], "why": rec.get("reason") or ""})
    if rec.get("action") == "alarm":
        view.alarm(f"alarm at frame {rec.get('frame')}: {rec.get('reason')}")
    else:
        view.verdict(True, f"frame {rec.get('frame')}: {rec.get('action')} ({rec.get('reason')})")


class ViewProgress:
    """``Engine.on_step`` for the views of ``CellSession.intrinsics_views`` (``views`` planned; None: the operator's,
    ``CellSession.operator_views``): one line per view with the time left for the views (from the time per view
    so far), and on the live view each picture as it comes with
    the plate's discs found in it and the picture's coverage by all the views so far."""

    def __init__(self, say, views: int, engine, cell, view=None, grid: int = 4):
        import time

        self.say, self.views, self.engine, self.cell, self.view, self.grid = say, views, engine, cell, view, grid
        self.t0 = time.monotonic()
        self.pending = None
        self.covered = set()
        self.canvas = None
        self.taken: list = []  # the plate found in each view taken (``detect_plate``'s), for the live feed's coverage

    def __call__(self, n, step) -> None:
        import time

        self.flush()
        if step.kind == "grab" and (step.name or "").startswith("view"):
            i = int(step.name[4:])
            el = time.monotonic() - self.t0
            if self.views is None:  # the operator takes the views: no plan, no time left
                self.say(f"view {i}: taken on the page, grabbing; elapsed {el:.1f} s")
            else:
                self.say(f"view {i} of {self.views}: at its pose, grabbing; elapsed {el:.1f} s, "
                         f"views left ~{el / i * (self.views - i):.0f} s")
            self.pending = step.name if self.view is not None else None

    def flush(self) -> None:
        """Show the view just grabbed now (else the next step's start shows it)."""
        if self.pending:
            self._show(self.pending)
            self.pending = None

    def _show(self, name) -> None:
        import cv2
        import numpy as np

        from selfview.measurement.plates import detect_plate
        from selfview.errors import ImageError

        img = self.engine.results.get(name)
        if img is None:
            return
        big = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        if self.canvas is None:
            self.canvas = np.zeros_like(big)
        try:
            det = detect_plate(img, self.cell.plate, camera=self.cell.camera.guess())
            uv = det.uv
            self.taken.append(det)
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
[hidden]{display:none!important}
#bar{display:flex;align-items:stretch}
#verdict{flex:1;padding:12px 16px;font-size:22px;font-weight:bold;background:#555}
#verdict.go{background:#1b7f2a}#verdict.nogo{background:#b0201a}
button{font-size:18px;font-weight:bold;border:0;padding:0 22px;cursor:pointer}
#stop{background:#e00000;color:#fff;min-width:120px}#stop:disabled{background:#733;color:#ccc}
#alarmbox{padding:8px 16px;background:#7a1010;display:flex;gap:16px;align-items:center}
#ack{background:#ffd84a;color:#000;padding:6px 16px}
#askbox{padding:8px 16px;background:#1d3f6e;display:flex;gap:16px;align-items:center}
#askbuttons button{background:#9cf;color:#000;padding:6px 16px;margin-right:8px}
#doing{padding:6px 16px;background:#333;font-family:monospace}
main{display:flex;flex-wrap:wrap;gap:12px;padding:12px}
#framebox{flex:1 1 760px;max-width:1000px}#frame{width:100%;background:#000;display:block}
#side{flex:1 1 360px;max-width:600px}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #555;padding:2px 6px;text-align:right}
th{background:#333}section{min-width:320px}h2{font-size:15px;margin:8px 0 4px}
#logwrap{max-height:260px;overflow-y:auto}svg{background:#111}
#log td:last-child{text-align:left;min-width:300px;font-size:11px}
#views td:first-child{white-space:nowrap}
.barout{width:220px;height:14px;background:#444}.barin{height:14px;background:#3a9}
#livebox{margin-bottom:12px}#live{width:100%;background:#000;display:block;outline:3px solid #3a9}
.barnow{position:relative;height:14px;background:#3a9}#livecaption{font-size:18px;margin:0 0 6px;color:#7f7}#livecaption.nf{color:#f77}
.barout{position:relative}.barnext{position:absolute;top:0;left:0;height:14px;background:#3a96;outline:1px dashed #9fc}
</style></head><body>
<div id="bar"><div id="verdict">waiting for a verdict</div>
<button id="stop" title="abort the robot and make the valve safe (as Ctrl-C)">STOP</button></div>
<div id="alarmbox" hidden><span id="alarmtext"></span><button id="ack">acknowledge the alarm</button></div>
<div id="askbox" hidden><span id="asktext"></span><span id="askbuttons"></span></div>
<div id="doing">connecting</div>
<main><section id="framebox"><div id="livebox" hidden><h2 id="livecaption">live</h2>
<img id="live" alt="the camera now, with the plate found in it"></div>
<h2 id="framecaption" hidden>the last view taken</h2><a href="frame.jpg" target="_blank" title="the frame at full size">
<img id="frame" alt="latest frame"></a></section>
<section id="side"><div id="livecovbox" hidden><h2>coverage of the views taken, and with the live view (dashed)</h2>
<table id="livecov"></table></div><h2 id="cmd">figures</h2><table id="numbers"></table>
<div id="plotbox" hidden><h2>change of the camera over time</h2><svg id="plot" width="360" height="240"></svg></div>
<div id="logbox" hidden><h2>decision per frame (newest first)</h2><div id="logwrap"><table id="log"></table></div></div>
<div id="barbox" hidden><h2>coverage of the views (the stop rule decides)</h2><table id="bars"></table></div>
<div id="coveragebox" hidden><h2>coverage of the picture</h2><table id="coverage"></table></div>
<div id="viewbox" hidden><h2>per view</h2><table id="views"></table></div>
<div id="residualbox" hidden><h2>residuals per point</h2><table id="residuals"></table></div></section></main>
<script>
const TOKEN="__TOKEN__";let lastFrame=-1,askKey="",viewsKey="",lastLive=-1,liveBusy=false,liveURL=null;const rejected=new Set();
async function showLive(seq){liveBusy=true;try{const r=await fetch("live.jpg",{headers:{"X-Selfview-Token":TOKEN},cache:"no-store"});
 if(r.ok){const u=URL.createObjectURL(await r.blob());document.getElementById("live").src=u;
  if(liveURL)URL.revokeObjectURL(liveURL);liveURL=u;lastLive=seq;}}catch(e){}finally{liveBusy=false;}}
function live(L){const on=!!(L&&L.on);document.getElementById("livebox").hidden=!on;
 document.getElementById("framecaption").hidden=!on;document.getElementById("livecovbox").hidden=!(on&&L.coverage&&Object.keys(L.coverage).length);if(!L)return;
 const c=document.getElementById("livecaption");c.textContent=L.text+(L.at?" at "+L.at:"");c.className=L.found?"":"nf";
 if(L.on&&L.seq>0&&L.seq!==lastLive&&!liveBusy)showLive(L.seq);
 const t=document.getElementById("livecov");t.innerHTML="";for(const k in (on&&L.coverage||{})){const b=L.coverage[k],r=t.insertRow();
  const f=v=>Math.round(100*Math.min(1,v/b.goal));r.insertCell().textContent=k;
  r.insertCell().innerHTML=`<div class="barout"><div class="barnext" style="width:${f(b.if_taken)}%"></div>`+
   `<div class="barnow" style="width:${f(b.now)}%"></div></div>`;
  r.insertCell().textContent=fmt(b.now)+" \u2192 "+fmt(b.if_taken)+" of "+b.goal;}}
async function act(name,extra){const r=await fetch("action",{method:"POST",headers:{"Content-Type":"application/json",
 "X-Selfview-Token":TOKEN},body:JSON.stringify(Object.assign({action:name},extra||{}))});
 document.getElementById("doing").textContent=r.ok?(await r.json()).said:"refused: "+r.status;}
document.getElementById("stop").onclick=()=>{document.getElementById("stop").disabled=true;act("stop");};
document.getElementById("ack").onclick=()=>act("acknowledge");
function fmt(v){return typeof v==="number"?(Number.isInteger(v)?String(v):Math.abs(v)>=1e-3||v===0?v.toFixed(4):v.toExponential(3)):v===null?"":String(v)}
function rows(t,obj){t.innerHTML="";for(const k in obj){const r=t.insertRow();r.insertCell().textContent=k;
 r.insertCell().textContent=fmt(obj[k]);}}
function table(t,list){t.innerHTML="";if(!list.length)return;const h=t.insertRow();
 for(const k of Object.keys(list[0])){const c=document.createElement("th");c.textContent=k;h.appendChild(c);}
 for(const r of list){const tr=t.insertRow();for(const k in r)tr.insertCell().textContent=fmt(r[k]);}}
function plot(s){const svg=document.getElementById("plot");svg.innerHTML="";if(!s||!s.points)return;
 const L=s.limits||{},P=s.points,W=360,H=240,X0=44,X1=W-10,Y0=H-28,Y1=22,n=Math.max(P.length,2);
 const x=i=>X0+i*(X1-X0)/(n-1);
 const top=Math.max(1.2,...P.map(p=>Math.max((p.delta_deg||0)/L.alarm_deg,(p.d_mm||0)/L.alarm_mm)))*1.05;
 const y=v=>Y0-(v/top)*(Y0-Y1);let h=`<line x1="${X0}" x2="${X0}" y1="${Y1}" y2="${Y0}" stroke="#888"/>`+
  `<line x1="${X0}" x2="${X1}" y1="${Y0}" y2="${Y0}" stroke="#888"/>`;
 const step=top>3?1:top>1.5?0.5:0.25;
 for(let v=0;v<=top+1e-9;v+=step)h+=`<line x1="${X0-4}" x2="${X0}" y1="${y(v)}" y2="${y(v)}" stroke="#888"/>`+
  `<text class="tick" x="${X0-6}" y="${y(v)+4}" fill="#aaa" font-size="10" text-anchor="end">${v.toFixed(2)}</text>`;
 const every=Math.max(1,Math.ceil(P.length/8));
 P.forEach((p,i)=>{if(i%every===0||i===P.length-1)h+=`<line x1="${x(i)}" x2="${x(i)}" y1="${Y0}" y2="${Y0+4}" stroke="#888"/>`+
  `<text class="tick" x="${x(i)}" y="${Y0+15}" fill="#aaa" font-size="10" text-anchor="middle">${p.frame}</text>`;});
 h+=`<text x="${X1}" y="${H-2}" fill="#aaa" font-size="10" text-anchor="end">frame</text>`;
 const N=L.names||["alarm limit","update limit","the alarm limit"];
 const lines=[[1,"#ff4040",`${N[0]} ${L.alarm_deg} deg / ${L.alarm_mm} mm`],
  [L.update_deg/L.alarm_deg,"#e0c000",`${N[1]} ${L.update_deg} deg`],[L.update_mm/L.alarm_mm,"#c08000",`${N[1]} ${L.update_mm} mm`]];
 const used=[];for(const [v,c,t] of lines){let ly=y(v)-3;while(used.some(u=>Math.abs(u-ly)<12))ly-=12;used.push(ly);
  h+=`<line x1="${X0}" x2="${X1}" y1="${y(v)}" y2="${y(v)}" stroke="${c}" stroke-dasharray="4"/>`+
  `<text class="limit" x="${X1-4}" y="${ly}" fill="${c}" font-size="11" text-anchor="end">${t}</text>`;}
 for(const [k,c,a] of [["delta_deg","#6cf",L.alarm_deg],["d_mm","#f8a",L.alarm_mm]])
  h+=`<polyline fill="none" stroke="${c}" points="${P.map((p,i)=>x(i)+","+y((p[k]||0)/a)).join(" ")}"/>`;
 h+=`<text x="${X0}" y="12" font-size="11"><tspan fill="#6cf">rotation</tspan> <tspan fill="#f8a">shift</tspan>`+
  `<tspan fill="#ccc"> as a fraction of ${N[2]}, ${P.length} frames</tspan></text>`;svg.innerHTML=h;}
async function poll(){let s;try{s=await (await fetch("state.json",{cache:"no-store"})).json();}
 catch(e){document.getElementById("doing").textContent="the command has ended; this is its last state";
  document.getElementById("stop").disabled=true;setTimeout(poll,1000);return;}
 try{
 document.getElementById("cmd").textContent="selfview "+s.command;
 document.getElementById("doing").textContent=(s.done?"finished; last step: ":"now: ")+s.doing;
 document.getElementById("stop").disabled=s.done||s.stop_requested;
 const v=document.getElementById("verdict");
 if(s.verdict){v.className=s.verdict.go?"go":"nogo";v.textContent=(s.verdict.go?"GO: ":"NO-GO: ")+s.verdict.why;}
 const a=document.getElementById("alarmbox");a.hidden=!s.alarm;
 if(s.alarm){document.getElementById("alarmtext").textContent=s.alarm.acknowledged?
  "ALARM acknowledged at "+s.alarm.at+": "+s.alarm.why:"ALARM: "+s.alarm.why;document.getElementById("ack").hidden=s.alarm.acknowledged;}
 rows(document.getElementById("numbers"),s.numbers);plot(s.series);live(s.live);
 document.getElementById("plotbox").hidden=!s.series;document.getElementById("coveragebox").hidden=!s.coverage;
 document.getElementById("residualbox").hidden=!s.residuals.length;document.getElementById("logbox").hidden=!s.log.length;
 if(s.coverage)rows(document.getElementById("coverage"),s.coverage);
 document.getElementById("barbox").hidden=!s.bars;if(s.bars){const t=document.getElementById("bars");t.innerHTML="";
  for(const k in s.bars){const b=s.bars[k],r=t.insertRow();r.insertCell().textContent=k;
   r.insertCell().innerHTML=`<div class="barout"><div class="barin" style="width:${Math.round(100*b.fraction)}%"></div></div>`;
   r.insertCell().textContent=fmt(b.value)+" of "+b.goal;}}
 const ak=document.getElementById("askbox");ak.hidden=!s.ask;
 if(s.ask&&JSON.stringify(s.ask)!==askKey){askKey=JSON.stringify(s.ask);document.getElementById("asktext").textContent=s.ask.prompt;
  const bb=document.getElementById("askbuttons");bb.innerHTML="";for(const b of s.ask.buttons){const e=document.createElement("button");
   e.id="ask-"+b.action;e.textContent=b.label;e.onclick=()=>{ak.hidden=true;act(b.action,{reject:[...rejected]});};bb.appendChild(e);}}
 if(!s.ask)askKey="";
 table(document.getElementById("residuals"),s.residuals);
 document.getElementById("viewbox").hidden=!s.views.length;const vk=JSON.stringify([s.views,s.ask]);
 if(vk!==viewsKey){viewsKey=vk;table(document.getElementById("views"),s.views);
 if(s.ask&&s.ask.select==="views"){const t=document.getElementById("views");t.rows[0].insertCell().outerHTML="<th>reject</th>";
  for(let i=1;i<t.rows.length;i++){const nm=t.rows[i].cells[0].textContent,c=document.createElement("input");c.type="checkbox";
   c.id="reject-"+nm.replace(/\\W+/g,"-");c.checked=rejected.has(nm);c.onchange=()=>{c.checked?rejected.add(nm):rejected.delete(nm);};
   t.rows[i].insertCell().appendChild(c);}}}table(document.getElementById("log"),s.log.slice().reverse());
 if(s.frame_seq!==lastFrame&&s.frame_seq>0){lastFrame=s.frame_seq;
  document.getElementById("frame").src="frame.jpg?"+s.frame_seq;}
}catch(e){document.getElementById("doing").textContent="page error: "+e;}
setTimeout(poll,250);}
poll();
</script></body></html>
"""
