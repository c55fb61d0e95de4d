import numpy as np
import pytest
import yaml

from selfview.files.calfile import Calibration, history_dir, load_calibration, save_calibration
from selfview.maths.camera import CameraModel
from selfview.errors import CalibrationFileError
from selfview.maths.geometry import H_from_rotvec


def make_cal(rng, f=962.0):
    return Calibration(
        camera=CameraModel(f=f, kappa=1.9e-7),
        C_H_W=H_from_rotvec(rng.normal(size=3) * 0.3, [1.0, 2.0, 110.0]),
        C_H_G=H_from_rotvec(rng.normal(size=3) * 0.3, [0.1, -0.2, 111.0]),
        points_G={"open": np.arange(18.0).reshape(6, 3) * 1e-7 + 1 / 3, "closed": np.ones((6, 3))},
        state="open",
        residuals={"rms_px": np.float64(0.0123456789), "discs_used": np.int64(57), "per_disc": np.zeros((2, 2))},
        image_sha256="ab" * 32,
        cell_sha256="cd" * 32,
    )


def test_round_trip_is_exact(tmp_path, rng):
    cal = make_cal(rng)
    p = tmp_path / "cal.yaml"
    assert save_calibration(cal, p) is None
    back = load_calibration(p)
    assert back.camera == cal.camera
    assert np.array_equal(back.C_H_G, cal.C_H_G) or np.allclose(back.C_H_G, cal.C_H_G, atol=1e-15)
    assert np.array_equal(back.points_G["open"], cal.points_G["open"])
    assert back.residuals["discs_used"] == 57 and back.state == "open"
    assert yaml.safe_load(p.read_text())["format"] == "selfview-calibration"


def test_previous_calibration_is_kept(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    first = p.read_bytes()
    kept = save_calibration(make_cal(rng, f=960.0), p)
    assert kept is not None and kept.parent == history_dir(p)
    assert kept.read_bytes() == first
    assert load_calibration(p).camera.f == 960.0
    assert load_calibration(kept).camera.f == 950.0
    assert not list(tmp_path.glob(".cal.yaml.*.tmp"))  # no temporary left behind


@pytest.mark.parametrize(
    "content, message",
    [
        ("camera: [1, 2\n", "not valid YAML"),
        ("just: a mapping\n", "not a selfview calibration"),
        ("", "not a selfview calibration"),
    ],
)
def test_corrupt_or_foreign_files_are_refused_and_kept(tmp_path, rng, content, message):
    p = tmp_path / "cal.yaml"
    p.write_text(content)
    with pytest.raises(CalibrationFileError, match=message):
        load_calibration(p)
    with pytest.raises(CalibrationFileError, match=message):
        save_calibration(make_cal(rng), p)
    assert p.read_text() == content  # nothing overwritten


def test_altered_file_fails_its_checksum(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    doc = yaml.safe_load(p.read_text())
    doc["camera"]["f"] = 1000.0
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match="checksum"):
        load_calibration(p)


def test_truncated_file_is_refused(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(CalibrationFileError):
        load_calibration(p)


def test_unknown_version_and_missing_file(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    doc = yaml.safe_load(p.read_text())
    doc["version"] = 99
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match="version 99"):
        load_calibration(p)
    with pytest.raises(CalibrationFileError, match="no such calibration file"):
        load_calibration(tmp_path / "none.yaml")


# --- hostile files --------------------------------------------------------------------------------
def _rechecksummed(p, doc):
    """Write ``doc`` with a valid checksum, as somebody re-checksumming an edited file would."""
    from selfview.files.calfile import doc_checksum

    body = {k: v for k, v in doc.items() if k != "checksum"}
    doc = dict(body, checksum=doc_checksum(body))
    p.write_text(yaml.safe_dump(doc, sort_keys=False))


ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8)
)


