"""Progress in a log: whole lines at an interval, no carriage-return frames; a live bar on a terminal."""
import io
import time

import pytest

from clgs.fit.training_log import Progress
from clgs.progress import LogLines, log_seconds, on_terminal, progress_bar


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_log_gets_plain_lines_at_the_interval(monkeypatch):
    monkeypatch.setenv("CLGS_PROGRESS_SECONDS", "0.05")
    out = io.StringIO()
    bar = progress_bar(total=200, desc="train", unit="it", file=out)
    for _ in range(200):
        time.sleep(0.002)
        bar.update(1)
        bar.set_postfix({"psnr": "31.2"}, refresh=False)
    bar.close()
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    # 200 updates over ~0.4-1 s at one line per 0.05 s: a handful of lines, not one per update
    assert 3 <= len(lines) <= 60, lines
    assert lines[-1].startswith("train: 200/200 it (100%)") and "psnr=31.2" in lines[-1]
    assert len(set(lines)) == len(lines)  # the closing refresh is not repeated


def test_a_terminal_keeps_the_live_bar():
    term = _Terminal()
    assert on_terminal(term) and not on_terminal(io.StringIO())
    bar = progress_bar(total=3, desc="x", file=term, mininterval=0)
    for _ in range(3):
        bar.update(1)
    bar.close()
    assert "\r" in term.getvalue()


@pytest.mark.parametrize("value, want", [("2.5", 2.5), ("0", 10.0), ("-1", 10.0), ("nan", 10.0), ("x", 10.0)])
def test_interval_setting_is_checked(monkeypatch, value, want):
    monkeypatch.setenv("CLGS_PROGRESS_SECONDS", value)
    assert log_seconds() == want


def test_training_progress_in_a_log_is_lines(monkeypatch, capsys):
    monkeypatch.setenv("CLGS_PROGRESS_SECONDS", "1000")
    p = Progress(total=5000, desc="train")
    for i in range(5000):
        p.update(1, {"psnr": 30.0 + i * 1e-4})
    p.close()
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert 1 <= len(lines) <= 3 and lines[-1].startswith("train: 5000/5000 it (100%)"), lines


def test_log_lines_drops_empty_writes():
    out = io.StringIO()
    w = LogLines(out)
    w.write("\r")
    w.write("")
    w.write("\ra line\r")
    assert out.getvalue() == "a line\n"


def test_new_figures_do_not_force_extra_lines_in_a_log(monkeypatch):
    monkeypatch.setenv("CLGS_PROGRESS_SECONDS", "1000")
    out = io.StringIO()
    bar = progress_bar(range(50), desc="registering", unit="subject", file=out)
    for i in bar:
        bar.set_postfix(surface_mm=i * 0.01)  # refresh=True by default: on a terminal, a frame each
    lines = out.getvalue().splitlines()
    assert len(lines) <= 3 and lines[-1].startswith("registering: 50/50 subject (100%)"), lines
