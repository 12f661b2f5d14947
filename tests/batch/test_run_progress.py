"""The batch run's progress (``batch.run.Progress``): a tqdm bar on a terminal, one plain line per frame in
logs and with --quiet (no carriage returns), and the summary at the end."""

from __future__ import annotations

import io
import sys

import pytest

from batch.run import Progress
from batch_helpers import TINY, batch, write_set


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _record(status: str = "ok", n: int = 0) -> dict:
    record = {"status": status, "job_id": f"job{n}", "scene": "corner", "view": {"label": "suggested0"},
              "preset": "kinect_v2", "render_seconds": 1.5, "spp": 2, "rms_depth_error_m": 0.0123}
    if status != "ok":
        record["error"] = "RuntimeError: boom"
    return record


def _feed(progress: Progress) -> str:
    progress.draw()                                  # a heartbeat before the first frame
    for n, status in enumerate(("ok", "failed", "ok")):
        progress.record(_record(status, n))
    progress.close()
    return progress.stream.getvalue()


def test_a_log_gets_one_plain_line_per_frame():
    text = _feed(Progress(3, stream=io.StringIO()))
    assert "\r" not in text and "\033" not in text
    assert text.splitlines() == [
        "[1/3] ok      job0 corner/suggested0/kinect_v2 (1.5 s, 2 spp, RMS error 12.3 mm)",
        "[2/3] FAILED  job1 corner/suggested0/kinect_v2: RuntimeError: boom",
        "[3/3] ok      job2 corner/suggested0/kinect_v2 (1.5 s, 2 spp, RMS error 12.3 mm)"]


def test_quiet_on_a_terminal_logs_plain_lines_without_a_bar():
    text = _feed(Progress(3, quiet=True, stream=_Terminal()))
    assert "\r" not in text and len(text.splitlines()) == 3


def test_a_terminal_gets_a_tqdm_bar_with_failures_above_it():
    pytest.importorskip("tqdm")
    text = _feed(Progress(3, stream=_Terminal()))
    assert "\r" in text and "3/3 frames" in text and "1 failed" in text and "frames/min" in text
    assert "FAILED job1 corner/suggested0/kinect_v2: RuntimeError: boom\n" in text
    assert text.endswith("\n")


def test_a_terminal_without_tqdm_gets_plain_lines(monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)
    text = _feed(Progress(3, stream=_Terminal()))
    assert "\r" not in text and len(text.splitlines()) == 3


def test_nothing_to_render_draws_no_bar():
    terminal = _Terminal()
    Progress(0, stream=terminal).close()
    assert terminal.getvalue() == ""


def test_run_logs_plain_lines_and_the_summary_when_stderr_is_not_a_terminal(tmp_path):
    set_file = write_set(tmp_path, 'seed = 1\npresets = ["kinect_v2"]\n' + TINY
                         + '[output]\nformats = ["png", "json"]\n[[scenes]]\ndemo = "corner"\n'
                           '[[scenes.poses]]\nsuggested = true\n')
    proc = batch("run", str(set_file), "--out", str(tmp_path / "dataset"), "--workers", "1")
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and "\033" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert lines[0].startswith("1 frames in the set: 0 done; rendering 1 (1 view) with the local pool")
    assert lines[1].startswith("[1/1] ok      ") and "corner/pose0/kinect_v2 (" in lines[1]
    assert lines[2].startswith("1 frames: 1 ok (1 rendered now in ")
    assert lines[-1] == f"dataset: {tmp_path / 'dataset'} (index.jsonl, README.md, frames/)"
