"""``selfview devices``: every device tried on its own, one row each, the exit status says whether all answered."""

import json
import socket

import cv2
import numpy as np

from selfview.mocks.valve_terminal import ValveTerminal
from selfview.procedures.cli import main


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # nothing listens there once the socket is closed


def test_the_simulated_cell_answers_on_every_device(capsys):
    assert main(["devices", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["all_answered"] is True
    rows = {r["device"]: r for r in out["devices"]}
    assert list(rows) == ["robot", "gripper", "camera"]
    assert all(r["status"] == "answered" for r in rows.values())
    assert len(rows["robot"]["pose_xyzoat"]) == 6 and rows["camera"]["size"] == [768, 576]


def test_one_failing_device_leaves_the_others_tried(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "img_000.png"), np.full((576, 768), 90, np.uint8))
    with ValveTerminal(travel_s=0.02) as valve:
        argv = ["devices", "--real", "--robot", f"socket://127.0.0.1:{closed_port()}", "--gripper", valve.url,
                "--camera", f"frames://{tmp_path}/img_%03d.png"]
        assert main(argv + ["--json"]) == 4
        out = json.loads(capsys.readouterr().out)
        assert main(argv) == 4
        text = capsys.readouterr().out
    rows = {r["device"]: r for r in out["devices"]}
    assert out["all_answered"] is False
    assert rows["robot"]["status"] == "failed" and "refused" in rows["robot"]["detail"]
    assert rows["gripper"]["status"] == "answered" and rows["gripper"]["state"] in ("open", "closed", "moving", "unknown")
    assert rows["camera"]["status"] == "answered" and abs(rows["camera"]["mean_grey"] - 90) < 1
    lines = text.splitlines()
    assert lines[0].startswith("robot    failed") and lines[1].startswith("gripper  answered")
    assert lines[2].startswith("camera   answered")


def test_a_device_without_url_is_not_tried(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "img_000.png"), np.full((576, 768), 90, np.uint8))
    assert main(["devices", "--real", "--camera", f"frames://{tmp_path}/img_%03d.png", "--json"]) == 4
    rows = {r["device"]: r for r in json.loads(capsys.readouterr().out)["devices"]}
    assert rows["robot"]["status"] == rows["gripper"]["status"] == "not tried"
    assert "--robot URL" in rows["robot"]["detail"] and rows["camera"]["status"] == "answered"


def test_reset_of_the_operators_arm_says_there_is_nothing_to_abort():
    from selfview.procedures.commands.devices import reset_devices

    assert reset_devices({"robot": "manual://"}) == [
        "robot: the operator's arm (manual://) has no controller to ABORT; stop it by hand"]
