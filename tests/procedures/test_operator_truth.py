"""What the operator reads is what the fit used: the residuals on the page, in the picture and on the command
line; a sigma that covers the camera model's error; the one-call API against the commands."""

import json
import re

import cv2
import numpy as np
import pytest

import selfview
from selfview.files.calfile import load_calibration
from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.procedures.cli import main
from selfview.procedures.results import offline_residuals
from selfview.procedures.view import LiveView, offline_state


@pytest.fixture(scope="module")
def scenes(cell, tmp_path_factory):
    """A parked picture and one after the camera moved (cable pull), for an ideal and a realistic camera,
    with the simulator's true C_H_G of each."""
    d = tmp_path_factory.mktemp("scenes")
    out = {}
    for kind in ("ideal", "realistic"):
        w = SimWorld(cell, seed=4, camera=kind)
        w.park()
        cv2.imwrite(str(d / f"{kind}-parked.png"), render(w, seed=1).image)
        truth = w.C_H_G.copy()
        w.disturb("cable")
        cv2.imwrite(str(d / f"{kind}-moved.png"), render(w, seed=2).image)
        out[kind] = (d / f"{kind}-parked.png", truth, d / f"{kind}-moved.png", w.C_H_G.copy())
    return d, out


def test_page_picture_and_command_show_the_residuals_the_fit_used(cell, scenes, tmp_path, capsys):
    _, s = scenes
    parked = s["ideal"][0]
    assert main(["calibrate", "--image", str(parked), "--out", str(tmp_path / "c.yaml"), "--no-pictures"]) == 0
    text = capsys.readouterr().out
    printed = float(text.split("residual rms ")[1].split(" px")[0])
    pc = selfview.calibrate_picture(parked, cell=cell)
    rows = offline_residuals(pc.offline)
    r = np.array([row["|r| [px]"] for row in rows])
    dv = np.array([row["dv [px]"] for row in rows])
    s_ = pc.offline.summary()
    # the table's residuals are the fit's: their RMS and max are the headline's
    assert len(rows) == s_["discs_used"]
    assert np.sqrt(np.mean(r**2)) == pytest.approx(s_["rms_px"], rel=1e-9)
    assert r.max() == pytest.approx(s_["max_px"], rel=1e-9)
    assert printed == pytest.approx(s_["rms_px"], abs=5e-4)
    # no systematic shift left in them (against the raw centroids every disc read 0.1-0.2 px up)
    assert abs(dv.mean()) < 0.5 * s_["rms_px"]
    # the page shows the same rows and the same headline
    view = LiveView("calibrate")
    offline_state(view, cv2.imread(str(parked), cv2.IMREAD_GRAYSCALE), pc)
    st = view.state()
    assert st["residuals"] == json.loads(json.dumps(rows))
    assert st["numbers"]["residual rms [px]"] == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-9)
    assert st["verdict"] == {"go": True, "why": pc.reason}
    # the picture's arrows start at the centres the fit used and end at the model's projections
    model = pc.offline.calibration.camera.project(
        (pc.offline.calibration.C_H_W[:3, :3] @ pc.offline.discs.p_W.T).T + pc.offline.calibration.C_H_W[:3, 3])
    ends = np.asarray(pc.offline.disc_uv_corrected) + pc.offline.disc_residuals_px()
    assert np.sqrt(np.mean(np.sum((ends - model) ** 2, axis=1))) < 0.01 * s_["rms_px"] + 1e-9


def test_an_unmeasured_camera_reports_the_sigma_its_warning_implies(cell, scenes, tmp_path, capsys):
    _, s = scenes
    parked, truth, *_ = s["realistic"]
    pc = selfview.calibrate_picture(parked, cell=cell)
    e = pc.C_H_G[:3, 3] - truth[:3, 3]
    assert abs(e[2]) > 1.0  # the nominal camera costs millimetres here
    shift = np.abs(pc.camera_check["tcp_shift_mm"])
    sg = np.asarray(pc.tcp_sigma_mm)
    assert np.all(sg >= shift) and "camera_model" in pc.sigma_parts_mm
    assert np.all(np.abs(e) <= 2 * sg)  # the error is within two of its own sigmas on every axis
    assert pc.verdict == "no-go" and "camera_model" in pc.reason and "selfview intrinsics" in pc.reason
    # the command prints and records that sigma, and says NO-GO
    cal = tmp_path / "c.yaml"
    assert main(["calibrate", "--image", str(parked), "--out", str(cal), "--no-pictures"]) == 0
    out = capsys.readouterr().out
    z = float(out.split("TCP 1-sigma:")[1].split(" z ")[1].split(" mm")[0])
    assert z == pytest.approx(sg[2], abs=1e-4) and z > 1.0
    assert "\nNO-GO: " in out
    assert load_calibration(cal).residuals["tcp_sigma_mm"] == pytest.approx(list(sg))
    # the ideal camera: no model error, go, micrometres
    good = selfview.calibrate_picture(s["ideal"][0], cell=cell)
    assert good.go and "camera_model" not in good.sigma_parts_mm and max(good.tcp_sigma_mm) < 0.08