@pytest.mark.parametrize(
    "content, message",
    [
        (ALIAS_BOMB, "alias"),  # 9**9 strings once expanded
        ("a: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper"),
        ("format: selfview-calibration\nversion: " + "9" * 5000 + "\n", "cannot be read"),
        ("x: " + "y" * (2 << 20) + "\n", "bytes"),
        (b"\xff\xfe\x00garbage", "not UTF-8"),
    ],
    ids=["alias-bomb", "deep-nesting", "huge-integer", "huge-file", "not-utf8"],
)
def test_hostile_yaml_is_refused_at_once(tmp_path, rng, content, message):
    p = tmp_path / "cal.yaml"
    (p.write_bytes if isinstance(content, bytes) else p.write_text)(content)
    with pytest.raises(CalibrationFileError, match=message) as e:
        load_calibration(p)
    assert str(p) in str(e.value) and len(str(e.value)) < 600
    with pytest.raises(CalibrationFileError):
        save_calibration(make_cal(rng), p)  # never replaced
    assert p.read_bytes() == (content if isinstance(content, bytes) else content.encode())


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["gripper"]["points_G"]["open"].__setitem__("A-inner-front", [float("nan"), 0.0, 1.0]), "non-finite"),
        (lambda d: d["gripper"]["points_G"]["open"].__setitem__("B-outer-front", [float("inf"), 0.0, 1.0]), "non-finite"),
        (lambda d: d["camera"].__setitem__("f", float("nan")), "camera f"),
        (lambda d: d["camera"].__setitem__("kappa", 10**400), "OverflowError"),
        (lambda d: d["gripper"].__setitem__("points_G", [1, 2]), "points_G is not a table of jaw states"),
        (lambda d: d.__setitem__("camera", "a text"), "TypeError"),
        (lambda d: d["C_H_G"][0].__setitem__(3, float("nan")), "non-finite"),
        # well-typed values that are not what a calibration writes there
        (lambda d: d["gripper"]["points_G"]["open"].__setitem__("A-inner-back", [1, 2, 3]), "not a fingertip shape"),
        (lambda d: d["gripper"]["points_G"]["closed"].__setitem__("B-outer-front", [-13.0, -6.0, 2.5]), "tip plane"),
        (lambda d: d.__setitem__("version", True), "version is True"),
        (lambda d: d.__setitem__("image_sha256", "a string"), "not a SHA-256"),
        (lambda d: d.__setitem__("residuals", None), "residuals is not a table"),
        (lambda d: d.__setitem__("updates", {"x": 1}), "updates is"),
        (lambda d: d["residuals"].__setitem__("tsai_mode", "a string"), "tsai_mode"),
    ],
    ids=["nan-point", "inf-point", "nan-f", "huge-int", "points-list", "camera-text", "nan-transform",
         "point-moved", "point-off-plane", "version-flag", "sha-text", "residuals-null", "updates-table", "tsai-mode"],
)
def test_wrong_values_in_a_rechecksummed_file_are_refused(tmp_path, rng, edit, message):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    doc = yaml.safe_load(p.read_text())
    edit(doc)
    _rechecksummed(p, doc)
    with pytest.raises(CalibrationFileError, match=message) as e:
        load_calibration(p)
    assert str(p) in str(e.value)


