import copy

import numpy as np
import pytest
import yaml

from selfview.files.cell import POINT_NAMES, default_cell_path, load_cell, parse_cell
from selfview.errors import ConfigError


@pytest.fixture(scope="module")
def raw(cell_path):
    return yaml.safe_load(cell_path.read_text())


def test_reference_cell_loads_as_it_is(cell, cell_path):
    assert cell.camera.width == 768 and cell.camera.height == 576
    assert cell.camera.principal_point == (383.5, 287.5)
    assert cell.plate.rows == 8 and cell.plate.pitch == 9.0
    assert cell.gripper.states == {"open": 56.0, "closed": 20.0}
    assert cell.monitor.update_limit.angle_deg == 1.0 and cell.monitor.alarm_limit.shift_mm == 10.0
    assert set(cell.simulation.disturbances) == {"cable", "tilt"}
    assert cell.simulation.true_f == 962.0
    R = cell.mount_guess_C_H_G[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert len(cell.sha256) == 64


def test_packaged_copy_is_the_shared_reference_with_the_measured_update_limit(cell, cell_path):
    """The packaged cell is the shared one but for monitor.update_limit, measured by bench/update_limit.py."""
    packaged = load_cell(default_cell_path())
    assert packaged.raw["monitor"]["alarm_limit"] == cell.raw["monitor"]["alarm_limit"]
    for key in set(cell.raw) - {"monitor"}:
        assert packaged.raw[key] == cell.raw[key], key
    lim = packaged.monitor.update_limit
    assert 0 < lim.angle_deg < packaged.monitor.alarm_limit.angle_deg
    text = default_cell_path().read_text()
    assert "measured by bench/update_limit.py" in text
    # apart from the update limit and its comment, the file is the shared one line for line
    diff = [ln for ln in text.splitlines() if ln not in cell_path.read_text().splitlines()]
    assert len(diff) == 2 and all("update_limit" in ln for ln in diff)


def test_fingertip_points_follow_the_conventions(cell):
    P = cell.gripper.points_G("open")
    g, w, t = 56.0, 12.0, 8.0
    assert P.shape == (6, 3) and len(POINT_NAMES) == 6
    assert np.allclose(P[0], [g / 2, -w / 2, 0]) and np.allclose(P[3], [-g / 2, w / 2, 0])
    assert np.allclose(P[4], [g / 2 + t, -w / 2, 0]) and np.allclose(P[5], [-g / 2 - t, -w / 2, 0])
    assert np.allclose(P[:4].mean(0), 0)  # the TCP is the centre of the inner rectangle
    assert np.allclose(cell.gripper.points_G("closed")[0], [10, -6, 0])
    with pytest.raises(ConfigError, match="half-open"):
        cell.gripper.gap("half-open")


def test_plate_disc_centres(cell):
    c = cell.plate.disc_centres_W()
    assert c.shape == (64, 3) and np.allclose(c.mean(0), 0)
    assert np.allclose(c[1] - c[0], [9, 0, 0]) and np.allclose(c[8] - c[0], [0, 9, 0])


def _bad(raw, path, value):
    d = copy.deepcopy(raw)
    node = d
    for k in path[:-1]:
        node = node[k]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


@pytest.mark.parametrize(
    "path, value, message",
    [
        (("plate", "pitch"), -9.0, r"plate\.pitch: expected a positive number, got -9\.0"),
        (("camera", "width"), 0, r"camera\.width: expected a positive whole number, got 0"),
        (("camera", "height"), "576", r"camera\.height: expected a whole number, got '576'"),
        (("plate", "rows"), KeyError, r"plate\.rows: missing key"),
        (("plate", "colour"), "red", r"plate: unknown key\(s\) colour"),
        (("gripper", "calibrate_in"), "ajar", r"gripper\.calibrate_in: expected one of open, closed, got 'ajar'"),
        (("mount_guess", "C_H_G"), [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 110], [0, 0, 0, 1]], r"mount_guess\.C_H_G: not a rigid"),
        (("mount_guess", "C_H_G"), [[1, 0, 0], [0, 1, 0]], r"mount_guess\.C_H_G: expected a 4x4"),
        (("monitor", "update_limit"), {"angle_deg": 1.0}, r"monitor\.update_limit\.shift_mm: missing key"),
        (("monitor", "alarm_limit"), {"angle_deg": 0.5, "shift_mm": 10.0}, r"monitor\.alarm_limit.*must not be below"),
        (("simulation", "image", "noise_gray"), -1, r"simulation\.image\.noise_gray: expected a number >= 0"),
        (("plate", "disc_diameter"), 10.0, r"plate\.disc_diameter: 10\.0 mm; expected less than the pitch"),
        (("camera", "principal_point"), [900, 287.5], r"camera\.principal_point: .* outside"),
        (("camera", "aspect"), True, r"camera\.aspect: expected a number, got True"),
    ],
)
def test_bad_values_are_named(raw, path, value, message):
    with pytest.raises(ConfigError, match=message):
        parse_cell(_bad(raw, path, value))