def test_the_one_call_api_gives_what_the_commands_give(cell, cell_path, scenes, tmp_path, capsys):
    _, s = scenes
    parked, truth, moved, truth_moved = s["ideal"]
    pc = selfview.calibrate_picture(str(parked), cell=cell)
    assert np.linalg.norm(pc.C_H_G[:3, 3] - truth[:3, 3]) < 0.05
    cal = tmp_path / "api.yaml"
    pc.save(cal)
    assert main(["calibrate", "--image", str(parked), "--out", str(tmp_path / "cli.yaml"), "--json", "--no-pictures"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert np.allclose(cli["C_H_G"], pc.C_H_G, atol=1e-9) and cli["tcp_sigma_mm"] == pytest.approx(pc.tcp_sigma_mm)
    assert cli["verdict"] == pc.verdict == "go"
    tr = selfview.track(moved, cal, method="auto", cell=cell)
    assert tr.verdict == "go" and tr.decision in ("update", "recalibrate")
    e = tr.C_H_G_orthonormal[:3, 3] - truth_moved[:3, 3]
    sg = np.asarray(tr.tcp_sigma_mm)
    assert np.all(sg >= np.asarray(pc.tcp_sigma_mm) - 1e-12)  # the calibration's own sigma is part of it
    assert np.all(np.abs(e) <= 4 * sg), (e, sg)
    assert main(["track", "--cell", str(cell_path), "--calibration", str(cal), "--image", str(moved), "--method", "auto", "--json",
                 "--no-pictures"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert np.allclose(cli["C_H_G"], tr.C_H_G, atol=1e-9) and cli["tcp_sigma_mm"] == pytest.approx(tr.tcp_sigma_mm)
    # a named method, and bad arguments named
    t4 = selfview.track(moved, cal, method="4P-I", cell=cell)
    assert t4.points_used == ["A-inner-front", "A-inner-back", "B-inner-front", "B-inner-back"]
    with pytest.raises(selfview.ConfigError, match="method '4P-X'"):
        selfview.track(moved, cal, method="4P-X", cell=cell)
    with pytest.raises(selfview.ImageError, match="nope.png"):
        selfview.calibrate_picture(tmp_path / "nope.png", cell=cell)


def test_an_out_in_a_missing_folder_is_named_before_any_work(scenes, tmp_path, capsys):
    _, s = scenes
    out = tmp_path / "no" / "dir" / "c.yaml"
    assert main(["calibrate", "--image", str(s["ideal"][0]), "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert f"--out {out}: the folder" in err and "does not exist" in err and ".tmp" not in err
    assert not out.parent.exists()


def test_a_mistyped_option_or_choice_gets_a_did_you_mean(capsys):
    assert main(["calibrate", "--image", "p.png", "--forse"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: selfview calibrate ") and "unrecognized arguments: --forse" in err
    assert "--forse: did you mean --force?" in err
    with pytest.raises(SystemExit) as stop:
        main(["calibrat", "--image", "p.png"])
    assert stop.value.code == 2 and "did you mean calibrate" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["track", "--calibration", "c.yaml", "--image", "p.png", "--method", "4P-X"])
    assert stop.value.code == 2 and "did you mean 4P-" in capsys.readouterr().err


def test_a_report_whose_part_fails_exits_non_zero(tmp_path, capsys):
    bench = tmp_path / "bench"
    bench.mkdir()
    argv = ["report", "--only", "online", "--trials", "0", "--bench-dir", str(bench), "--out", str(tmp_path / "R.md")]
    assert main(argv) == 3  # the benchmark is not there: a matter of files
    err = capsys.readouterr().err
    assert "online not available" in err and "--bench-dir" in err
    (bench / "online.py").write_text("import sys\nsys.exit('no plate')\n")
    assert main(argv) == 1  # it ran and failed
    err = capsys.readouterr().err
    assert "online failed" in err and "--only NAME" in err
    assert (tmp_path / "R.md").is_file()  # the report is still written, saying so


def test_robot_motions_say_what_they_did_and_each_refusal_its_own_advice(capsys):
    """``robot ready`` on an uncalibrated controller says to calibrate (not to check the cable); a motion that
    succeeds says which one it was."""
    import select
    import signal
    import subprocess
    import sys

    from tests.conftest import REPO

    proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", "mock", "robot", "--link", "tcp",
                             "--duration", "20", "--time-scale", "0.02"], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        assert select.select([proc.stdout], [], [], 30.0)[0], "the mock printed no URL within 30 s"
        url = proc.stdout.readline().strip()
        assert main(["robot", "--url", url, "ready"]) == 4
        err = capsys.readouterr().err
        assert "Robot not calibrated" in err and "what to do: calibrate the arm first" in err and "cable" not in err
        assert main(["robot", "--url", url, "calibrate"]) == 0
        assert capsys.readouterr().out.startswith("CAL done")
        assert main(["robot", "--url", url, "ready"]) == 0
        assert capsys.readouterr().out.startswith("READY done; the arm is now at:\n")
        assert main(["robot", "--url", url, "depart", "10"]) == 0
        assert capsys.readouterr().out.startswith("DEPART done (depart(distance_mm=10.0)); the arm is now at:\n")
        assert main(["robot", "--url", url, "move", "nowhere"]) == 4
        assert "what to do: teach it first" in capsys.readouterr().err
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        proc.stdout.close()


def test_a_new_calibration_says_what_moved_since_the_previous_one(cell, scenes, tmp_path, capsys):
    _, s = scenes
    cal = tmp_path / "c.yaml"
    assert main(["calibrate", "--image", str(s["ideal"][0]), "--out", str(cal), "--json", "--no-pictures"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["against_previous"] is None  # nothing to compare with
    assert main(["calibrate", "--image", str(s["realistic"][0]), "--out", str(cal), "--json", "--no-pictures"]) == 0
    second = json.loads(capsys.readouterr().out)
    ch = second["against_previous"]
    moved = np.asarray(second["C_H_G"])[:3, 3] - np.asarray(first["C_H_G"])[:3, 3]
    assert ch["tcp_moved_mm"] == pytest.approx(moved.tolist(), abs=1e-9) and ch["tcp_moved_norm_mm"] > 1.0
    assert ch["f_changed_px"] == pytest.approx(second["f"] - first["f"]) and not ch["same_picture"]
    assert main(["calibrate", "--image", str(s["realistic"][0]), "--out", str(cal), "--no-pictures"]) == 0
    out = capsys.readouterr().out
    assert "against the previous calibration: TCP moved x +0.0000  y +0.0000  z +0.0000 mm (0.0000 mm)" in out


def test_the_online_picture_shows_each_methods_tcp_apart(cell, scenes, tmp_path):
    """Methods that agree to a thousandth of a pixel are drawn on top of each other; the inset shows each
    one's TCP at its magnified offset, in its colour."""
    import types

    from selfview.procedures.results import annotate_online

    _, s = scenes
    parked, _, moved, _ = s["ideal"]
    pc = selfview.calibrate_picture(parked, cell=cell)
    ests, ft = {}, None
    for m in ("3P-U", "4P-U", "4P-R"):
        t = selfview.track(moved, pc.calibration, method=m, cell=cell)
        ests[m], ft = types.SimpleNamespace(C_H_G_orth=t.C_H_G_orthonormal), t.fingertips
    img = cv2.imread(str(moved), cv2.IMREAD_GRAYSCALE)
    out = annotate_online(img, pc.calibration.camera, pc.C_H_G, ests, ft, pc.calibration.points_G[pc.calibration.state],
                          tmp_path / "online.png")
    pic = cv2.imread(str(out))
    inset = pic[-310:-10, -310:-10].astype(int)
    for colour in ((0, 0, 255), (0, 128, 255), (0, 200, 0)):  # 3P-U, 4P-U, 4P-R: a dot of each in the inset
        assert np.count_nonzero(np.abs(inset - colour).sum(axis=2) < 40) >= 20, colour


def test_ctrl_c_in_an_experiment_keeps_the_finished_trials_and_says_one_thing(tmp_path, capsys, monkeypatch):
    import signal
    import threading

    import selfview.procedures.runs as runs

    finished = threading.Event()
    real = runs.run_trial
    count = [0]

    def trial(*a, **kw):
        out = real(*a, **kw)
        count[0] += 1
        if count[0] == 2:
            finished.set()
        return out

    monkeypatch.setattr(runs, "run_trial", trial)
    main_thread = threading.get_ident()
    ctrl_c = threading.Thread(target=lambda: finished.wait(120) and signal.pthread_kill(main_thread, signal.SIGINT))
    ctrl_c.start()
    out = tmp_path / "run"
    try:
        code = main(["experiment", "--trials", "6", "--series", "cable", "--out", str(out), "--profile", "ideal",
                     "--sim-camera", "ideal", "--seed", "3"])
    finally:
        ctrl_c.join(120)
    err = capsys.readouterr().err
    assert code == 130, err
    res = json.loads((out / "results.json").read_text())
    n = res["config"]["trials_finished"]
    assert n >= 2 and len(res["trials"]) == n and "interrupted" in res["summary"]["interrupted"]
    assert (out / "tables.md").is_file()
    tail = err[err.index("interrupted by the operator"):]
    assert f"the {n} finished trial(s) are kept in {out}/" in tail
    assert tail.count("ABORT sent") == 2  # once in the cleanup's line, once in the error; one outcome each
    assert "confirmed" in tail and not re.search(r"trial \d+ of", tail)  # no progress after the interrupt


def test_the_monitors_updates_carry_their_sigma_with_the_calibrations(tmp_path, capsys):
    cal = tmp_path / "cal.yaml"
    assert main(["calibrate", "--out", str(cal), "--no-pictures", "--json"]) == 0
    own = np.asarray(json.loads(capsys.readouterr().out)["tcp_sigma_mm"])
    assert main(["monitor", "--calibration", str(cal), "--frames", "4", "--drift", "0.05", "--json"]) == 0
    recs = [json.loads(ln) for ln in capsys.readouterr().out.splitlines() if ln.startswith("{")]
    updates = [r for r in recs if r["action"] in ("update", "recalibrate")]
    assert len(updates) >= 3
    for r in updates:
        sg = np.asarray(r["tcp_sigma_mm"])
        assert sg.shape == (3,) and np.all(sg >= own - 1e-12) and np.all(sg < 0.5)
    assert main(["monitor", "--calibration", str(cal), "--frames", "2"]) == 0
    assert re.search(r"rms \d\.\d{3} px, TCP 1-sigma z \d\.\d{4} mm - ", capsys.readouterr().out)


def test_the_corner_floor_is_what_the_corner_search_achieves_and_the_sigma_covers_the_error(cell):
    """``CORNER_FLOOR_PX`` against the corner search's error on rendered pictures whose corners are known, and
    the TCP's sigma (ideal camera) against the TCP's error: neither a sigma far below the error nor far above."""
    from selfview.maths.geometry import transform_points
    from selfview.estimation.intrinsics.checks import CORNER_FLOOR_PX

    errs, ratios = [], []
    for seed in (11, 12, 13, 14):
        w = SimWorld(cell, seed=seed)
        w.park()
        pc = selfview.calibrate_picture(render(w, seed=1).image, cell=cell)
        ft = pc.offline.fingertips
        found = np.asarray(ft.found, bool)
        truth = w.camera.project(transform_points(w.C_H_G, cell.gripper.points_G(pc.calibration.state)))
        errs.append(ft.uv[found] - truth[found])
        ratios.append((pc.C_H_G[:3, 3] - w.C_H_G[:3, 3]) / np.asarray(pc.tcp_sigma_mm))
    rms = np.sqrt(np.mean(np.vstack(errs) ** 2, axis=0))
    assert np.all(rms > 0.5 * np.asarray(CORNER_FLOOR_PX)) and np.all(rms < 2.0 * np.asarray(CORNER_FLOOR_PX)), rms
    r = np.sqrt(np.mean(np.square(ratios), axis=0))  # 1: the sigma is the error's size
    assert np.all(r < 2.0) and np.all(r > 0.2), r


def test_verify_with_an_unmeasured_camera_says_no_go_whatever_the_spread(capsys):
    """The parks share the camera's error, so they agree with each other while all are millimetres off: the
    verdict names it instead of passing on the spread."""
    code = main(["verify", "--parks", "3", "--sim-camera", "realistic", "--target-mm", "0.5", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 5 and out["verdict"] == "no-go"
    assert max(out["spread_mm"]) < 0.5  # the spread alone would say go
    assert "which the spread cannot see" in out["reason"] and "selfview intrinsics" in out["reason"]
    shared = np.asarray(out["camera_model_sigma_mm"])
    assert shared.max() > 0.5 and np.all(np.asarray(out["sigma_mm"]) >= shared - 1e-9)
    err = np.abs(np.asarray(out["truth_error_mm"]))
    assert err.max() > 0.5 and np.all(err <= 3 * np.asarray(out["sigma_mm"]))  # the sigma covers the error
