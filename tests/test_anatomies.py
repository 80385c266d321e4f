"""The built-in anatomy plugins (femur, patella): real LLP26 surfaces -> subjects, template, model."""
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

clgs_femur = pytest.importorskip("clgs_femur", reason="install with: pip install -e anatomies/femur")
clgs_patella = pytest.importorskip("clgs_patella", reason="install with: pip install -e anatomies/patella")

from clgs.anatomy import phantom as ph  # noqa: E402
from clgs.anatomy.alignment import align_rigid  # noqa: E402
from clgs.mesh import voxels as mv  # noqa: E402

HELD_OUT = [f"{i:02d}" for i in range(20, 26)]
MODEL_IDS = [f"{i:02d}" for i in range(20)]


@pytest.fixture(scope="module")
def femur():
    return clgs_femur.population_model()


@pytest.fixture(scope="module")
def patella():
    return clgs_patella.population_model()


# --------------------------------------------------------------------------------------- plugins
def test_entry_points_register_both_anatomies():
    from importlib.metadata import entry_points

    eps = {e.name: e.value for e in entry_points(group="clgs.anatomies")}
    assert eps.get("femur") == "clgs_femur" and eps.get("patella") == "clgs_patella"
    from clgs.anatomy import Anatomy

    for mod, name in ((clgs_femur, "femur"), (clgs_patella, "patella")):
        (anatomy,) = mod.clgs_anatomies()
        assert isinstance(anatomy, Anatomy) and anatomy.name == name
        assert anatomy.population() == MODEL_IDS and anatomy.test_subjects() == HELD_OUT
        assert callable(anatomy.subject_from_mesh) and anatomy.model_path.endswith(".npz")


def test_plugin_manager_finds_them():
    plugins = pytest.importorskip("clgs.anatomy.plugins")
    names = plugins.anatomy_names()
    assert "femur" in names and "patella" in names


def test_data_ships_with_its_licence(femur, patella):
    for pop, n_files in ((femur, 27), (patella, 26)):
        files = os.listdir(pop.data_dir)
        assert sum(f.endswith(".npz") for f in files) == n_files
        licence = Path(pop.data_dir, "LICENSE-MPL-2.0.txt").read_text()
        assert licence.startswith("Mozilla Public License Version 2.0") and "Exhibit B" in licence
        notice = Path(pop.data_dir, "LLP26_README.md").read_text()
        assert "musculoskeletal-models" in notice and "MPL-2.0" in notice


# --------------------------------------------------------------------------------------- held out
def test_held_out_subjects_are_disjoint_from_the_population(femur, patella):
    for pop in (femur, patella):
        assert pop.population() == MODEL_IDS
        assert pop.test_subjects() == HELD_OUT
        assert not set(pop.population()) & set(pop.test_subjects())
        assert sorted(pop.population() + pop.test_subjects()) == pop.ids


def test_held_out_subjects_never_reach_the_model_builder(patella, monkeypatch, tmp_path):
    from clgs.shape import builder as model_builder

    seen = {}

    def fake_build(template, subjects, out_path, **kw):
        seen["ids"] = list(subjects)
        seen["template"] = template
        np.savez(out_path, ok=np.ones(1))
        return out_path

    monkeypatch.setattr(model_builder, "build_model", fake_build)
    patella.build_model(out_path=tmp_path / "m.npz", force=True)
    assert seen["ids"] == MODEL_IDS
    with pytest.raises(ValueError, match="held-out"):
        patella.build_model(out_path=tmp_path / "n.npz", subjects=["00", "01", "21"], force=True)
    assert not (tmp_path / "n.npz").exists()


def test_template_is_the_mean_of_the_model_subjects_only(femur):
    v, f = femur.template_mesh()
    meshes = [femur.mesh(s)[0] for s in MODEL_IDS]
    assert np.allclose(v, np.mean(meshes, axis=0))
    # the shipped mean surface averages all 26 (held-out included): it must differ from ours
    with np.load(os.path.join(femur.data_dir, "femur_left_LLP26_mean.npz"), allow_pickle=False) as z:
        shipped = z["vertices"] - femur.frame_offset
    all26 = np.mean([femur.mesh(s)[0] for s in femur.ids], axis=0)
    from scipy.spatial import cKDTree

    assert cKDTree(all26).query(shipped)[0].max() < 1e-3
    assert cKDTree(v).query(shipped)[0].max() > 0.5