def test_simulation_section_is_optional(raw):
    d = copy.deepcopy(raw)
    del d["simulation"]
    assert parse_cell(d).simulation is None


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_cell(tmp_path / "missing.yaml")
    p = tmp_path / "empty.yaml"
    p.write_text("")
    with pytest.raises(ConfigError, match="empty"):
        load_cell(p)
    p.write_text("camera: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_cell(p)
    # safe_load only: a Python object tag is refused
    p.write_text("camera: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_cell(p)
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_cell(p)


# --- hostile files --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, message",
    [
        ("a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
         "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: [*c, *c, *c, *c, *c, *c, *c, *c, *c]\n", "alias"),
        ("camera: " + "{a: " * 3000 + "1" + "}" * 3000 + "\n", "nested deeper"),
        ("camera: " + "7" * 6000 + "\n", "cannot be read"),
    ],
    ids=["alias-bomb", "deep-nesting", "huge-integer"],
)
def test_hostile_cell_files_are_refused_at_once(tmp_path, text, message):
    p = tmp_path / "cell.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=message) as e:
        load_cell(p)
    assert "cell.yaml" in str(e.value) and len(str(e.value)) < 600


def test_huge_numbers_and_wrong_types_in_a_cell_file(tmp_path, raw):
    for edit, message in [
        (lambda d: d["plate"].__setitem__("pitch", 10**400), "too large"),
        (lambda d: d["mount_guess"].__setitem__("C_H_G", [[10**400] * 4 for _ in range(4)]), "too large"),
        (lambda d: d.__setitem__("gripper", [1, 2]), "expected a mapping"),
        (lambda d: d["camera"].__setitem__("principal_point", [float("nan"), 1.0]), "finite"),
    ]:
        doc = copy.deepcopy(raw)
        edit(doc)
        p = tmp_path / "cell.yaml"
        p.write_text(yaml.safe_dump(doc))
        with pytest.raises(ConfigError, match=message):
            load_cell(p)


def test_cli_maps_a_hostile_cell_file_to_exit_3(tmp_path, capsys):
    from selfview.procedures.cli import EXIT_CONFIG, main

    p = tmp_path / "bomb.yaml"
    p.write_text("a: &a [x, x, x]\nb: [*a, *a, *a]\n")
    assert main(["render", "--cell", str(p), "--out", str(tmp_path / "x.png")]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "bomb.yaml" in err and "alias" in err and "Traceback" not in err


@pytest.mark.parametrize("line, value", [("focal_guess: 950.0", "focal_guess: 1.8446744073709552e+19"),
                                         ("aspect: 1.0", "aspect: 40.0"), ("pitch: 9.0", "pitch: 1.0e+30"),
                                         # a transform's translation (its rotation is bounded by being one)
                                         ("- [-1.0,  0.0,     0.0,     0.0]", "- [-1.0,  0.0,     0.0,  1.0e+30]")])
def test_numbers_no_cell_has_are_refused(tmp_path, cell_path, line, value):
    """A number that parses but is no plausible cell value (the fault campaign's huge_number) is refused."""
    from selfview.files.cell import load_cell
    from selfview.errors import ConfigError

    text = cell_path.read_text()
    assert line in text
    p = tmp_path / "cell.yaml"
    p.write_text(text.replace(line, value, 1))
    with pytest.raises(ConfigError, match="plausible|expected a number"):
        load_cell(p)
