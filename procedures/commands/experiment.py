"""``selfview experiment``: the paper's section 5 (Tables 1 and 2) on a simulated or real cell."""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from selfview.procedures.commands._common import add_view_arguments, numeric, print_json
from selfview.procedures.commands._session import add_session_arguments, open_session, progress_printer
from selfview.procedures.view import viewing, watch, with_progress


def register(sub):
    p = sub.add_parser(
        "experiment",
        help="the paper's experiment: park, calibrate, disturb the camera, re-measure (Tables 1 and 2)",
        description=(
            "The paper's experiment (section 5). For each series (cable: the TCP moves about 1.5 mm along C x; "
            "tilt: about 4.5 mm along C y), N trials of: park the gripper on the plate, calibrate off-line, disturb "
            "the camera (simulation: through the simulated world; real cell: the operator pulls the cable and presses "
            "Enter), take a second picture, apply 3P-U, 4P-U, 5P-U, 4P-R, 5P-R, 3P-I, 4P-I, 5P-I, run the off-line "
            "method on the second picture as the reference, compare the TCP per camera axis. Prints both tables "
            "(ours beside the paper's) and writes a results folder: results.json, tables.md, annotated pictures, "
            "errors.png. A run never overwrites an earlier run's folder."
        ),
    )
    # the same simulated cell as every command's; --profile realistic --sim-camera realistic: a real cell's
    # imperfections and a camera that is not the nominal one, measured first as a lab would with a new camera
    add_session_arguments(p)
    p.add_argument("--trials", type=numeric(integer=True, lo=1, hi=10_000, name="trials"), default=20, help="trials per series (default %(default)s)")
    p.add_argument("--series", nargs="+", default=["cable", "tilt"], help="series to run (default: cable tilt)")
    p.add_argument("--out", metavar="DIR", help="results folder (must be new or empty; default runs/experiment-TIME)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--intrinsics", action=argparse.BooleanOptionalAction, default=None,
                   help="measure the camera first (the robot takes the views of 'selfview intrinsics') and calibrate "
                        "with it, as a lab does with a new camera (default: on with --sim-camera realistic)")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    with viewing(args, "experiment") as view:
        return _start(args, view)


def _start(args, view) -> int:
    from selfview.procedures.results import new_run_dir

    say = with_progress(view, progress_printer(args.quiet))
    cell, session = open_session(args, say)
    given_existed = args.out is not None and Path(args.out).is_dir()
    folder = None if args.dry_run else new_run_dir(args.out)
    try:
        return _run(args, cell, session, folder, say, view)
    except BaseException:
        if folder is not None and not getattr(session, "experiment_kept", False):
            _discard(folder, keep_folder=given_existed)
        raise


def _discard(folder: Path, *, keep_folder: bool) -> None:
    """Remove what a failed run left in its results folder (new or empty when the run began), and the
    folder itself unless it existed before: a half-written run is never taken for a result."""
    try:
        for entry in folder.iterdir():
            shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
        if not keep_folder:
            folder.rmdir()
    except OSError as exc:
        print(f"selfview experiment: could not remove the incomplete results folder {folder} ({exc.strerror or exc})",
              file=sys.stderr)


def _config(args, session, intrinsics) -> dict:
    return {"trials": args.trials, "series": list(args.series), "seed": args.seed, "real": args.real,
            "profile": None if args.real else args.profile,
            "time_scale": args.time_scale, "urls": vars(session.urls), "sim_camera": args.sim_camera,
            "intrinsics": bool(intrinsics)}


def _camera_info(summary, cam_info, session) -> None:
    if cam_info is not None:
        if session.sim is not None:
            cam_info["truth"] = session.sim.world.camera.to_dict()
        summary["camera"] = cam_info


def _keep_finished(exc, args, cell, session, folder, cam_info, intrinsics):
    """An interrupted run: the trials it finished written to ``folder`` (marked interrupted), and the
    interruption's error saying so (one message: the stop and what was kept)."""
    from selfview.procedures.engine import Cancelled
    from selfview.procedures.experiment import summarise
    from selfview.procedures.runs import write_experiment_folder

    part = getattr(session, "experiment_partial", None) or {}
    records = part.get("records") or []
    if folder is None or not records:
        return exc
    summary = summarise(records)
    summary["failures"] = part.get("failures", [])
    summary["interrupted"] = str(exc)
    _camera_info(summary, cam_info, session)
    config = _config(args, session, intrinsics) | {"trials_finished": len(records)}
    try:
        write_experiment_folder(folder, records, summary, part.get("first"), cell=cell, config=config)
    except Exception as err:  # noqa: BLE001 - the interruption is what the operator must hear about
        return Cancelled(f"{exc}; the {len(records)} finished trial(s) could not be kept ({err})", exc.signum)
    session.experiment_kept = True
    return Cancelled(f"{exc}; the {len(records)} finished trial(s) are kept in {folder}/", exc.signum)


def _run(args, cell, session, folder, say, view) -> int:
    from selfview.procedures.engine import Cancelled
    from selfview.procedures.experiment import tables_markdown
    from selfview.procedures.intrinsics import measure_camera
    from selfview.procedures.runs import write_experiment_folder

    total = args.trials * len(args.series)
    t0 = [time.monotonic()]  # the trials' start: the measuring of the camera is timed apart
    done = [0]
    rows = []

    def on_trial(series, k, n, rec):
        if session.engine is not None and session.engine.cancel.is_set():
            return  # interrupted: the stop is reported once, nothing after it
        done[0] += 1
        el = time.monotonic() - t0[0]
        rem = el / done[0] * (total - done[0])
        e4 = rec.estimates.get("4P-U", {}).get("err_ref_mm")
        extra = f"; 4P-U vs reference {' '.join(f'{v:.3f}' for v in e4)} mm" if e4 else ""
        say(f"{series} trial {k + 1} of {n} ({done[0]}/{total}), trials elapsed {el:.0f} s, remaining ~{rem:.0f} s{extra}")
        if view and e4:
            rows.append({"trial": f"{series} {k + 1}", **{f"4P-U vs reference {a} [mm]": v for a, v in zip("xyz", e4)}})
            view.update(residuals=rows, numbers={"trials done": f"{done[0]} of {total}", "remaining [s]": round(rem)})

    intrinsics = args.intrinsics if args.intrinsics is not None else (args.sim_camera == "realistic" and not args.real)
    cam_info = None
    with session:
        watch(view, session)
        camera = None
        if intrinsics:
            camera, cam_info = measure_camera(session, say, view)
        t0[0] = time.monotonic()
        try:
            out = session.experiment(series=tuple(args.series), trials=args.trials, on_trial=on_trial, camera=camera)
        except Cancelled as exc:
            exc = _keep_finished(exc, args, cell, session, folder, cam_info, intrinsics)
            raise exc from None
    if args.dry_run:
        return 0
    records, summary, first = out
    _camera_info(summary, cam_info, session)
    results = write_experiment_folder(folder, records, summary, first, cell=cell,
                                      config=_config(args, session, intrinsics))
    if view:
        fails = summary.get("failures") or []
        view.verdict(not fails, f"{len(records)} trials done, results in {folder}" if not fails else
                     f"{len(fails)} trial(s) failed: {fails[0]['error']}")
    if args.json:
        print_json({"folder": str(folder), "summary": summary, "files": results["files"]})
    else:
        print(tables_markdown(summary))
        print(f"results written to {folder}/ (results.json, tables.md, errors.png, annotated pictures)")
    return 0
