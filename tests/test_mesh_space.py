"""Surface files without a coordinate tag: read as LPS (as 3D Slicer reads them) with a warning that
names the frame, or in the frame the caller names (``space=``, ``--mesh-space``); a tag always
wins; every surface clgs writes carries its tag (read back raw with trimesh)."""
import json
import subprocess
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from cli_helpers import run

from clgs.io.mesh import MeshError, MeshWarning, load_mesh, mesh_space, save_mesh
from clgs.io.volume import save_volume

ROOT = Path(__file__).resolve().parents[1]
CENTRE_RAS = np.array([20.0, 15.0, 5.0])  # off the origin: a mirrored reading lands 50 mm away
RADIUS = 4.0  # an 8 mm ball


def ball_volume(path):
    """A ball of 8 mm diameter at CENTRE_RAS, 1 mm voxels, NIfTI (RAS)."""
    n = 32
    org = CENTRE_RAS - (n - 1) / 2.0
    z, y, x = np.meshgrid(*[np.arange(n) + org[i] for i in (2, 1, 0)], indexing="ij")
    r = np.sqrt((x - CENTRE_RAS[0]) ** 2 + (y - CENTRE_RAS[1]) ** 2 + (z - CENTRE_RAS[2]) ** 2)
    vol = np.clip(RADIUS + 0.5 - r, 0.0, 1.0).astype(np.float32) * 0.05
    save_volume(path, vol, spacing=(1.0, 1.0, 1.0), origin=tuple(org))


def untagged_lps_stl(path):
    """The ball's surface as an ITK-based tool writes it: LPS coordinates, no SPACE= tag."""
    ball = trimesh.creation.icosphere(3, radius=RADIUS)
    ball.apply_translation(CENTRE_RAS * [-1, -1, 1])
    ball.export(path)
    assert mesh_space(path) is None
    return path


def surface_mean(res_json):
    return json.loads(res_json.read_text())["surface"]["mean"]


