"""Issue 32: no proper prefix of a line the VAL-II driver sends to move the arm, set its speed or define a
location is itself a valid line, so a line end that noise puts inside a typed line makes a syntax error,
never a shorter motion. The parser is the one the simulated controller reads its input with."""

from __future__ import annotations

import itertools

import pytest

from selfview.drivers.puma_val_serial.dialect import DEFAULT_COMMANDS, PREFIX_SAFE_KINDS, ValDialect

VAL = ValDialect()
NAMES = ("p", "p1", "above", "plate", "svtgt", "a" * 15, "Q7_x")
NUMBERS = (0.0, 5.0, 50.0, 100.0, 12.5, -10.5, 0.001, -0.125, 1234.567, -999.999)
#: the templates before issue 32: bare numbers and names
BARE = {"speed": "SPEED {pct}", "define": "DO SET {name} = TRANS({x}, {y}, {z}, {o}, {a}, {t})", "move": "DO MOVE {name}",
        "moves": "DO MOVES {name}", "appro": "DO APPRO {name}, {d}", "depart": "DO DEPART {d}",
        "drive": "DO DRIVE {joint}, {deg}, {speed}"}


def lines_of(kind: str):
    """Field values of ``kind`` covering every name and number shape the driver writes."""
    if kind == "speed":
        return [{"pct": v} for v in (1, 5, 10, 12.5, 20, 45.25, 100)]
    if kind in ("move", "moves"):
        return [{"name": n} for n in NAMES]
    if kind == "appro":
        return [{"name": n, "d": v} for n, v in itertools.product(NAMES, NUMBERS)]
    if kind == "depart":
        return [{"d": v} for v in NUMBERS]
    if kind == "drive":
        return [{"joint": j, "deg": v, "speed": s} for j in range(1, 7) for v in NUMBERS for s in (1, 20, 50, 100)]
    if kind == "define":
        return [{"name": n, **dict(zip("xyzoat", (v, -v, 100.0, 0.0, 90.0, v)))} for n in NAMES for v in NUMBERS]
    assert kind == "ready"
    return [{}]


@pytest.mark.parametrize("kind", PREFIX_SAFE_KINDS)
def test_no_proper_prefix_of_a_motion_speed_or_location_line_is_a_valid_line(kind):
    n = 0
    for values in lines_of(kind):
        line = VAL.command(kind, **values)
        parsed = VAL.parse_command(line)  # the whole line is read back as sent
        assert parsed is not None and parsed[0] == kind, line
        for k, v in values.items():
            assert parsed[1][k] == (v if k == "name" else pytest.approx(v, abs=1e-3)), (line, k)
        assert VAL.valid_prefixes(kind, **values) == [], line
        n += len(line) - 1
    assert n >= len(lines_of(kind)) * 7  # every prefix was tried


def test_the_bare_templates_leave_shorter_motions_open():
    """What the check above catches: with bare numbers and names, cut lines are other motions."""
    bare = ValDialect.from_dict({"commands": BARE})
    assert bare.valid_prefixes("appro", name="plate", d=50) == ["DO APPRO plate, 5"]
    assert bare.valid_prefixes("depart", d=60) == ["DO DEPART 6"]
    assert bare.valid_prefixes("move", name="p1") == ["DO MOVE p"]
    assert bare.valid_prefixes("drive", joint=2, deg=-10.5, speed=20) == ["DO DRIVE 2, -10.5, 2"]
    assert bare.valid_prefixes("speed", pct=20) == ["SPEED 2"]


@pytest.mark.parametrize("line", [
    "DO APPRO plate, (5", "DO APPRO plate, ((50)", "DO APPRO plate, (50))", "DO MOVE (above", "DO MOVE above)",
    "DO DEPART (", "DO DEPART ()", "DO DRIVE 2, (-10.5), (2", "SPEED (2", "SPEED", "DO SET p1 = (TRANS(1, 2, 3, 4, 5, 6)",
    "DO SET p1 = (TRANS(1, 2, 3, 4, 5, 6)))", "DO MOVEabove", "DO APPRO plate", "DO DRIVE 2, (-10.5)", "DO", "DO READ",
])
def test_unbalanced_or_short_lines_are_refused(line):
    assert VAL.parse_command(line) is None


@pytest.mark.parametrize("line, kind, fields", [
    ("DO APPRO plate, 50", "appro", {"name": "plate", "d": 50.0}),  # a controller reads the bare form too
    ("do appro PLATE,((-5.5))", "appro", {"name": "PLATE", "d": -5.5}),
    ("DO MOVE above", "move", {"name": "above"}),
    ("DO MOVE(( above ))", "move", {"name": "above"}),
    ("SPEED ( 20 )", "speed", {"pct": 20.0}),
    ("DO SET p1 = TRANS((1), 2, 3, 4, 5, (-6))", "define", dict(name="p1", x=1.0, y=2.0, z=3.0, o=4.0, a=5.0, t=-6.0)),
])
def test_parenthesised_values_are_read_as_a_controller_reads_expressions(line, kind, fields):
    assert VAL.parse_command(line) == (kind, fields)


def test_every_default_template_is_checked():
    assert set(PREFIX_SAFE_KINDS) <= set(DEFAULT_COMMANDS)
    assert set(DEFAULT_COMMANDS) - set(PREFIX_SAFE_KINDS) == {"where", "calibrate", "here", "point", "abort", "status"}


def test_a_lab_dialect_with_bare_templates_is_loaded_with_a_warning_naming_its_open_lines(tmp_path, caplog):
    from selfview.drivers.puma_val_serial import load_dialect

    f = tmp_path / "dialect.yaml"
    f.write_text("commands: {appro: 'DO APPRO {name}, {d}', speed: 'SP {pct}'}\n")
    with caplog.at_level("WARNING", logger="selfview.drivers.puma_val_serial.dialect"):
        d = load_dialect(f)
    assert d.commands["appro"] == "DO APPRO {name}, {d}"  # allowed: a controller may not read parentheses
    assert d.open_prefixes() == {"speed": ["SP 2"], "appro": ["DO APPRO p1, 5"]}
    assert "dialect.yaml" in caplog.text and "'DO APPRO p1, 5'" in caplog.text and "'SP 2'" in caplog.text
    caplog.clear()
    f.write_text("echo: true\n")
    with caplog.at_level("WARNING", logger="selfview.drivers.puma_val_serial.dialect"):
        assert load_dialect(f).open_prefixes() == {}
    assert caplog.text == ""