# --------------------------------------------------------------------------------------- volumes
@pytest.mark.parametrize("which,sid", [("femur", "00"), ("femur", "23"), ("patella", "07"), ("patella", "25")])
def test_mesh_to_label_keeps_the_volume_at_the_default_grid(which, sid, femur, patella):
    pop = {"femur": femur, "patella": patella}[which]
    v, f = pop.mesh(sid)
    label = mv.mesh_to_label(v, f, pop.grid)
    voxel = float(np.prod(pop.grid.spacing))
    truth = trimesh.Trimesh(v, f, process=False).volume
    assert label.sum() * voxel == pytest.approx(truth, rel=0.02)


def test_subject_ct_is_plausible_and_deterministic(patella):
    a = patella.load_subject("21")
    b = patella.load_subject("21")
    assert a.meta["held_out"] and a.volume.shape == tuple(patella.grid.shape)
    assert np.array_equal(a.volume, b.volume)
    other = patella.load_subject("03")
    assert not np.array_equal(other.volume, a.volume)
    p = patella.params
    assert a.volume.min() >= 0 and a.volume.max() <= p.cortical_range[1] + 1e-6
    label = mv.mesh_to_label(a.vertices, a.faces, patella.grid)
    inside = a.volume[label]
    assert p.trabecular_range[0] * 0.8 < np.median(inside) < p.cortical_range[1]
    # the subject's grid is the CT grid, centred on the rotation axis
    assert np.allclose(np.asarray(a.origin) + 0.5 * (np.asarray(a.volume.shape) - 1) * np.asarray(a.spacing), 0)


def test_femur_subject_has_cortex_canal_and_thigh(femur):
    ph_ = femur.phantom("05")
    t = ph_.tissue
    counts = np.bincount(t.ravel(), minlength=7)
    assert all(counts[c] > 0 for c in range(7))
    bone = counts[ph.MARROW] + counts[ph.TRABECULAR] + counts[ph.CORTICAL]
    assert 0.15 < counts[ph.CORTICAL] / bone < 0.6
    # air on every side of the limb in x and y
    for sl in (t[:, 0], t[:, -1], t[:, :, 0], t[:, :, -1]):
        assert np.all(sl == ph.AIR)


# --------------------------------------------------------------------------------------- user meshes
def test_right_femur_from_a_file_is_mirrored_and_aligned(femur, tmp_path):
    """A 'right femur' in a scanner frame: mirror of a held-out left femur, rotated and moved."""
    v, f = femur.mesh("22")
    ang = np.deg2rad(25.0)
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1.0]])
    right = (v * np.array([-1.0, 1.0, 1.0])) @ R.T + np.array([300.0, -50.0, 20.0])
    trimesh.Trimesh(right, f[:, ::-1], process=False).export(tmp_path / "right_femur.stl")
    messages = []
    subject, al = femur.subject_from_mesh(tmp_path / "right_femur.stl", seed=1, echo=messages.append)
    assert al.mirrored
    assert "mirrored" in messages[0] and "RMS" in messages[0]
    assert subject.volume.shape == tuple(femur.grid.shape)
    # the fit is as good as fitting the left femur in its own frame (RMS = shape difference to the
    # template, a few mm), and it lands where femur 22 sits, up to that difference
    direct = align_rigid(v, femur.template_mesh()[0], allow_mirror=False)
    assert al.rms_mm == pytest.approx(direct.rms_mm, abs=0.05) and al.rms_mm < 5.0
    from scipy.spatial import cKDTree  # (an STL file does not keep the vertex order)

    assert cKDTree(v).query(subject.vertices)[0].max() < 3.0
    assert trimesh.Trimesh(subject.vertices, subject.faces, process=False).volume > 0


