"""``clgs bench ct``: FDK and SART wall time and quality at 5-50 views, and a 2-D comparison
with scikit-image.

3-D part: the head-like ellipsoid phantom of :func:`clgs.ct.phantoms.head_phantom` on a
``size``^3 grid (default 128^3, 2 mm voxels), cone beam (:meth:`Geometry.default`, detector
1.5 x size pixels, so a pixel at the axis is about one voxel), projections are the phantom's
*exact* line integrals (no inverse crime), with the acquisition noise of
:func:`clgs.ct.noise.add_noise` (I0 = 1e5, sigma = 10) unless ``--noiseless``. For each view
count: FDK (Hann window) and OS-SART (5 views per subset, relaxation 1, ``--sart-iters``
iterations) wall time, 3-D PSNR and SSIM (:mod:`clgs.metrics`, R2-Gaussian's definitions).

2-D part: the phantom's middle slice as a one-slice volume, parallel beam over 180 degrees, the
same exact sinogram (noise included) given to our FBP and SART and to scikit-image's ``iradon``
(Hann filter) and ``iradon_sart`` (as many passes as our iterations, its default relaxation
0.15): time ratio, PSNR (2-D here) and 2-D SSIM (scikit-image, Gaussian 11x11 window as R2-Gaussian). The
mapping to scikit-image's sinogram convention is checked against its own ``radon`` first.

Times are wall-clock medians of ``--repeat`` runs after a warm-up (compilation excluded); the
machine is shared, so compare ratios measured in the same run.
"""
from __future__ import annotations

import time

import click


