"""Any femur a user brings: 350-550 mm, left or right, any frame, units checked, shapes unlike a
femur warned; the CT grid and the detector follow the subject. Synthetic variants of LLP26's
held-out subject 22 (scaled, mirrored, rotated, in metres)."""
import warnings

import numpy as np
import pytest

clgs_femur = pytest.importorskip("clgs_femur", reason="install with: pip install -e anatomies/femur")

from clgs.io.mesh import save_mesh  # noqa: E402


@pytest.fixture(scope="module")
def femur():
    return clgs_femur.population_model()


@pytest.fixture(scope="module")
def subject22(femur):
    from clgs.anatomy.population import surface_length

    v, f = femur.mesh("22")
    return v, f, surface_length(v)


def _rotation(deg, axis):
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _on_template_lattice(femur, grid):
    off = (np.asarray(grid.origin) - np.asarray(femur.grid.origin)) / np.asarray(femur.grid.spacing)
    return np.allclose(off, np.round(off), atol=1e-6)


@pytest.mark.parametrize("length", [350.0, 550.0])
def test_a_femur_of_any_adult_length_gets_a_grid_and_detector_that_see_it_whole(femur, subject22, length, tmp_path):
    from clgs.anatomy.simulation import scan_geometry, simulate_subject

    v, f, own = subject22
    save_mesh(tmp_path / "f.stl", v * (length / own), f)
    messages = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a scaled real femur is a femur: no warning
        subject, al = femur.subject_from_mesh(tmp_path / "f.stl", seed=3, echo=messages.append)
    from clgs.anatomy.alignment import align_rigid
    from clgs.anatomy.population import surface_length

    direct = align_rigid(v, femur.template_mesh()[0], allow_mirror=False, allow_scale=True)
    assert al.scale * length == pytest.approx(direct.scale * own, rel=0.01)  # its size found, and kept:
    assert surface_length(subject.vertices) == pytest.approx(length, rel=1e-3)
    assert al.shape_rms_mm < femur.plausible_rms_mm() / 2
    assert f"length {length:.0f} mm" in messages[0] and "extrapolates" in messages[0]  # beyond 404-462 mm
    shape = np.asarray(subject.volume.shape)
    if length <= 480.0:  # fits the template's grid (480 mm along the leg): the grid is the template's
        assert tuple(shape) == tuple(femur.grid.shape)
    else:  # grown (along the leg, and across it where its limb needs room), on the template's
        # lattice, centred on the rotation axis
        assert shape[0] > femur.grid.shape[0] and np.all(shape[1:] >= femur.grid.shape[1:])
    from clgs.geometry import Grid

    grid = Grid(tuple(shape), tuple(np.asarray(subject.origin)[::-1]), tuple(np.asarray(subject.spacing)[::-1]))
    assert _on_template_lattice(femur, grid)
    lo = np.asarray(grid.origin)
    hi = lo + (np.asarray(grid.shape[::-1]) - 1) * np.asarray(grid.spacing)
    assert np.all(subject.vertices.min(0) >= lo + [40, 40, 9]) and np.all(subject.vertices.max(0) <= hi - [40, 40, 9])
    geo = scan_geometry(femur.anatomy(), subject, 2, np.pi)
    assert np.allclose(geo.offOrigin, 0.0, atol=1e-9)
    scan = simulate_subject(femur.anatomy(), subject, angles=[0.0, np.pi / 2], noise=False)
    p = np.asarray(scan.projections)
    # the detector sees the whole limb across (air in its outer columns) and the bone's both ends
    assert p[:, :, :3].max() < 1e-3 and p[:, :, -3:].max() < 1e-3
    assert p.max() > 2.0  # a thigh and a femur in the beam


def test_a_right_femur_rotated_anywhere_and_in_metres(femur, subject22, tmp_path):
    from scipy.spatial import cKDTree

    v, f, _ = subject22
    right = (v * [-1.0, 1.0, 1.0]) @ (_rotation(40, 0) @ _rotation(-70, 2)).T + [500.0, -200.0, 30.0]
    save_mesh(tmp_path / "right_m.stl", right / 1000.0, f[:, ::-1])
    with pytest.raises(ValueError, match=r"0\.45\d* units long.*looks like metres: scale it by 1000.*--units m"):
        femur.subject_from_mesh(tmp_path / "right_m.stl", echo=None)
    subject, al = femur.subject_from_mesh(tmp_path / "right_m.stl", echo=None, units="m")
    assert al.mirrored and subject.meta["mirrored"] and subject.meta["unit_factor"] == 1000.0
    assert np.asarray(subject.meta["matrix"]).shape == (4, 4)
    assert cKDTree(v).query(subject.vertices)[0].max() < 3.0  # lands where left femur 22 sits
    assert tuple(subject.volume.shape) == tuple(femur.grid.shape)


