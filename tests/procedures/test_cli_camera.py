"""``selfview camera``: Tsai calibration from a correspondence file, run in-process through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from selfview.procedures.cli import EXIT_CALIBRATION, EXIT_CONFIG, EXIT_OK, main


@pytest.fixture
def cc_cd(willson_dir):
    return str(willson_dir / "cc_cd.dat")


def test_json_output_on_willsons_data(cc_cd, capsys):
    rc = main(["camera", "--points", cc_cd, "--principal-point", "258", "204", "--mode", "tsai", "--json"])
    out = capsys.readouterr().out
    assert rc == EXIT_OK
    lines = out.strip().splitlines()
    assert len(lines) == 1  # one JSON object, nothing else on stdout
    res = json.loads(lines[0])
    assert res["f"] == pytest.approx(220.222296 / 0.023, rel=1e-4)
    assert res["kappa"] == pytest.approx(-5.393556e-4 * 0.023**2, rel=1e-4)
    H = np.array(res["C_H_W"])
    assert H.shape == (4, 4) and np.allclose(H[3], [0, 0, 0, 1])
    assert np.allclose(H[:3, :3] @ H[:3, :3].T, np.eye(3), atol=1e-12)
    assert H[:3, 3] == pytest.approx([152.194102, -70.609515, 5375.732834], rel=1e-4)
    assert res["mean_px"] == pytest.approx(0.131654, rel=1e-4)
    assert res["max_px"] == pytest.approx(0.370579, rel=1e-4)
    assert res["sse_px2"] == pytest.approx(2.232979, rel=1e-4)
    assert res["rms_px"] == pytest.approx(np.sqrt(2.232979 / 100), rel=1e-4)
    assert res["mode"] == "tsai" and res["n_points"] == 100 and res["principal_point"] == [258.0, 204.0]


def test_default_mode_prints_a_summary(cc_cd, capsys):
    rc = main(["camera", "--points", cc_cd, "--principal-point", "258", "204"])
    out = capsys.readouterr().out
    assert rc == EXIT_OK
    assert "Tsai coplanar calibration (full) from 100 points" in out
    assert "(258.000, 204.000) px (fixed)" in out
    f = float(out.split("f            =")[1].split()[0])
    assert 9000 < f < 12000  # 207 .. 276 mm on Willson's 0.023 mm pixels
    assert "C_H_W =" in out and "rms" in out


def test_full_centre_reports_the_fitted_centre(cc_cd, capsys):
    rc = main(["camera", "--points", cc_cd, "--principal-point", "258", "204", "--mode", "full+centre", "--json"])
    res = json.loads(capsys.readouterr().out)
    assert rc == EXIT_OK
    assert np.hypot(res["principal_point"][0] - 262.156687, res["principal_point"][1] - 211.703998) < 0.5


def test_willson_mode_reproduces_his_full_optimisation(cc_cd, capsys):
    """ccal.log's full optimisation: f = 257.133427 mm, centre (262.156687, 211.703998), sse 1.213781."""
    argv = ["camera", "--points", cc_cd, "--principal-point", "258", "204", "--mode", "willson", "--size", "576", "384"]
    rc = main([*argv, "--json"])
    res = json.loads(capsys.readouterr().out)
    assert rc == EXIT_OK and res["mode"] == "willson" and res["n_points"] == 100
    assert res["f"] * 0.023 == pytest.approx(257.133427, rel=2e-3)
    assert np.hypot(res["principal_point"][0] - 262.156687, res["principal_point"][1] - 211.703998) < 0.5
    assert res["kappa"] == pytest.approx(-5.954120e-4 * 0.023**2, rel=5e-3)
    assert res["sse_px2"] == pytest.approx(1.213781, rel=3e-4)
    assert res["width"] == 576 and res["height"] == 384
    # the summary shows the fitted centre, not a fixed one
    assert main(argv) == EXIT_OK
    out = capsys.readouterr().out
    assert "Tsai coplanar calibration (willson) from 100 points" in out and "(fixed)" not in out
    cx, cy = (float(v) for v in out.split("principal pt = (")[1].split(")")[0].split(","))
    assert (cx, cy) == pytest.approx(res["principal_point"], abs=1e-3)


def test_help_lists_the_modes(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["camera", "--help"])
    assert exc.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # whatever width argparse wrapped to
    assert all(m in out for m in ("tsai", "full+centre", "willson")) and "Willson's full optimisation" in out


def test_malformed_file_names_the_line(tmp_path, capsys):
    f = tmp_path / "bad.dat"
    f.write_text("# header\n10 10 0 519.1 94.5\n10 30 0 483.4\n")
    rc = main(["camera", "--points", str(f), "--principal-point", "258", "204", "--json"])
    cap = capsys.readouterr()
    assert rc == EXIT_CONFIG
    assert cap.out == ""
    assert "line 3" in cap.err and "expected 5 numbers" in cap.err


def test_missing_file(tmp_path, capsys):
    rc = main(["camera", "--points", str(tmp_path / "absent.dat"), "--principal-point", "258", "204"])
    cap = capsys.readouterr()
    assert rc == EXIT_CONFIG
    assert "no such points file" in cap.err and "absent.dat" in cap.err


def test_degenerate_points_fail_with_the_reason(tmp_path, capsys):
    f = tmp_path / "line.dat"
    f.write_text("".join(f"{10 * i} 0 0 {100 + 20 * i} {50 + 3 * i}\n" for i in range(8)))
    rc = main(["camera", "--points", str(f), "--principal-point", "258", "204"])
    cap = capsys.readouterr()
    assert rc == EXIT_CALIBRATION
    assert "collinear" in cap.err


def test_bad_mode_is_a_usage_error(cc_cd, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["camera", "--points", cc_cd, "--principal-point", "258", "204", "--mode", "bundle"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