def _timed(fn, repeat):
    out, times = None, []
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    times.sort()
    return out, times[len(times) // 2]


def _ssim2d(pred, truth):
    import numpy as np
    from skimage.metrics import structural_similarity

    lo, hi = float(truth.min()), float(truth.max())
    p = (np.asarray(pred, np.float64) - lo) / (hi - lo)
    t = (np.asarray(truth, np.float64) - lo) / (hi - lo)
    return structural_similarity(t, p, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False)


def _psnr2d(pred, truth):
    import numpy as np

    lo, hi = float(truth.min()), float(truth.max())
    mse = float(np.mean(((np.asarray(pred, np.float64) - truth) / (hi - lo)) ** 2))
    return 10 * np.log10(1.0 / mse)


def bench_3d(size, views_list, sart_iters, arc_deg, noise, seed, repeat, echo):
    import numpy as np

    from clgs import metrics
    from clgs.ct import phantoms as ph
    from clgs.ct.fdk import fdk
    from clgs.ct.noise import add_noise
    from clgs.ct.sart import sart
    from clgs.geometry import Geometry
    from clgs.ops.ct_projector import CTProjector

    n_det = int(round(1.5 * size))
    base = Geometry.default(n_views=max(views_list), arc=np.deg2rad(arc_deg), mode="cone", n_voxel=size,
                            n_detector=n_det, volume_mm=256.0)
    phantom = ph.head_phantom(base)
    t0 = time.perf_counter()
    truth = ph.voxelize(phantom, base, supersample=2)
    echo(f"3-D: head phantom {size}^3 ({256.0 / size:.1f} mm voxels, built in {time.perf_counter() - t0:.1f} s), "
         f"cone beam, detector {n_det}^2, arc {arc_deg:g} deg, "
         + ("noise I0=1e5 sigma=10" if noise else "noiseless") + f", OS-SART {sart_iters} iterations")
    head = (f"{'views':>5} | {'FDK s':>7} {'PSNR':>6} {'SSIM':>6} | {'SART s':>7} {'PSNR':>6} {'SSIM':>6} | "
            f"{'fwd+bwd s':>9}")
    echo(head)
    echo("-" * len(head))
    rows = []
    for nv in views_list:
        g = Geometry.default(n_views=nv, arc=np.deg2rad(arc_deg), mode="cone", n_voxel=size, n_detector=n_det,
                             volume_mm=256.0)
        proj = ph.project(phantom, g).astype(np.float32)
        if noise:
            proj = add_noise(proj, I0=1e5, sigma=10.0, seed=seed)
        fdk(proj, g, filter="hann")  # warm-up: compile
        rec_f, t_f = _timed(lambda: fdk(proj, g, filter="hann"), repeat)
        P = CTProjector(g)
        P.backward(P.forward(truth))  # warm-up
        _, t_fb = _timed(lambda: P.backward(P.forward(truth)), repeat)
        subsets = max(1, nv // 5)
        rec_s, t_s = _timed(lambda: sart(proj, g, n_iter=sart_iters, subsets=subsets, projector=P, seed=seed), 1)
        row = (nv, t_f, metrics.psnr3d(rec_f, truth), metrics.ssim3d(rec_f, truth),
               t_s, metrics.psnr3d(rec_s, truth), metrics.ssim3d(rec_s, truth), t_fb)
        rows.append(row)
        echo(f"{row[0]:>5} | {row[1]:>7.2f} {row[2]:>6.2f} {row[3]:>6.3f} | {row[4]:>7.2f} {row[5]:>6.2f} "
             f"{row[6]:>6.3f} | {row[7]:>9.2f}")
    return rows


def _skimage_mapping(size):
    """Our parallel geometry for a size x size slice that matches scikit-image's radon: its
    angle theta (degrees) is our pi/2 - theta, its detector axis our u reversed, its rotation
    centre the pixel (size // 2, size // 2) and its detector centre index diag // 2."""
    import numpy as np

    from clgs.geometry import Geometry

    diag = int(np.ceil(np.sqrt(2) * size))
    centre = size // 2 - 0.5 * (size - 1)          # rotation axis relative to the grid centre, voxels
    ou = 0.5 if diag % 2 == 0 else 0.0

    def geometry(theta_deg):
        return Geometry(DSD=4.0 * size, DSO=2.0 * size, nDetector=(1, diag), dDetector=(1.0, 1.0),
                        nVoxel=(1, size, size), dVoxel=(1.0, 1.0, 1.0), angles=np.pi / 2 - np.deg2rad(theta_deg),
                        offOrigin=(0.0, -centre, -centre), offDetector=(0.0, ou), mode="parallel")

    return geometry


def bench_2d(size, views_list, sart_iters, noise, seed, repeat, echo):
    import numpy as np
    from skimage.transform import iradon, iradon_sart, radon

    from clgs.ct import phantoms as ph
    from clgs.ct.fdk import fdk
    from clgs.ct.noise import add_noise
    from clgs.ct.sart import sart
    from clgs.geometry import Geometry
    from clgs.ops.ct_projector import CTProjector

    make = _skimage_mapping(size)
    # phantom: the 3-D head phantom's middle slice, as a one-slice volume
    g3 = Geometry.default(n_views=1, n_voxel=size, volume_mm=float(size))
    slab = [ph.Ellipsoid((e.centre[0], e.centre[1], 0.0), e.axes, e.density, e.angles)
            for e in ph.head_phantom(g3)]
    truth = ph.voxelize(slab, make(np.array([0.0])), supersample=3)[0].astype(np.float64)

    # check the convention mapping against scikit-image's own radon
    th = np.linspace(0.0, 180.0, 12, endpoint=False)
    ours = ph.project(slab, make(th))[:, 0, ::-1].T
    theirs = radon(truth, th, circle=False)
    mismatch = float(np.abs(ours - theirs).mean() / np.abs(ours).mean())
    echo(f"\n2-D: head phantom slice {size}^2 (1 mm pixels), parallel beam over 180 deg, "
         + ("noise I0=1e5 sigma=10" if noise else "noiseless")
         + f"; sinogram convention check vs skimage.radon: mean rel. difference {mismatch:.3f}")
    if mismatch > 0.05:
        echo("WARNING: the sinogram mapping to scikit-image does not match; its figures are not comparable")
    head = (f"{'views':>5} | {'FBP s':>7} {'skim s':>7} {'ratio':>6} {'PSNR':>6} {'skim':>6} {'SSIM':>6} {'skim':>6} | "
            f"{'SART s':>7} {'skim s':>7} {'ratio':>6} {'PSNR':>6} {'skim':>6} {'SSIM':>6} {'skim':>6}")
    echo(head)
    echo("-" * len(head))
    rows = []
    for nv in views_list:
        theta = np.linspace(0.0, 180.0, nv, endpoint=False)
        g = make(theta)
        proj = ph.project(slab, g).astype(np.float32)
        if noise:
            proj = add_noise(proj, I0=1e5, sigma=10.0, seed=seed)
        sino = np.ascontiguousarray(proj[:, 0, ::-1].T.astype(np.float64))
        fdk(proj, g, filter="hann")
        ours_f, t_of = _timed(lambda: fdk(proj, g, filter="hann")[0], repeat)
        sk_f, t_sf = _timed(lambda: iradon(sino, theta, filter_name="hann", circle=False, output_size=size), repeat)
        P = CTProjector(g)
        subsets = max(1, nv // 5)
        sart(proj, g, n_iter=1, subsets=subsets, projector=P)
        ours_s, t_os = _timed(lambda: sart(proj, g, n_iter=sart_iters, subsets=subsets, projector=P, seed=seed)[0], 1)

        def sk_sart():  # iradon_sart works on a diag x diag image centred at diag // 2: crop ours
            img = None
            for _ in range(sart_iters):
                img = iradon_sart(sino, theta, image=img)
            pad = sino.shape[0] // 2 - size // 2
            return img[pad:pad + size, pad:pad + size]

        sk_s, t_ss = _timed(sk_sart, 1)
        row = (nv, t_of, t_sf, t_sf / t_of, _psnr2d(ours_f, truth), _psnr2d(sk_f, truth), _ssim2d(ours_f, truth),
               _ssim2d(sk_f, truth), t_os, t_ss, t_ss / t_os, _psnr2d(ours_s, truth), _psnr2d(sk_s, truth),
               _ssim2d(ours_s, truth), _ssim2d(sk_s, truth))
        rows.append(row)
        echo(f"{nv:>5} | {row[1]:>7.3f} {row[2]:>7.3f} {row[3]:>6.1f} {row[4]:>6.2f} {row[5]:>6.2f} {row[6]:>6.3f} "
             f"{row[7]:>6.3f} | {row[8]:>7.3f} {row[9]:>7.3f} {row[10]:>6.1f} {row[11]:>6.2f} {row[12]:>6.2f} "
             f"{row[13]:>6.3f} {row[14]:>6.3f}")
    echo("ratio = scikit-image time / ours (above 1: ours is faster)")
    return rows


class ViewCounts(click.ParamType):
    """View counts: ``5,10,25`` -> (5, 10, 25), each a whole number of at least 1."""

    name = "count[,count...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (tuple, list)):
            return tuple(value)
        try:
            counts = tuple(int(v) for v in str(value).split(",") if v.strip())
        except ValueError:
            counts = ()
        if not counts or min(counts) < 1:
            self.fail(f"{value!r}: give view counts of at least 1, e.g. 5,10,25", param, ctx)
        return counts


@click.command()
@click.option("--quick", is_flag=True, help="64^3 volume, 64^2 slice, 5 SART iterations, one repeat")
@click.option("--size", type=int, default=128, show_default=True, help="3-D volume side (voxels)")
@click.option("--views", type=ViewCounts(), default="5,10,25,50", show_default=True, help="comma-separated view counts")
@click.option("--sart-iters", type=int, default=10, show_default=True, help="OS-SART iterations (and skimage passes)")
@click.option("--arc", "arc_deg", type=float, default=360.0, show_default=True, help="3-D scan arc, degrees")
@click.option("--noise/--no-noise", default=True, show_default=True, help="Poisson + electronic noise")
@click.option("--repeat", type=int, default=3, show_default=True, help="timed repeats of FDK (median)")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--skip-2d", is_flag=True, help="only the 3-D part")
def main(quick, size, views, sart_iters, arc_deg, noise, repeat, seed, skip_2d):
    """FDK and SART: wall time and 3-D PSNR/SSIM at 5-50 views; 2-D against scikit-image."""
    from clgs.runtime import device

    views_list = list(views)
    size2d = 128
    if quick:
        size, size2d, sart_iters, repeat = 64, 64, 5, 1
    click.echo(f"device: {device().name.strip()}")
    bench_3d(size, views_list, sart_iters, arc_deg, noise, seed, repeat, click.echo)
    if not skip_2d:
        bench_2d(size2d, views_list, sart_iters, noise, seed, repeat, click.echo)
