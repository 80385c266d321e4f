"""Simulation grids and world positions: the reconstruction grid (--grid), the finer grid the
projections come from (no inverse crime), and the input's position kept in every output."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from clgs.ct.simulation_grid import fine_bytes, parse_grid, projection_volume, resample_box
from clgs.errors import InputError
from clgs.geometry import Geometry


def _blob(n=24):
    z, y, x = (np.mgrid[:n, :n, :n] + 0.5) / n - 0.5
    return (0.02 * np.exp(-(x**2 + (y - 0.05) ** 2 + (z + 0.03) ** 2) / 0.03)).astype(np.float32)


def test_parse_grid():
    assert parse_grid(None) is None
    assert parse_grid("16") == (16, 16, 16)
    assert parse_grid("8, 16,32") == (8, 16, 32)
    for bad in ("0", "a", "1,2", "4,4,-1"):
        with pytest.raises(InputError, match="NZ,NY,NX"):
            parse_grid(bad)


def test_resample_box_keeps_the_box():
    """A linear ramp along x sampled at voxel centres stays exact where both grids have samples
    away from the edges: the new grid covers the same box, not the same first and last centres."""
    n, m = 32, 16
    x = (np.arange(n) + 0.5) / n  # voxel centres in units of the box
    ramp = np.broadcast_to(x, (4, 4, n)).astype(np.float32)
    out = resample_box(ramp, (4, 4, m))
    xm = (np.arange(m) + 0.5) / m
    np.testing.assert_allclose(out[2, 2, 1:-1], xm[1:-1], atol=1e-6)
    up = resample_box(ramp, (4, 4, 2 * n))
    x2 = (np.arange(2 * n) + 0.5) / (2 * n)
    np.testing.assert_allclose(up[2, 2, 2:-2], x2[2:-2], atol=1e-6)


def test_projection_volume_protocols():
    vol = _blob(24)
    assert np.array_equal(projection_volume(vol, vol.shape, "same"), vol)
    fine = projection_volume(vol, vol.shape, "fine")
    assert fine.shape == (48, 48, 48)
    assert fine_bytes(vol.shape, vol.shape) == 4.0 * 48 ** 3
    # an input already twice as fine as the reconstruction grid is projected as it is
    coarse = (12, 12, 10)
    same_input = projection_volume(vol, coarse, "fine")
    assert same_input.shape == (24, 24, 24) and np.array_equal(same_input, vol)
    with pytest.raises(InputError, match="fine, same"):
        projection_volume(vol, vol.shape, "exact")


def test_fine_projections_describe_the_same_object_but_not_the_same_model():
    """Projections of the twice-as-fine grid agree with the same-grid ones to a few percent of
    the largest line integral (one object) without being those numbers (another discretisation)."""
    from clgs.ops.ct_projector import CTProjector

    vol = _blob(24)
    g = Geometry.default(n_views=4, n_voxel=24, n_detector=32, volume_mm=48.0)
    d = g.to_dict()
    d.update(nVoxel=[48] * 3, dVoxel=[1.0] * 3)
    same = np.asarray(CTProjector(g).forward(vol))
    fine = np.asarray(CTProjector(Geometry.from_dict(d)).forward(projection_volume(vol, vol.shape, "fine")))
    scale = float(same.max())
    assert scale > 0.1
    diff = np.abs(fine - same).max() / scale
    assert 1e-4 < diff < 0.04, diff


def test_isocentre_moves_world_positions_only():
    g0 = Geometry.default(n_views=3, n_voxel=16, n_detector=24, volume_mm=32.0)
    d = g0.to_dict()
    d["isocentre"] = [300.0, 40.0, -120.0]  # (Z, Y, X)
    g1 = Geometry.from_dict(d)
    back = Geometry.from_dict(json.loads(g1.to_json()))
    assert back.isocentre == (300.0, 40.0, -120.0)
    assert np.array_equal(back.view_vectors(scene=False), g1.view_vectors(scene=False))
    assert "isocentre" not in g0.to_dict()  # circular TIGRE scans keep TIGRE's names only
    # the kernels' view of the scan (scene units, relative to the volume) is unchanged, bit for bit
    assert np.array_equal(g0.view_vectors(scene=True), g1.view_vectors(scene=True))
    np.testing.assert_allclose(g1.view_vectors(scene=False)[:, :6] - g0.view_vectors(scene=False)[:, :6],
                               np.tile([-120.0, 40.0, 300.0], (3, 2)), atol=1e-9)
    np.testing.assert_allclose(np.asarray(g1.volume_grid(scene=False).origin) -
                               np.asarray(g0.volume_grid(scene=False).origin), [-120.0, 40.0, 300.0])
    p = np.array([[0.1, -0.2, 0.3]])
    np.testing.assert_allclose(g1.scene_to_world(p) - g0.scene_to_world(p), [[-120.0, 40.0, 300.0]])
    np.testing.assert_allclose(g1.world_to_scene(g1.scene_to_world(p)), p, atol=1e-12)
    # the CT projector, which works in world mm, gives the same projections
    from clgs.ops.ct_projector import CTProjector

    vol = _blob(16)
    np.testing.assert_allclose(CTProjector(g1).forward(vol), CTProjector(g0).forward(vol), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="non-finite"):
        Geometry.from_dict({**d, "isocentre": [0, float("nan"), 0]})


@pytest.fixture(scope="module")
def placed_nifti(tmp_path_factory):
    import nibabel as nib

    folder = tmp_path_factory.mktemp("placed")
    z, y, x = np.mgrid[:32, :32, :32]
    vol = (((x - 16) ** 2 + (y - 13) ** 2 + (z - 18) ** 2) < 80).astype(np.float32) * 0.02
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    aff[:3, 3] = (-120.0, 40.0, 300.0)
    nib.save(nib.Nifti1Image(vol.transpose(2, 1, 0), aff), folder / "in.nii.gz")
    return folder, vol, aff


def _centroid_world(img):
    v = np.clip(img.get_fdata(), 0, None)
    ijk = (v * np.indices(v.shape)).sum((1, 2, 3)) / v.sum()
    return img.affine[:3, :3] @ ijk + img.affine[:3, 3]


def test_simulate_and_reconstruct_keep_the_input_position(placed_nifti):
    """Input, truth and reconstruction, loaded with nibabel: the same affine, and the object's
    centroid at the same world point (within a third of a voxel)."""
    import nibabel as nib

    from clgs.cli import main

    folder, vol, aff = placed_nifti
    runner = CliRunner()
    scan, rec = folder / "scan", folder / "rec"
    r = runner.invoke(main, ["simulate", str(folder / "in.nii.gz"), "--out", str(scan), "--views", "24",
                             "--detector", "64", "--no-noise"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(main, ["reconstruct", str(scan), "--method", "fdk", "--out", str(rec)])
    assert r.exit_code == 0, r.output
    inp = nib.load(folder / "in.nii.gz")
    truth, out = nib.load(scan / "truth.nii.gz"), nib.load(rec / "volume.nii.gz")
    np.testing.assert_allclose(truth.affine, aff)
    np.testing.assert_allclose(out.affine, aff)
    np.testing.assert_allclose(_centroid_world(out), _centroid_world(inp), atol=2.0 / 3)
    meta = json.loads((scan / "scan.json").read_text())
    sim = meta["meta"]["acquisition"]["simulation"]
    assert sim == {"protocol": "fine", "projected_grid": [64, 64, 64], "reconstruction_grid": [32, 32, 32]}


def test_a_coarser_grid_covers_the_same_box(placed_nifti):
    import nibabel as nib

    from clgs.cli import main

    folder, vol, aff = placed_nifti
    scan = folder / "scan16"
    r = CliRunner().invoke(main, ["simulate", str(folder / "in.nii.gz"), "--out", str(scan), "--views", "8",
                                  "--detector", "32", "--grid", "16", "--simulation", "same", "--no-noise"])
    assert r.exit_code == 0, r.output
    truth = nib.load(scan / "truth.nii.gz")
    assert truth.shape == (16, 16, 16)
    np.testing.assert_allclose(np.diag(truth.affine)[:3], [4.0, 4.0, 4.0])
    np.testing.assert_allclose(truth.affine[:3, 3], [-119.0, 41.0, 301.0])  # same box: half a new voxel in
    np.testing.assert_allclose(_centroid_world(truth), _centroid_world(nib.load(folder / "in.nii.gz")), atol=0.5)
    assert np.isclose(truth.get_fdata().sum() * 64, vol.sum() * 8, rtol=0.02)  # mass kept
    r = CliRunner().invoke(main, ["simulate", str(folder / "in.nii.gz"), "--out", str(folder / "bad"),
                                  "--grid", "4,4"])
    assert r.exit_code != 0 and "--grid" in r.output and "NZ,NY,NX" in r.output


def test_grid_spacing_chooses_the_grid_by_voxel_size(placed_nifti, tmp_path):
    import nibabel as nib

    from clgs.cli import main

    folder, vol, aff = placed_nifti
    r = CliRunner().invoke(main, ["simulate", str(folder / "in.nii.gz"), "--out", str(tmp_path / "s"), "--views", "4",
                                  "--detector", "32", "--grid-spacing", "4,4,8", "--no-noise"])
    assert r.exit_code == 0, r.output
    truth = nib.load(tmp_path / "s" / "truth.nii.gz")
    assert truth.shape == (8, 16, 16)  # (X, Y, Z) in NIfTI: 64 mm / 8, / 4, / 4
    np.testing.assert_allclose(np.diag(truth.affine)[:3], [8.0, 4.0, 4.0])
    for bad in (["--grid", "8", "--grid-spacing", "4"], ["--grid-spacing", "0"]):
        r = CliRunner().invoke(main, ["simulate", str(folder / "in.nii.gz"), "--out", str(tmp_path / "b"), *bad])
        assert r.exit_code == 2 and "grid" in r.output, r.output