def test_inches_are_named_and_units_are_checked(femur, subject22, tmp_path):
    v, f, _ = subject22
    save_mesh(tmp_path / "in.stl", v / 25.4, f)
    with pytest.raises(ValueError, match="looks like inches: scale it by 25.4.*--units in"):
        femur.subject_from_mesh(tmp_path / "in.stl", echo=None)
    with pytest.raises(ValueError, match="units 'feet'"):
        femur.subject_from_mesh(tmp_path / "in.stl", echo=None, units="feet")


def test_a_box_of_a_femurs_size_is_warned_with_both_residuals(femur, tmp_path):
    import trimesh

    box = trimesh.creation.box((80.0, 80.0, 400.0))
    save_mesh(tmp_path / "box.stl", box.vertices, box.faces)
    worst = max(femur.population_fit()["shape_rms_mm"].values())
    assert 1.0 < worst < 8.0  # LLP26's own femurs
    with pytest.warns(UserWarning, match=rf"fits the femur template poorly: its shape is \d+\.\d mm RMS.*within "
                                         rf"{worst:.1f} mm"):
        femur.subject_from_mesh(tmp_path / "box.stl", echo=None)


def test_a_constant_truth_leaves_the_anatomy_evaluation_undefined_not_failed(femur):
    from clgs.anatomy.evaluation import evaluate_volume
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan

    geo = Geometry.default(n_views=2, n_voxel=8, n_detector=16, volume_mm=64.0)
    v, f = femur.mesh("22")
    scan = Scan(geo, np.zeros((2, 16, 16), np.float32), truth=np.full((8, 8, 8), 0.02, np.float32),
                surface=(v * 0.1, f))
    out = evaluate_volume(femur.anatomy(), scan, np.full((8, 8, 8), 0.01, np.float32))
    assert out["psnr3d"] is None and "constant" in out["metrics_undefined"]
    # the truth gives no bone level; the anatomy's atlas does, and no voxel is above it
    assert out["surface_level_source"] == "atlas" and "no bone surface" in out["surface_error"]


