"""The command line prints clgs's warnings as ``Category: text``, without a source line that
means nothing to the user (it was ``<string>:8:`` for warnings raised in generated code)."""
import warnings

import pytest


@pytest.fixture
def plain(monkeypatch):
    from clgs.cli import _plain_warnings

    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # restored afterwards
    _plain_warnings()
    return warnings.formatwarning


def test_clgs_warnings_print_without_a_source_line(plain):
    import clgs.methods.shape_guided as sg
    from clgs.io.validate import ScanWarning

    assert plain("3 negative values", ScanWarning, "<string>", 8) == "ScanWarning: 3 negative values\n"
    assert plain("too small", UserWarning, sg.__file__, 480) == "UserWarning: too small\n"


def test_other_packages_warnings_keep_their_source(plain):
    out = plain("deprecated", DeprecationWarning, "/usr/lib/python3/dist-packages/x.py", 12, line="")
    assert out.startswith("/usr/lib/python3/dist-packages/x.py:12: DeprecationWarning: deprecated")
