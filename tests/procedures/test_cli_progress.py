"""Progress of the long commands: one line per view with the time left, the camera's measuring said apart."""

import re

from selfview.procedures.cli import main


def test_intrinsics_prints_one_line_per_view_with_the_time_left(capsys):
    assert main(["intrinsics", "--views", "6", "--json"]) == 0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "of 6: at its pose" in ln]
    assert [int(re.search(r"view (\d+) of 6", ln).group(1)) for ln in lines] == [1, 2, 3, 4, 5, 6]
    left = [float(re.search(r"views left ~(\d+) s", ln).group(1)) for ln in lines]
    assert left[-1] == 0 and all(0 <= v < 300 for v in left)
    assert "measuring the camera from 6 views" in err
    assert err.index("view 6 of 6") < err.index("measuring the camera")