# --------------------------------------------------------------------------------------- command line
def test_simulate_takes_clinical_angles_and_a_c_arm_detector(tmp_path):
    from click.testing import CliRunner

    from clgs.cli import main
    from clgs.io.scan import Scan

    res = CliRunner().invoke(main, ["femur", "simulate", "--subject", "22", "--angles", "0,90", "--detector-mm", "300",
                                    "--no-noise", "--out", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    assert "2 views at 0, 90 deg" in res.output and "truncated field of view" in res.output
    scan = Scan.load(tmp_path / "s")
    assert np.allclose(scan.geometry.angles, [0.0, np.pi / 2])
    # 300 mm at the isocentre, magnified 1.5 onto 3 mm pixels: 150 x 150; the femur (480 mm grid)
    # runs off its top and bottom, the thigh stays inside across it
    assert tuple(scan.geometry.nDetector) == (150, 150)
    assert scan.meta["acquisition"]["detector_fov_mm"] == [300.0, 300.0]
    p = np.asarray(scan.projections)
    assert p[:, 0, :].max() > 1.0 and p[:, -1, :].max() > 1.0 and p[:, :, :2].max() < 1e-3
    fov = scan.geometry.field_of_view()
    assert 0.3 < fov.mean() < 0.8  # about 300 / 480 of the grid along the leg (less the cone's corners)
    res = CliRunner().invoke(main, ["femur", "simulate", "--angles", "carm5", "--no-noise", "--views", "9",
                                    "--out", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    assert np.allclose(np.degrees(Scan.load(tmp_path / "c").geometry.angles), [0, 22.5, 45, 67.5, 90])


@pytest.mark.parametrize("args, words", [
    (["--angles", "0,ninety"], ["--angles", "0,ninety", "degrees"]),
    (["--angles", "0,360"], ["--angles", "repeated"]),
    (["--detector-mm", "-3"], ["--detector-mm", "positive"]),
    (["--units", "m"], ["--units", "--mesh"]),
])
def test_simulate_refuses_bad_view_and_detector_options_before_any_work(tmp_path, args, words):
    from click.testing import CliRunner

    from clgs.cli import main

    res = CliRunner().invoke(main, ["femur", "simulate", *args, "--out", str(tmp_path / "s")])
    assert res.exit_code == 2, res.output
    for w in words:
        assert w in res.output
    assert "Traceback" not in res.output and not (tmp_path / "s").exists()


def test_experiment_meshes_folder_needs_surfaces(tmp_path):
    from click.testing import CliRunner

    from clgs.cli import main

    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "notes.txt").write_text("no surface here")
    res = CliRunner().invoke(main, ["femur", "experiment", "--meshes", str(tmp_path / "m"),
                                    "--out", str(tmp_path / "e")])
    assert res.exit_code == 2 and "holds no surface file" in res.output
    res = CliRunner().invoke(main, ["femur", "experiment", "--meshes", str(tmp_path / "m"), "--subjects", "20",
                                    "--out", str(tmp_path / "e")])
    assert res.exit_code != 0 and ("holds no surface file" in res.output or "not both" in res.output)


def test_a_reconstruction_with_a_true_surface_writes_its_distance_picture(tmp_path):
    """`clgs <anatomy> reconstruct` of a scan with a true surface: OUT/surface_distance.png, the
    bone surface coloured by distance to the truth (a ball here, FDK of 12 views)."""
    import trimesh
    from click.testing import CliRunner

    from clgs.anatomy import Anatomy
    from clgs.anatomy.surface_figure import vertex_distances
    from clgs.cli.anatomy_group import make_group
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector

    geo = Geometry.default(n_views=12, n_voxel=24, n_detector=40, volume_mm=64.0)
    pts = geo.volume_grid(scene=False).points()
    truth = np.where(np.linalg.norm(pts, axis=-1) < 18.0, 0.02, 0.0).astype(np.float32)
    proj = np.asarray(CTProjector(geo).forward(truth), np.float32)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=18.0)
    Scan(geo, proj, truth=truth, surface=(ball.vertices, ball.faces)).save(tmp_path / "scan")
    group = make_group(Anatomy(name="bare", summary="a bare anatomy"))
    res = CliRunner().invoke(group, ["reconstruct", str(tmp_path / "scan"), "--method", "fdk", "--out",
                                     str(tmp_path / "rec")])
    assert res.exit_code == 0, res.output
    png = tmp_path / "rec" / "surface_distance.png"
    assert "surface picture" in res.output and png.read_bytes()[:4] == b"\x89PNG"
    # the distances it colours: a sphere 1 mm larger lies 1 mm from the truth everywhere
    d = vertex_distances((ball.vertices * 19.0 / 18.0, ball.faces), (ball.vertices, ball.faces))
    assert np.allclose(d, 1.0, atol=0.05)


def test_surfaces_compare_on_one_limb_with_a_tissue_seed(femur, subject22, tmp_path):
    """Two names for the same femur surface: each name draws its own limb around it by default (the
    truths differ), one --tissue-seed gives both the same (equal truths, equal FDK figures); the
    records name the seed, and a folder made with one is not resumed without it."""
    import json
    import math

    from click.testing import CliRunner

    from clgs.anatomy import plugins
    from clgs.anatomy.simulation import simulate_subject
    from clgs.cli import main
    from clgs.errors import InputError
    from clgs.experiment import load_experiment_subject, run_experiment

    anatomy = plugins.get_anatomy("femur")
    v, f, _ = subject22
    for name in ("a", "b"):
        save_mesh(tmp_path / f"{name}.stl", v, f)
    meshes = {n: (str(tmp_path / f"{n}.stl"), "mm") for n in ("a", "b")}

    def truth(name, tissue_seed):
        sub = load_experiment_subject(anatomy, name, meshes, 0, tissue_seed)
        return simulate_subject(anatomy, sub, 1, math.pi, False, 0, protocol="same").truth

    assert not np.array_equal(truth("a", None), truth("b", None))  # each name its own limb
    np.testing.assert_array_equal(truth("a", 7), truth("b", 7))
    kw = dict(views=(2,), iterations=1, ablation_views=None, methods=("fdk",), progress=False, meshes=meshes,
              simulation="same", echo=lambda *_: None)
    summary = run_experiment(anatomy, tmp_path / "e", tissue_seed=7, **kw)
    rows = {p.stem: json.loads(p.read_text()) for p in (tmp_path / "e" / "runs").glob("*.json")}
    assert rows["a_2_fdk"]["tissue_seed"] == 7 and rows["a_2_fdk"]["psnr3d"] == rows["b_2_fdk"]["psnr3d"]
    assert summary["per_method"]["2/fdk"]["psnr3d"] == rows["a_2_fdk"]["psnr3d"]
    with pytest.raises(InputError, match="tissue_seed 7, this run asks for None: give the same --tissue-seed"):
        run_experiment(anatomy, tmp_path / "e", **kw)
    res = CliRunner().invoke(main, ["femur", "experiment", "--tissue-seed", "3", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--tissue-seed draws the tissue around --meshes surfaces" in res.output