def test_cli_maps_a_hostile_calibration_file_to_exit_3(tmp_path, capsys):
    from selfview.procedures.cli import EXIT_CONFIG, main

    p = tmp_path / "bomb.yaml"
    p.write_text(ALIAS_BOMB)
    img = tmp_path / "x.png"
    import cv2

    cv2.imwrite(str(img), np.full((576, 768), 100, np.uint8))
    assert main(["track", "--calibration", str(p), "--image", str(img)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "bomb.yaml" in err and "alias" in err and "Traceback" not in err


# --- writes ------------------------------------------------------------------------------------------
def test_a_write_that_fails_half_way_leaves_the_old_file(tmp_path, rng, monkeypatch):
    """A full disk in the middle of the write: the error names the path and the cause, the old file is
    intact (the writer never writes in place), no temporary file is left."""
    import errno

    from selfview.files import io_safe

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    old = p.read_bytes()
    real = io_safe._write_all

    def half_then_full(fd, data):
        real(fd, data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io_safe, "_write_all", half_then_full)
    with pytest.raises(CalibrationFileError, match="no space left") as e:
        save_calibration(make_cal(rng, f=960.0), p, keep_history=False)
    assert str(p) in str(e.value)
    assert p.read_bytes() == old and load_calibration(p).camera.f == 950.0
    assert sorted(x.name for x in tmp_path.iterdir()) == ["cal.yaml"]  # no temporary file, no lock file beside it


_CRASH = r"""
import os, signal, sys
import numpy as np
from selfview.files import io_safe
from selfview.files.calfile import save_calibration, load_calibration
cal = load_calibration(sys.argv[1])
import dataclasses
cal.camera = dataclasses.replace(cal.camera, f=975.0)
real = io_safe._write_all
def crash(fd, data):
    real(fd, data[: len(data) // 2])
    os.kill(os.getpid(), signal.SIGKILL)  # the power fails half-way through the write
io_safe._write_all = crash
save_calibration(cal, sys.argv[1], keep_history=False)
"""


def test_a_crash_in_the_middle_of_a_write_leaves_the_old_file(tmp_path, rng):
    import os
    import signal
    import subprocess
    import sys

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    old = p.read_bytes()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    r = subprocess.run([sys.executable, "-c", _CRASH, str(p)], capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert p.read_bytes() == old  # no half file under the name, ever
    assert load_calibration(p).camera.f == 950.0
    left = list(tmp_path.glob(".cal.yaml.*.tmp"))  # the killed writer's temporary, named with its pid
    assert len(left) == 1 and left[0].name.split(".")[3].isdigit()
    mine = tmp_path / f".cal.yaml.{os.getpid()}.{'0' * 12}.tmp"  # a live writer's is never touched
    mine.write_bytes(b"being written")
    save_calibration(make_cal(rng, f=960.0), p)  # and the next write goes through, removing the leftover
    assert load_calibration(p).camera.f == 960.0
    assert list(tmp_path.glob(".cal.yaml.*.tmp")) == [mine]


def test_a_file_size_limit_is_a_clear_error(tmp_path, rng):
    import os
    import resource
    import subprocess
    import sys

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    old = p.read_bytes()
    code = (
        "import sys\nfrom selfview.files.calfile import load_calibration, save_calibration\n"
        "from selfview.errors import CalibrationFileError\n"
        "cal = load_calibration(sys.argv[1]); cal.residuals = {'note': 'x' * 100000}\n"
        "try:\n    save_calibration(cal, sys.argv[1], keep_history=False)\n"
        "except CalibrationFileError as e:\n    print(e); sys.exit(3)\n"
    )
    limit = len(old) + 1000

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    r = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True, timeout=60,
                       preexec_fn=small_files, env=env)
    assert r.returncode == 3, r.stderr
    assert str(p) in r.stdout and "file too large" in r.stdout
    assert p.read_bytes() == old and sorted(x.name for x in tmp_path.iterdir()) == ["cal.yaml"]


def test_history_that_is_a_file_and_out_under_a_file(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    old = p.read_bytes()
    history_dir(p).write_text("not a folder")
    with pytest.raises(CalibrationFileError, match="history folder") as e:
        save_calibration(make_cal(rng, f=960.0), p)
    assert str(history_dir(p)) in str(e.value) and p.read_bytes() == old
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    with pytest.raises(CalibrationFileError, match="is a file, not a folder") as e:
        save_calibration(make_cal(rng), blocker / "cal.yaml")
    assert str(blocker) in str(e.value)


def test_missing_folders_are_not_created(tmp_path, rng):
    target = tmp_path / "no" / "such" / "cal.yaml"
    with pytest.raises(CalibrationFileError, match="does not exist"):
        save_calibration(make_cal(rng), target)
    assert not (tmp_path / "no").exists()


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o600])
def test_replacing_keeps_the_permissions(tmp_path, rng, mode):
    import os
    import stat

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    os.chmod(p, mode)
    ino = os.stat(p).st_ino
    kept = save_calibration(make_cal(rng, f=960.0), p)
    st = os.stat(p)
    assert stat.S_IMODE(st.st_mode) == mode
    assert st.st_ino != ino  # replaced by a rename, not rewritten in place
    assert stat.S_IMODE(os.stat(kept).st_mode) == mode


def test_a_calibration_that_does_not_read_back_is_never_written(tmp_path, rng):
    """The new document is checked before it replaces anything (and before the history copy)."""
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    old = p.read_bytes()
    bad = make_cal(rng, f=960.0)
    bad.points_G["open"] = np.full((6, 3), np.nan)
    with pytest.raises(CalibrationFileError, match="non-finite"):
        save_calibration(bad, p)
    assert p.read_bytes() == old and not history_dir(p).exists()


@pytest.mark.parametrize("where, value", [
    (("camera", "f"), 1e30), (("camera", "aspect"), 18446744073709551616), (("camera", "kappa"), 0.5),
    (("camera", "principal_point", 0), -4000.0), (("camera", "width"), 2 ** 40),
    (("C_H_G", 0, 3), 1e12), (("residuals", "rms_px"), float("nan")),
])
def test_values_no_camera_or_cell_has_are_refused_even_with_a_good_checksum(tmp_path, where, value):
    """A corrupted number that still parses and is re-checksummed (the fault campaign's huge_number and
    nan cases) is refused by its physical range, naming the value."""
    from selfview.files.calfile import doc_checksum

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(np.random.default_rng(3)), p)
    doc = yaml.safe_load(p.read_text())
    node = doc
    for k in where[:-1]:
        node = node[k]
    node[where[-1]] = value
    doc["checksum"] = doc_checksum({k: v for k, v in doc.items() if k != "checksum"})
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(CalibrationFileError, match="not a|outside|over|plausible"):
        load_calibration(p)