def test_an_untagged_surface_lands_where_slicer_puts_it_with_a_warning(tmp_path):
    """`clgs evaluate --surface`: the untagged LPS file measured against the ball it was drawn on.
    Read as RAS (the old reading) it lay 50 mm off."""
    ball_volume(tmp_path / "ball.nii.gz")
    stl = untagged_lps_stl(tmp_path / "ball.stl")
    common = ("evaluate", tmp_path / "ball.nii.gz", "--truth", tmp_path / "ball.nii.gz", "--level", 0.025,
              "--surface", stl)
    with pytest.warns(MeshWarning, match=r"declares no coordinate frame .* read as LPS.*--mesh-space RAS"):
        run(*common, "--json", tmp_path / "lps.json")
    assert surface_mean(tmp_path / "lps.json") < 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)  # a frame given: nothing to warn about
        run(*common, "--mesh-space", "ras", "--json", tmp_path / "ras.json")
        run(*common, "--mesh-space", "LPS", "--json", tmp_path / "lps2.json")
    assert surface_mean(tmp_path / "ras.json") > 40.0  # mirrored through the z axis: 50 mm away
    assert surface_mean(tmp_path / "lps2.json") < 0.5
    # on the command line the warning prints as one plain line on stderr
    out = subprocess.run([sys.executable, "-m", "clgs.cli", *map(str, common)], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "MeshWarning: " in out.stderr and "read as LPS, as 3D Slicer reads it" in out.stderr
    res = run("evaluate", tmp_path / "ball.nii.gz", "--truth", tmp_path / "ball.nii.gz", "--mesh-space", "RAS",
              ok=False)
    assert res.exit_code == 2 and "--surface" in res.output


def test_space_keyword_tag_wins_and_bad_frames_are_refused(tmp_path):
    stl = untagged_lps_stl(tmp_path / "ball.stl")
    with pytest.warns(MeshWarning, match=r"ball.stl declares no coordinate frame .* read as LPS"):
        lps = load_mesh(stl)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ras = load_mesh(stl, space="RAS")
        assert np.allclose(load_mesh(stl, space="lps").vertices, lps.vertices)
    assert np.allclose(lps.vertices.mean(0), CENTRE_RAS, atol=1e-6)
    assert np.allclose(ras.vertices.mean(0), CENTRE_RAS * [-1, -1, 1], atol=1e-6)
    tagged = save_mesh(tmp_path / "tagged.stl", lps)  # clgs writes SPACE=LPS
    back = load_mesh(tagged, space="RAS")  # the tag wins: the frame given is for untagged files
    assert np.allclose(back.vertices.mean(0), CENTRE_RAS, atol=1e-4)
    with pytest.raises(MeshError, match="RAS or LPS"):
        load_mesh(stl, space="RAI")


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj"])
def test_surfaces_clgs_writes_are_tagged_and_in_lps(tmp_path, suffix):
    ball = trimesh.creation.icosphere(2, radius=RADIUS)
    path = save_mesh(tmp_path / f"b{suffix}", ball.vertices + CENTRE_RAS, ball.faces)
    head = path.read_bytes()[:200]
    assert b"SPACE=LPS" in head
    raw = trimesh.load(str(path), force="mesh", process=False)
    assert np.allclose(np.asarray(raw.vertices).mean(0), CENTRE_RAS * [-1, -1, 1], atol=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.allclose(load_mesh(path).vertices.mean(0), CENTRE_RAS, atol=1e-3)


def test_a_scans_true_surface_is_tagged_and_an_earlier_untagged_one_stays_ras(tmp_path):
    from clgs.io.scan import Scan

    ball_volume(tmp_path / "ball.nii.gz")
    run("simulate", tmp_path / "ball.nii.gz", "--views", 4, "--detector", 16, "--no-noise", "--surface-level",
        0.025, "--out", tmp_path / "scan")
    stl = tmp_path / "scan" / "truth_surface.stl"
    assert mesh_space(stl) == "LPS"
    tagged = Scan.load(tmp_path / "scan").surface
    assert np.allclose(tagged.vertices.mean(0), CENTRE_RAS, atol=0.3)
    # earlier clgs versions wrote the same file in RAS without a tag: read as RAS, no warning
    trimesh.Trimesh(tagged.vertices, tagged.faces, process=False).export(stl)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        old = Scan.load(tmp_path / "scan").surface
    assert np.allclose(old.vertices.mean(0), CENTRE_RAS, atol=0.3)


def test_an_anatomys_surface_file_is_read_in_the_frame_given(tmp_path):
    """``clgs <anatomy> simulate --mesh`` and ``experiment --meshes`` read surfaces through
    subject_from_mesh_file; its ``space`` decides where an untagged surface lies."""
    from clgs.anatomy.simulation import subject_from_mesh_file
    from clgs.experiment import load_experiment_subject

    stl = untagged_lps_stl(tmp_path / "ball.stl")
    toy = types.SimpleNamespace(name="toy", scene={"density": 0.04}, load_template=None, subject_from_mesh=None)
    with pytest.warns(MeshWarning, match="read as LPS"):
        lps = subject_from_mesh_file(toy, stl)
    ras = subject_from_mesh_file(toy, stl, space="RAS")
    assert np.allclose(lps.vertices.mean(0), CENTRE_RAS, atol=1e-6)
    assert np.allclose(ras.vertices.mean(0), CENTRE_RAS * [-1, -1, 1], atol=1e-6)
    exp = load_experiment_subject(toy, "ball", {"ball": (str(stl), "mm", "RAS")}, seed=0)
    assert np.allclose(exp.vertices.mean(0), CENTRE_RAS * [-1, -1, 1], atol=1e-6)
    plugin = types.SimpleNamespace(name="plug", scene={}, load_template=None,
                                   subject_from_mesh=lambda path, seed=0: None)
    with pytest.raises(ValueError, match="its own frame"):
        subject_from_mesh_file(plugin, stl, space="RAS")
