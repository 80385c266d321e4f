"""Property-based: whatever a scan description or a command-line number holds, a command either
works or stops with one clean message (exit 1 or 2), never a traceback, and never reads outside
the scan folder."""
import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from clgs.cli import main

ODD = st.one_of(
    st.integers(-5, 70), st.floats(allow_nan=True, allow_infinity=True, width=32), st.text(max_size=5),
    st.none(), st.booleans(), st.lists(st.integers(-2, 40), max_size=4),
    st.lists(st.one_of(st.floats(-1e3, 1e3, width=32), st.just(float("nan")), st.just(float("inf"))), max_size=4),
)
def NUMBER(lo, hi):
    return st.one_of(st.floats(lo, hi), st.just(float("nan")), st.just(float("inf")))


GOOD = {"mode": "cone", "DSD": 1500.0, "DSO": 1000.0, "nDetector": [16, 16], "dDetector": [4.0, 4.0],
        "nVoxel": [8, 8, 8], "dVoxel": [4.0, 4.0, 4.0], "offOrigin": [0.0, 0.0, 0.0], "offDetector": [0.0, 0.0],
        "angles": [0.0, 0.8, 1.6]}


def _clean(res):
    """Exit 0, 1 or 2 and no traceback: a message a user can act on."""
    assert res.exit_code in (0, 1, 2), (res.exit_code, res.output[-2000:])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output


def _scan_folder(root, geometry, files=None):
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "projections.npy", np.ones((3, 16, 16), np.float32))
    doc = {"format": "clgs-scan", "version": 1, "geometry": geometry,
           "files": files or {"projections": "projections.npy"}}
    (root / "scan.json").write_text(json.dumps(doc, allow_nan=True))
    return root


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(sorted(GOOD)), value=ODD)
def test_any_geometry_field_value_gives_a_clean_result(tmp_path_factory, key, value):
    root = tmp_path_factory.mktemp("scan")
    _scan_folder(root / "s", {**GOOD, key: value})
    res = CliRunner().invoke(main, ["reconstruct", str(root / "s"), "--method", "fdk", "--out", str(root / "o.nii.gz")])
    _clean(res)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(views=st.integers(-3, 40), detector=st.integers(-3, 80), arc=NUMBER(-10, 400), spacing=NUMBER(-1, 20),
       I0=NUMBER(-5, 1e7), sigma=NUMBER(-5, 100))
def test_any_simulate_numbers_give_a_clean_result(tmp_path_factory, views, detector, arc, spacing, I0, sigma):
    root = tmp_path_factory.mktemp("sim")
    np.save(root / "v.npy", np.full((6, 6, 6), 0.02, np.float32))
    res = CliRunner().invoke(main, ["simulate", str(root / "v.npy"), "--out", str(root / "s"), "--views", str(views),
                                    "--detector", str(detector), "--arc", str(arc), "--spacing", str(spacing),
                                    "--I0", str(I0), "--sigma", str(sigma)])
    _clean(res)


@pytest.mark.parametrize("name", ["../outside.npy", "/etc/passwd", "sub/../../outside.npy", "link.npy"])
def test_a_scan_may_name_only_files_inside_its_folder(tmp_path, name):
    """A scan folder is data from elsewhere: a projections file outside it (parent paths, absolute
    paths, a link pointing out) is refused before anything is read."""
    outside = tmp_path / "outside.npy"
    np.save(outside, np.ones((3, 16, 16), np.float32))
    scan = _scan_folder(tmp_path / "scan", GOOD, {"projections": name})
    (scan / "sub").mkdir()
    (scan / "link.npy").symlink_to(outside)
    res = CliRunner().invoke(main, ["reconstruct", str(scan), "--method", "fdk", "--out", str(tmp_path / "o.nii.gz")])
    _clean(res)
    assert res.exit_code != 0 and "outside the scan folder" in res.output, res.output


def test_an_r2gaussian_folder_may_name_only_files_inside_it(tmp_path):
    from clgs.geometry import Geometry
    from clgs.io.r2gaussian import to_r2gaussian_folder
    from clgs.io.scan import Scan, ScanError

    geo = Geometry.from_dict(GOOD)
    folder = to_r2gaussian_folder(Scan(geo, np.ones((3, 16, 16), np.float32)), tmp_path / "r2")
    meta = json.loads((folder / "meta_data.json").read_text())
    np.save(tmp_path / "elsewhere.npy", np.ones((16, 16), np.float32))
    meta["proj_train"][0]["file_path"] = "../elsewhere.npy"
    (folder / "meta_data.json").write_text(json.dumps(meta))
    with pytest.raises(ScanError, match="outside the scan folder"):
        Scan.load(folder)


def test_a_pickled_array_is_refused_without_unsafe_advice(tmp_path):
    scan = _scan_folder(tmp_path / "scan", GOOD)
    np.save(scan / "projections.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    res = CliRunner().invoke(main, ["reconstruct", str(scan), "--method", "fdk", "--out", str(tmp_path / "o.nii.gz")])
    _clean(res)
    assert res.exit_code == 1 and "never loads" in res.output and "allow_pickle" not in res.output
