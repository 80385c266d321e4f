"""Loss terms (against direct formulas), the training log files, checkpoints' format, and the
``clgs reconstruct --method r2gs`` command."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from clgs.fit import checkpoint as ckpt
from clgs.fit import losses as L
from clgs.fit.training_log import TrainingLog
from clgs.geometry import Grid
from clgs.ops import ssim as ssim_op


def _ssim_direct(a, b):
    """SSIM with the full 11x11 window as one 2D convolution (the textbook 3DGS form), float64."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-x * x / (2 * 1.5 ** 2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :])[None, None]
    f = lambda t: F.conv2d(t[None, None], w, padding=5)[0, 0]  # noqa: E731
    ma, mb = f(a), f(b)
    va, vb, cov = f(a * a) - ma ** 2, f(b * b) - mb ** 2, f(a * b) - ma * mb
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2))).mean()


def test_ssim_matches_the_2d_window_formula_and_bounds():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(40, 33, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.rand(40, 33, generator=g, dtype=torch.float64)).clamp(0, 1)
    assert float(L.ssim(a, b)) == pytest.approx(float(_ssim_direct(a, b)), rel=1e-10)
    assert float(L.ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
    assert float(L.ssim(a, b, b_maps=L.target_maps(b))) == pytest.approx(float(_ssim_direct(a, b)), rel=1e-10)
    assert float(L.dssim(a, b)) == pytest.approx(1 - float(_ssim_direct(a, b)), rel=1e-9)
    assert 0 < float(L.dssim(a, 1 - a)) <= 2
    a32 = a.float().requires_grad_(True)
    L.dssim(a32, b.float()).backward()
    assert torch.isfinite(a32.grad).all() and a32.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="shapes"):
        L.ssim(a, b[:-1])


def test_ssim_gradient_matches_autograd_through_the_direct_formula():
    """The hand-written SSIM backward (fixed target, cached maps or not) against autograd through
    the 2D-window formula, float64; and a gradient check on a small image."""
    g = torch.Generator().manual_seed(2)
    a = torch.rand(40, 33, generator=g, dtype=torch.float64, requires_grad=True)
    b = (a.detach() + 0.3 * torch.rand(40, 33, generator=g, dtype=torch.float64)).clamp(0, 1)
    ref, = torch.autograd.grad(_ssim_direct(a, b), a)
    for maps in (None, L.target_maps(b)):
        got, = torch.autograd.grad(L.ssim(a, b, b_maps=maps), a)
        torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-14)
    # a target that needs a gradient too takes plain autograd: same values for a
    b2 = b.clone().requires_grad_(True)
    got, gb = torch.autograd.grad(L.ssim(a, b2), (a, b2))
    torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-14)
    assert torch.isfinite(gb).all() and gb.abs().sum() > 0
    small = a.detach()[:6, :7].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: L.ssim(t, b[:6, :7]), (small,))


