"""Phase lines, the one switch that silences progress, and the listeners' events."""
import io

import pytest

from clgs import progress
from clgs.progress import enabled, format_seconds, listen, note, phase, phased, progress_bar, set_quiet


class _Terminal(io.StringIO):
    def isatty(self):
        return True


class _Clock:
    """A clock that moves only when told (no test depends on wall time)."""

    def __init__(self, t=100.0):
        self.t = t

    def __call__(self):
        return self.t


@pytest.fixture(autouse=True)
def _not_quiet():
    set_quiet(False)
    yield
    set_quiet(False)


def test_a_phase_in_a_log_is_a_start_line_and_an_end_line_with_its_time():
    out, clock = io.StringIO(), _Clock()
    with phase("loading the shape model", stream=out, clock=clock):
        clock.t += 2.34
    assert out.getvalue().splitlines() == ["loading the shape model ...", "loading the shape model: 2.3 s"]


def test_a_phase_on_a_terminal_is_one_line_completed_by_its_time():
    term, clock = _Terminal(), _Clock()
    with phase("FDK", stream=term, clock=clock):
        clock.t += 75
    assert term.getvalue() == "FDK ... 1 min 15 s\n"


def test_a_line_written_during_a_phase_ends_its_open_line_first():
    term = _Terminal()
    with phase("searching the size", stream=term, clock=_Clock()):
        note("something else", stream=term)
    assert term.getvalue().splitlines() == ["searching the size ...", "something else",
                                                "searching the size: 0.000 s"]


def test_inner_phases_and_phases_under_a_bar_stay_off_the_screen_but_reach_listeners():
    out = io.StringIO()
    with listen() as events:
        with phase("outer", stream=out, clock=_Clock()), phase("inner", stream=out, clock=_Clock()):
            pass
        bar = progress_bar(total=2, desc="subjects", file=out)
        with phase("under the bar", stream=out, clock=_Clock()):
            bar.update(2)
        bar.close()
    text = out.getvalue()
    assert "outer ..." in text and "inner" not in text and "under the bar" not in text
    assert [(e["desc"], e["state"]) for e in events if e["event"] == "phase"] == [
        ("outer", "start"), ("inner", "start"), ("inner", "end"), ("outer", "end"),
        ("under the bar", "start"), ("under the bar", "end")]


@pytest.mark.parametrize("switch", ["quiet", "enabled"])
def test_one_switch_silences_bars_phases_and_notes(switch, capsys):
    out = io.StringIO()
    with listen() as events:
        if switch == "quiet":
            set_quiet(True)
            ctx = enabled(True)  # an inner True never turns it back on
        else:
            ctx = enabled(False)
        with ctx:
            assert not progress.progress_enabled()
            with phase("a phase", stream=out):
                pass
            note("a note", stream=out)
            bar = progress_bar(total=3, desc="a bar", file=out)
            bar.update(3)
            bar.close()
    assert out.getvalue() == "" and capsys.readouterr().err == ""
    assert [e["event"] for e in events] == ["phase", "phase", "note"]  # listeners still hear
    set_quiet(False)
    assert progress.progress_enabled()


def test_phased_keeps_the_function_and_its_doc():
    @phased("drawing")
    def draw(x):
        """Doc."""
        return x + 1

    with listen() as events:
        assert draw(1) == 2
    assert draw.__doc__ == "Doc." and events[0]["desc"] == "drawing"


@pytest.mark.parametrize("seconds, text", [(0.0764, "0.076 s"), (1.6e-5, "0.000 s"), (0.384, "0.38 s"),
                                           (2.44, "2.4 s"), (42, "42 s"), (185, "3 min 5 s"),
                                           (9660, "2 h 41 min"), (7200, "2 h")])
def test_format_seconds(seconds, text):
    assert format_seconds(seconds) == text
