"""occtrain.run.control: the run directory's lock and stop signals turned into a clean stop."""

from __future__ import annotations

import os
import signal

import pytest

from occtrain.run.control import LOCK_FILE, Interrupted, RunLocked, run_lock, stop_on_signals


def test_a_second_holder_is_refused_naming_the_first_and_the_lock_frees_on_exit(tmp_path):
    with run_lock(tmp_path / "run"):
        assert (tmp_path / "run" / LOCK_FILE).read_text().startswith(f"pid {os.getpid()} on ")
        with pytest.raises(RunLocked, match=rf"run is in use by pid {os.getpid()} on .*choose another --run-dir"):
            with run_lock(tmp_path / "run"):
                pass
    with run_lock(tmp_path / "run"):  # released when the block ended
        pass


def test_a_stale_lock_file_from_a_killed_run_does_not_block(tmp_path):
    (tmp_path / LOCK_FILE).write_text("pid 1 on elsewhere\n")  # the file stays after kill -9, the flock does not
    with run_lock(tmp_path):
        assert (tmp_path / LOCK_FILE).read_text().startswith(f"pid {os.getpid()} ")


@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_stop_signal_raises_interrupted_once_and_the_handlers_come_back(signum, code):
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    with pytest.raises(Interrupted) as stop:
        with stop_on_signals():
            os.kill(os.getpid(), signum)  # Python runs the handler as os.kill returns
            pytest.fail("the signal did not interrupt the block")
    assert stop.value.exit_code == code and signal.Signals(signum).name in str(stop.value)
    assert {s: signal.getsignal(s) for s in before} == before


def test_a_second_signal_while_stopping_is_ignored():
    with pytest.raises(Interrupted):
        with stop_on_signals():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
            finally:  # recording where the run stopped: a second Ctrl-C must not cut it short
                assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
                os.kill(os.getpid(), signal.SIGINT)