# --- concurrent writers, links and leftovers ------------------------------------------------------
def test_an_update_replaces_only_the_version_it_was_derived_from(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    started = load_calibration(p)  # a monitor run starts from this version
    save_calibration(make_cal(rng, f=960.0), p)  # a recalibration saved meanwhile
    recal = p.read_bytes()
    started.C_H_G = started.C_H_G.copy()
    started.updates.append({"by": "monitor"})
    with pytest.raises(CalibrationFileError, match="changed since it was read") as e:
        save_calibration(started, p, expected=started)
    import hashlib

    assert started.file_sha256[:12] in str(e.value) and hashlib.sha256(recal).hexdigest()[:12] in str(e.value)
    assert p.read_bytes() == recal  # the recalibration stays
    with pytest.raises(CalibrationFileError, match="changed since it was read"):
        save_calibration(started, p, expected=started.file_sha256)  # the hash alone does the same
    now = load_calibration(p)
    now.updates.append({"by": "monitor"})
    save_calibration(now, p, expected=now)  # derived from what is there: written
    assert load_calibration(p).updates == [{"by": "monitor"}]
    with pytest.raises(CalibrationFileError, match="not read from a file"):
        save_calibration(make_cal(rng), p, expected=make_cal(rng))


def test_writers_of_one_file_take_turns(tmp_path, rng):
    import threading
    import time

    from selfview.files.io_safe import file_lock

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    started = load_calibration(p)
    held, t_saved = threading.Event(), []

    def other_writer():  # takes the lock, replaces the file, then lets go
        with file_lock(p, error=CalibrationFileError):
            held.set()
            time.sleep(0.3)
            save_calibration(make_cal(rng, f=960.0), p.with_name("other.yaml"))
            p.with_name("other.yaml").replace(p)
        t_saved.append(time.monotonic())

    t = threading.Thread(target=other_writer)
    t.start()
    assert held.wait(5)
    with pytest.raises(CalibrationFileError, match="changed since it was read"):
        save_calibration(started, p, expected=started)  # waited for its turn, then saw the new version
    t.join(5)
    assert t_saved and load_calibration(p).camera.f == 960.0
    with file_lock(p, error=CalibrationFileError):
        with pytest.raises(CalibrationFileError, match="another process has been writing"):
            with file_lock(p, error=CalibrationFileError, timeout_s=0.1):
                pass


def test_a_symlinked_file_has_its_target_replaced(tmp_path, rng):
    real = tmp_path / "cells" / "cal.yaml"
    real.parent.mkdir()
    save_calibration(make_cal(rng, f=950.0), real)
    link = tmp_path / "current.yaml"
    link.symlink_to(real)
    save_calibration(make_cal(rng, f=960.0), link)
    assert link.is_symlink() and link.resolve() == real.resolve()
    assert load_calibration(real).camera.f == 960.0 and load_calibration(link).camera.f == 960.0
    assert [load_calibration(k).camera.f for k in history_dir(real).iterdir()] == [950.0]


def test_history_leftovers_of_dead_writers_are_removed(tmp_path, rng):
    import subprocess
    import sys

    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    save_calibration(make_cal(rng, f=955.0), p)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          timeout=60).stdout.strip()
    hd = history_dir(p)
    stale = hd / f".20260101T000000.000000Z-0123abcd.yaml.{dead}.{'a' * 12}.tmp"
    stale.write_bytes(b"half a copy")
    save_calibration(make_cal(rng, f=960.0), p)
    assert not stale.exists() and len(list(hd.iterdir())) == 2


def test_a_file_without_a_checksum_is_refused(tmp_path, rng):
    """A file whose checksum line was lost (an editor, a bad merge) is not trusted: the checksum is what
    tells a calibration from a hand-altered copy."""
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    doc = yaml.safe_load(p.read_text())
    del doc["checksum"]
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match="checksum mismatch"):
        load_calibration(p)
