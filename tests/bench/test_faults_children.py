"""The fault campaign's children start with a terminal's signal dispositions, whatever the campaign inherited."""

from __future__ import annotations

import signal
import sys

from selfview.bench.faults.common import _run_child

_SHOW = "import signal, sys; sys.stderr.write(' '.join(str(signal.getsignal(s)) for s in (signal.SIGQUIT, signal.SIGHUP)))"


def test_a_campaign_run_as_a_background_job_or_under_nohup_still_sends_its_signals_to_listening_children(tmp_path):
    # a background job ignores SIGQUIT, nohup ignores SIGHUP: the children (operators' commands at a terminal)
    # must not inherit that, or every signal case would measure an ignored signal
    before = {s: signal.getsignal(s) for s in (signal.SIGQUIT, signal.SIGHUP)}
    try:
        for s in before:
            signal.signal(s, signal.SIG_IGN)
        code, err = _run_child([sys.executable, "-c", _SHOW], tmp_path, 30.0)
    finally:
        for s, h in before.items():
            signal.signal(s, h)
    assert code == 0 and err.split() == [str(int(signal.SIG_DFL))] * 2, err  # not ignored (SIG_IGN is 1)