# --------------------------------------------------------------------------------------- model + scan
def test_patella_builds_a_small_model_and_simulates_a_scan(patella, tmp_path, monkeypatch):
    """The generic path end to end on the small anatomy: builder -> model file -> loaders; and a
    held-out subject through the CT projector."""
    pytest.importorskip("torch")
    from clgs.shape.model import read_metadata

    monkeypatch.setenv("CLGS_CACHE_DIR", str(tmp_path))
    ids = MODEL_IDS[:4]
    path = patella.build_model(out_path=tmp_path / "patella-small.npz", subjects=ids, max_cells=16,
                               progress=False, registration=dict(levels=(8, 0), iterations=(25, 15)))
    meta = read_metadata(path)
    assert meta["population"] == ids and meta["anatomy"] == "patella"
    assert not set(meta["population"]) & set(HELD_OUT)
    assert 1 <= meta["n_modes"] <= 3 and 0.9 <= meta["variance_kept"] <= 1.0
    for r in meta["residuals"].values():
        assert r["surface_mean_mm"] < 2.5 and r["dice"] > 0.85 and r["min_jacobian"] > 0
    from clgs.shape.model import load_model

    sm, atlas = load_model(path)
    assert atlas.mean.shape == tuple(patella.grid.shape)
    # the atlas mean is a CT: bone values inside the template, soft tissue around
    tmpl = patella.load_template()
    assert atlas.mean[tmpl.sdf < -2].mean() > atlas.mean[(tmpl.sdf > 4) & (tmpl.sdf < 10)].mean() + 0.003

    projector = pytest.importorskip("clgs.ops.ct_projector")
    subject = patella.load_subject("24")
    geo = patella.geometry(n_views=4)
    proj = np.asarray(projector.CTProjector(geo).forward(subject.volume))
    assert proj.shape == (4, *geo.nDetector) and np.all(np.isfinite(proj))
    # a knee-sized limb: the longest chord is about 120-150 mm of ~0.02/mm tissue plus the patella
    assert 1.8 < proj.max() < 4.5
    # the detector border sees only air (the whole volume is in the field of view)
    assert proj[:, :, 0].max() == 0 and proj[:, :, -1].max() == 0


def test_model_path_follows_the_cache_dir(patella, monkeypatch, tmp_path):
    monkeypatch.setenv("CLGS_CACHE_DIR", str(tmp_path))
    assert patella.model_path.startswith(str(tmp_path) + os.sep + "models" + os.sep + "patella-")
    h = patella.settings_hash()
    assert h == patella.settings_hash() and len(h) == 12


def _femur_population():
    from clgs.anatomy import plugins

    try:
        return plugins.get_anatomy("femur")
    except Exception:  # noqa: BLE001
        pytest.skip("the femur plugin is not installed (pip install -e anatomies/femur)")


def test_a_surface_in_the_wrong_units_is_refused_with_the_fix(tmp_path):
    import trimesh

    from clgs.io.mesh import save_mesh

    femur = _femur_population()
    subject = femur.load_subject(femur.test_subjects()[0])
    save_mesh(tmp_path / "metres.stl", np.asarray(subject.vertices) / 1000.0, subject.faces)
    with pytest.raises(ValueError, match="looks like metres: scale it by 1000"):
        femur.subject_from_mesh(tmp_path / "metres.stl", echo=None)
    box = trimesh.creation.box((80.0, 80.0, 400.0))
    save_mesh(tmp_path / "box.stl", box.vertices, box.faces)
    with pytest.warns(UserWarning, match="fits the femur template poorly"):
        femur.subject_from_mesh(tmp_path / "box.stl", echo=None)


def test_the_shape_method_warns_when_the_scan_or_the_fit_is_implausible():
    import warnings

    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.methods.shape_guided import warn_if_implausible, warn_if_the_scan_cannot_hold

    class Template:
        def bounds(self):
            return np.zeros(3), np.array([60.0, 60.0, 480.0])

    small = Scan(Geometry.default(n_views=2, n_voxel=8, n_detector=16, volume_mm=64.0), np.zeros((2, 16, 16)))
    with pytest.warns(UserWarning, match="64 mm across.*480 mm"):
        warn_if_the_scan_cannot_hold(small, Template())
    with pytest.warns(UserWarning, match="3.2 standard deviations.*0.7 dB"):
        warn_if_implausible(np.array([-3.2, 0.5, 0.1]), 0.7)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_implausible(np.array([1.2, -0.4, 0.0]), 45.0)  # a femur that fits: silent
        big = Scan(Geometry.default(n_views=2, n_voxel=8, n_detector=16, volume_mm=500.0), np.zeros((2, 16, 16)))
        warn_if_the_scan_cannot_hold(big, Template())