@pytest.mark.parametrize("shape", [(2, 1, 40, 33), (1, 1, 4, 7)])
def test_blur_is_the_zero_padded_window_and_its_gradient(shape):
    """The shifted-add filter against one 2D convolution (values and gradient, float64); images
    smaller than the window included. Its backward is the filter itself (self-adjoint)."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    w1 = ssim_op.window(11, 1.5, torch.float64)
    w2 = (w1[:, None] * w1[None, :])[None, None]
    ref = F.conv2d(x, w2, padding=5)
    got = ssim_op.blur(x, w1)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-15)
    v = torch.rand(shape, generator=g, dtype=torch.float64)
    ga, = torch.autograd.grad((got * v).sum(), x)
    gb, = torch.autograd.grad((ref * v).sum(), x)
    torch.testing.assert_close(ga, gb, rtol=1e-12, atol=1e-15)
    assert torch.autograd.gradcheck(lambda t: ssim_op.blur(t, w1), (x[:1, :, :6, :5].detach().requires_grad_(True),))


def test_l1_and_tv():
    a = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    assert float(L.l1(a, torch.zeros(2, 2))) == 2.5
    z, y, x = torch.meshgrid(torch.arange(4.0), torch.arange(5.0), torch.arange(6.0), indexing="ij")
    vol = 2 * x + 3 * y - z  # constant steps along each axis
    # all absolute differences over their count (R2-Gaussian's mean), not the sum of per-axis means
    n_x, n_y, n_z = 4 * 5 * 5, 4 * 4 * 6, 3 * 5 * 6
    assert L.tv_count(vol.shape) == n_x + n_y + n_z
    assert float(L.tv3d(vol)) == pytest.approx((2 * n_x + 3 * n_y + 1 * n_z) / (n_x + n_y + n_z))
    assert float(L.tv3d(torch.ones(3, 3, 3))) == 0
    assert float(L.tv3d(torch.ones(1, 1, 5).cumsum(-1))) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="block"):
        L.tv3d(torch.ones(3, 3))


def test_random_block_is_inside_seeded_and_clipped():
    grid = Grid((40, 50, 60), (-1.0, -1.0, -1.0), (0.05, 0.05, 0.05))
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    for _ in range(20):
        b = L.random_block(grid, 32, g1)
        assert b == L.random_block(grid, 32, g2)
        assert b.shape == (32, 32, 32)
        start = np.rint((np.asarray(b.origin) - grid.origin) / 0.05).astype(int)  # (x, y, z)
        assert np.all(start >= 0) and np.all(start + 32 <= np.asarray(grid.shape)[::-1])
    assert L.random_block(Grid((8, 40, 40), (0, 0, 0), (1, 1, 1)), 32, g1).shape == (8, 32, 32)


def test_subvoxel_blocks_leave_the_voxel_lattice_but_stay_inside():
    grid = Grid((40, 50, 60), (-1.0, -1.0, -1.0), (0.05, 0.05, 0.05))
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    fracs = []
    for _ in range(30):
        b = L.random_block(grid, 32, g1, subvoxel=True)
        assert b == L.random_block(grid, 32, g2, subvoxel=True)  # seeded
        assert b.shape == (32, 32, 32) and b.spacing == grid.spacing
        pos = (np.asarray(b.origin) - grid.origin) / 0.05  # (x, y, z) in voxels
        last = pos + 31
        assert np.all(pos >= 0) and np.all(last <= np.asarray(grid.shape)[::-1] - 1 + 1e-9)
        fracs.extend(pos - np.floor(pos))
    assert 0.3 < np.mean(fracs) < 0.7 and np.max(fracs) > 0.5  # off the lattice, spread over the voxel
    small = L.random_block(Grid((1, 40, 40), (0, 0, 0), (1, 1, 1)), 32, g1, subvoxel=True)
    assert small.shape == (1, 32, 32) and small.origin[2] == 0  # a one-sample axis is not shifted


def test_training_log_csv_plot_and_summary(tmp_path):
    log = TrainingLog()
    log.add({"iteration": 0, "seconds": 0.0, "wall": 0.0, "n_gaussians": 10, "proj_psnr": 20.0, "psnr3d": 18.0})
    log.add({"iteration": 100, "seconds": 2.0, "wall": 2.5, "n_gaussians": 12, "loss": 0.1, "l1": 0.08,
             "proj_psnr": 30.0, "psnr3d": 25.5, "ssim3d": 0.8})
    log.add({"iteration": 200, "seconds": 4.0, "wall": 4.9, "n_gaussians": 15, "loss": 0.05, "l1": 0.04,
             "proj_psnr": 33.0, "psnr3d": 25.0, "ssim3d": 0.85})
    log.write_csv(tmp_path / "log.csv")
    back = TrainingLog.read_csv(tmp_path / "log.csv")
    assert back.rows[0]["loss"] is None and back.rows[2]["iteration"] == 200
    assert back.rows[1]["psnr3d"] == pytest.approx(25.5)
    png = log.plot(tmp_path / "log.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = log.summary()
    assert "best" in text and "25.5" in text and "50.0 it/s" in text


def test_checkpoint_refuses_foreign_files(tmp_path):
    torch.save({"a": torch.ones(2)}, tmp_path / "x.pt")
    with pytest.raises(ckpt.CheckpointError, match="not a clgs checkpoint"):
        ckpt.load(tmp_path / "x.pt")
    (tmp_path / "y.pt").write_bytes(b"garbage")
    with pytest.raises(ckpt.CheckpointError, match="not a readable"):
        ckpt.load(tmp_path / "y.pt")
    ckpt.save(tmp_path / "ok.pt", {"t": torch.arange(3), "s": ckpt.dumps({"big": 2 ** 100}), "n": 4})
    back = ckpt.load(tmp_path / "ok.pt")
    assert torch.equal(back["t"], torch.arange(3)) and ckpt.loads(back["s"])["big"] == 2 ** 100


def test_cli_reconstruct_r2gs(tmp_path):
    from click.testing import CliRunner

    from clgs.cli import main
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.ops.projector import project
    from clgs.ops.voxelizer import voxelize

    geo = Geometry.default(n_views=6, n_voxel=16, n_detector=20, volume_mm=64.0)
    t = [torch.tensor(v, dtype=torch.float32) for v in
         ([[0.1, -0.1, 0.0], [-0.3, 0.2, 0.1]], [[0.2, 0.15, 0.1], [0.1, 0.1, 0.25]],
          [[1.0, 0, 0, 0], [0.9, 0.1, 0.3, 0]], [0.02, 0.015])]
    with torch.no_grad():
        scan = Scan(geo, project(*t, geo).numpy(), voxelize(*t, geo.volume_grid()).numpy())
    scan.save(tmp_path / "scan")
    out = tmp_path / "run"
    args = ["reconstruct", str(tmp_path / "scan"), "--method", "r2gs", "--iterations", "12", "--out", str(out),
            "--gaussians", "80", "--log-every", "6", "--no-progress"]
    r = CliRunner().invoke(main, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "PSNR" in r.output
    for f in ("volume.nii.gz", "gaussians.npz", "log.csv", "log.png", "checkpoint.pt"):
        assert (out / f).is_file(), f
    assert [row["iteration"] for row in TrainingLog.read_csv(out / "log.csv").rows] == [0, 6, 12]
    r = CliRunner().invoke(main, args[:4] + ["--iterations", "18", "--out", str(out), "--resume", "--no-progress"],
                           catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert [row["iteration"] for row in TrainingLog.read_csv(out / "log.csv").rows] == [0, 6, 12, 18]
    assert math.isfinite(TrainingLog.read_csv(out / "log.csv").rows[-1]["psnr3d"])


def test_a_hostile_checkpoint_is_refused_without_unsafe_advice(tmp_path):
    """A checkpoint holding arbitrary objects is refused by the safe loader; the message says to
    delete it or start without --resume, and never passes on torch's advice to load it unsafely."""
    import pickle

    from clgs.fit import checkpoint as ckpt

    class Payload:
        def __reduce__(self):
            return (print, ("this must never run",))

    path = tmp_path / "checkpoint.pt"
    with open(path, "wb") as fh:
        pickle.dump({"format": "clgs-checkpoint", "x": Payload()}, fh, protocol=2)
    with pytest.raises(ckpt.CheckpointError) as err:
        ckpt.load(path)
    text = str(err.value)
    assert "weights_only" not in text and "without --resume" in text and "delete it" in text
