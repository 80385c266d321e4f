"""``clgs bench kernels``: the Gaussian projector (and the voxelizer) against the same math in
torch, in one run.

Scene: N Gaussians (10k, 50k), centres uniform in [-0.7, 0.7]^3, standard deviations
log-uniform in 1-4 x 0.0077 scene units (3-sigma radius 2-8 pixels on the 256^2 detector of
``Geometry.default``, 1-4 on 128^2), random rotations, densities uniform in [0, 0.1]; float32.
For each detector (128^2, 256^2), beam (cone, parallel) and mode (affine, exact):

* ``fwd ms`` / ``bwd ms``: medians over ``--repeat`` single-view calls (a different view each
  time) of ``GaussianProjector.forward`` (set-up, on-device binning, render, read-back) and
  ``.backward`` (all three gradients, reusing the forward's set-up as the autograd op does),
  after a warm-up (compilation excluded).
* ``Geval/s``: useful Gaussian-pixel evaluations per second, useful = pixels whose ray passes
  within 3 sigma of a Gaussian (counted in torch from the affine 2D covariances, the same
  count used for both modes; the two footprints differ by well under 1%).
* ``x torch``: speed-up of forward + backward over ``clgs.reference.projection.project_patches``
  (each Gaussian on a square patch, ``index_add_``, autograd backward) timed in the same run on
  torch's CPU threads; with more than ``--torch-n`` Gaussians torch runs on the first
  ``--torch-n`` and its time is scaled by N / torch-n (its cost is linear in N).
* ``fwd cpu`` / ``bwd cpu``: the same calls' CPU time (all threads of the process, ms): on a
  shared machine, CPU time / cores estimates the unloaded wall time better than wall time does.
* ``exp ceil``: the fraction of the device's own exp throughput (probe kernel: the inline exp
  in a loop at the projector's vector width, ``fast_exp16`` where the device's native float
  vector has 16 lanes, else ``fast_exp8``; measured in the same run) reached by the useful
  evaluation rate, both per CPU-second (mean of forward and backward). The probe is printed at
  that width and at 8 lanes for comparison, and the widths each row's render and backward use
  are printed before the table (``$CLGS_TILE_WIDTH=8|16`` forces one; see ``clgs.ops.projector``).
* For exact rows: ``err vs exact`` is max |affine - exact| / max exact of the same view, and
  ``exact/affine`` the ratio of their fwd+bwd times.
* ``--stages``: after each row, every kernel's device time (event profiling, median ms), the
  number of kernel launches per forward and per backward call, and the call's wall time outside
  its kernels (Python, argument setting, waits, read-back), to see where time goes.
* ``--widths``: after each row, the same calls with the projector forced to 8 and to 16 lanes
  on every kernel, alternating call by call in this process (``--repeat`` rounds, medians): wall
  and CPU milliseconds and the 8/16 ratios, to decide per kernel which width pays.
* ``--fastest``: after each row, the fastest of the ``--repeat`` calls each way and its rate: on
  a shared machine the least disturbed call, a bound on what the code does unloaded (the table
  keeps the medians).
* ``--vectors``: after each row, the same calls on the same scan written as per-view vectors
  and on it with the detector tilted (rolled 5 degrees and, in cone beam, pitched 5 degrees),
  alternating call by call (``--repeat`` rounds, medians) with the circular description, and
  the ratios; then the CT projector pair (64^3 volume, 16 views of 96^2) circular against vectors.
* ``--n``, ``--det``, ``--beam``: run only these cases (each may be repeated), e.g. the
  reference case ``--n 50000 --det 256 --beam cone`` (the voxelizer rows are then left out).

The machine may be shared: compare ratios within a run, not across runs.
"""
from __future__ import annotations

import time

import click

from clgs.bench.devices import device_option, on_each_device, ratio_table
from clgs.bench.host import HostWatch


def _median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2]


def _scene(n, seed=0):
    import numpy as np
    import torch

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.4
    scales = 0.0077 * torch.exp(torch.rand(n, 3, generator=g) * float(np.log(4.0)))
    quats = torch.randn(n, 4, generator=g)
    rho = 0.1 * torch.rand(n, generator=g)
    return means, scales, quats, rho


def _useful(means, cov, geometry, view):
    """Pixels with q <= 9 summed over Gaussians (affine 2D covariance, in patches)."""
    import math

    import torch

    from clgs.reference.projection import affine_params as _affine_params

    nv, nu = geometry.nDetector
    total = 0
    for s in range(0, means.shape[0], 5000):
        c, S2, _, vis = _affine_params(means[s:s + 5000].detach().double(), cov[s:s + 5000].detach().double(),
                                       geometry, view)
        with torch.no_grad():
            det = S2[:, 0, 0] * S2[:, 1, 1] - S2[:, 0, 1] ** 2
            k0, k1, k2 = S2[:, 1, 1] / det, -S2[:, 0, 1] / det, S2[:, 0, 0] / det
            R = int(math.ceil(float((3 * torch.sqrt(torch.maximum(S2[:, 0, 0], S2[:, 1, 1]))).max()))) + 1
            off = torch.arange(-R, R + 1, dtype=torch.float64)
            base = torch.round(c)
            pu = base[:, 0, None, None] + off[None, None, :]
            pv = base[:, 1, None, None] + off[None, :, None]
            du, dv = pu - c[:, 0, None, None], pv - c[:, 1, None, None]
            q = k0[:, None, None] * du * du + 2 * k1[:, None, None] * du * dv + k2[:, None, None] * dv * dv
            ok = (q <= 9) & (pu >= 0) & (pu <= nu - 1) & (pv >= 0) & (pv <= nv - 1) & vis[:, None, None]
            total += int(ok.sum())
    return total


def _exp_ceiling(projector, repeat):
    """exp/s of the probe kernel at the projector's render width (``fast_exp8`` or ``fast_exp16``):
    (per wall second, per CPU second of this process)."""
    import numpy as np
    import pyopencl as cl

    prog = projector.program("cone", "affine", "float")
    width = projector.widths("cone", "affine")[0]
    n, G = 4000, 8192
    buf = cl.Buffer(projector.ctx, cl.mem_flags.READ_WRITE, size=G * 4)
    k = prog.kernel("exp_probe")
    k(projector.queue, (G,), (64,), np.int32(n), buf)
    projector.queue.finish()
    ts, cs = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        k(projector.queue, (G,), (64,), np.int32(n), buf)
        projector.queue.finish()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    return G * n * width / _median(ts), G * n * width / _median(cs)


def _time_kernels(projector, m, mats, rho, geometry, mode, repeat):
    """Median wall and CPU milliseconds of forward and backward, and the view-0 image."""
    import numpy as np

    mn, mt, rn = m.numpy(), mats.numpy(), rho.numpy()
    out = projector.forward(mn, mt, rn, geometry, [0], mode)
    gout = np.random.default_rng(0).random(out.shape, dtype=np.float32)
    projector.backward(mn, mt, rn, geometry, [0], mode, gout, token=projector.last_token)
    tf, tb, cf, cb = [], [], [], []
    for r in range(repeat):
        view = r % geometry.n_views
        t, c = time.perf_counter(), time.process_time()
        projector.forward(mn, mt, rn, geometry, [view], mode)
        tf.append(time.perf_counter() - t)
        cf.append(time.process_time() - c)
        t, c = time.perf_counter(), time.process_time()
        projector.backward(mn, mt, rn, geometry, [view], mode, gout, token=projector.last_token)
        tb.append(time.perf_counter() - t)
        cb.append(time.process_time() - c)
    return [_median(x) * 1e3 for x in (tf, tb, cf, cb)] + [out[0], min(tf) * 1e3, min(tb) * 1e3]


def _stages(projector, m, mats, rho, geometry, mode, repeat):
    """Per-kernel device milliseconds (median), launches per call and the call's wall time
    outside its kernels (median of wall minus the sum of its kernels: Python, argument setting,
    waits, read-back; on a busy machine also time the device spent waiting for a core),
    forward and backward."""
    import numpy as np
    import pyopencl as cl

    mn, mt, rn = m.numpy(), mats.numpy(), rho.numpy()
    queue = projector.queue
    projector.queue = cl.CommandQueue(projector.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
    events: list = []
    projector.on_launch = lambda name, event: events.append((name, event))
    gout = np.random.default_rng(0).random((1, *geometry.nDetector), dtype=np.float32)
    times = {"fwd": {}, "bwd": {}}
    outside = {"fwd": [], "bwd": []}
    launches = {"fwd": 0, "bwd": 0}
    try:
        for r in range(repeat):
            for phase in ("fwd", "bwd"):
                events.clear()
                t = time.perf_counter()
                if phase == "fwd":
                    projector.forward(mn, mt, rn, geometry, [r % geometry.n_views], mode)
                else:
                    projector.backward(mn, mt, rn, geometry, [r % geometry.n_views], mode, gout,
                                       token=projector.last_token)
                wall = time.perf_counter() - t
                projector.queue.finish()
                launches[phase] = len(events)
                dev = 0.0
                for name, ev in events:
                    ms = (ev.profile.end - ev.profile.start) * 1e-6
                    times[phase].setdefault(name, []).append(ms)
                    dev += ms
                outside[phase].append(wall * 1e3 - dev)
    finally:
        projector.queue = queue
        projector.on_launch = None
    return ({ph: {k: _median(v) for k, v in t.items()} for ph, t in times.items()}, launches,
            {ph: _median(v) for ph, v in outside.items()})


def _compare_widths(projectors, m, mats, rho, geometry, mode, repeat):
    """{width: [fwd wall, bwd wall, fwd cpu, bwd cpu] medians (ms)}, widths alternating call by call."""
    return _alternate({w: (p, geometry) for w, p in projectors.items()}, m, mats, rho, mode, repeat)


def _alternate(cases, m, mats, rho, mode, repeat):
    """{name: [fwd wall, bwd wall, fwd cpu, bwd cpu] medians (ms)} of ``cases`` {name: (projector,
    geometry)}, alternating call by call (the order reversed every round) so that a shared
    machine's load falls on every case alike."""
    import numpy as np

    mn, mt, rn = m.numpy(), mats.numpy(), rho.numpy()
    times = {w: ([], [], [], []) for w in cases}
    for r in range(repeat + 1):
        order = list(cases.items()) if r % 2 == 0 else list(cases.items())[::-1]
        for w, (p, geometry) in order:
            gout = np.random.default_rng(0).random((1, *geometry.nDetector), dtype=np.float32)
            view = [r % geometry.n_views]
            t, c = time.perf_counter(), time.process_time()
            p.forward(mn, mt, rn, geometry, view, mode)
            tf, cf = time.perf_counter() - t, time.process_time() - c
            t, c = time.perf_counter(), time.process_time()
            p.backward(mn, mt, rn, geometry, view, mode, gout, token=p.last_token)
            tb, cb = time.perf_counter() - t, time.process_time() - c
            if r:  # the first round compiles
                for lst, x in zip(times[w], (tf, tb, cf, cb)):
                    lst.append(x)
    return {w: [_median(x) * 1e3 for x in ts] for w, ts in times.items()}


def tilted(geometry, roll_deg: float = 5.0, pitch_deg: float = 5.0):
    """The scan as per-view vectors with its detector turned about its centre: ``roll_deg`` in its
    own plane and, in cone beam, ``pitch_deg`` about its u axis (parallel rays stay perpendicular)."""
    import numpy as np

    from clgs.geometry import Geometry

    vec = geometry.view_vectors(scene=False)
    out = vec.copy()
    for i, row in enumerate(vec):
        u, v = row[6:9], row[9:12]
        eu, ev = u / np.linalg.norm(u), v / np.linalg.norm(v)
        n = np.cross(eu, ev)
        r, p = np.deg2rad(roll_deg), np.deg2rad(pitch_deg if geometry.mode == "cone" else 0.0)
        eu2, ev2 = np.cos(r) * eu + np.sin(r) * ev, -np.sin(r) * eu + np.cos(r) * ev
        ev3 = np.cos(p) * ev2 + np.sin(p) * n
        out[i, 6:9] = np.linalg.norm(u) * eu2
        out[i, 9:12] = np.linalg.norm(v) * ev3
    return Geometry.from_vectors(out, geometry.nDetector, geometry.nVoxel, geometry.dVoxel, geometry.offOrigin,
                                 geometry.mode)


def _vector_rows(proj, m, mats, rho, g, mode, repeat) -> str:
    """The ``--vectors`` line of one row: the same scan circular, as vectors, and tilted."""
    r = _alternate({"circular": (proj, g), "vectors": (proj, g.as_vectors()), "tilted": (proj, tilted(g))},
                   m, mats, rho, mode, repeat)
    c, v, t = r["circular"], r["vectors"], r["tilted"]
    return (f"    circular / vectors / tilted vectors: fwd {c[0]:.2f} / {v[0]:.2f} / {t[0]:.2f} ms, "
            f"bwd {c[1]:.2f} / {v[1]:.2f} / {t[1]:.2f} ms; vectors/circular fwd+bwd {(v[0] + v[1]) / (c[0] + c[1]):.3f}x "
            f"(CPU {(v[2] + v[3]) / (c[2] + c[3]):.3f}x), tilted/circular {(t[0] + t[1]) / (c[0] + c[1]):.3f}x")


def ct_vector_rows(repeat: int, n_voxel: int = 64, n_detector: int = 96, n_views: int = 16) -> list:
    """The voxel projector pair (CT projector forward and its transpose) on one circular scan and
    the same scan as vectors, alternating call by call: lines of medians (ms) and ratios."""
    import numpy as np

    from clgs.geometry import Geometry
    from clgs.ops.ct_projector import CTProjector

    lines = []
    for beam in ("cone", "parallel"):
        g = Geometry.default(n_views=n_views, mode=beam, n_detector=n_detector, n_voxel=n_voxel)
        cases = {"circular": CTProjector(g), "vectors": CTProjector(g.as_vectors())}
        rng = np.random.default_rng(0)
        x = rng.random(g.nVoxel, dtype=np.float32)
        y = rng.random(g.projection_shape, dtype=np.float32)
        times = {k: ([], []) for k in cases}
        for r in range(repeat + 1):
            for name, P in (list(cases.items()) if r % 2 == 0 else list(cases.items())[::-1]):
                t = time.perf_counter()
                P.forward(x)
                tf = time.perf_counter() - t
                t = time.perf_counter()
                P.backward(y)
                tb = time.perf_counter() - t
                if r:
                    times[name][0].append(tf)
                    times[name][1].append(tb)
        c = [_median(t) * 1e3 for t in times["circular"]]
        v = [_median(t) * 1e3 for t in times["vectors"]]
        lines.append(f"CT projector {beam:>8} {n_voxel}^3, {n_views} views of {n_detector}^2: circular / vectors "
                     f"fwd {c[0]:.1f} / {v[0]:.1f} ms, bwd {c[1]:.1f} / {v[1]:.1f} ms; vectors/circular "
                     f"{(v[0] + v[1]) / (c[0] + c[1]):.3f}x")
    return lines


def _time_torch(m, mats, rho, geometry, mode, repeat):
    import torch

    from clgs.reference.projection import project_patches

    m = m.clone().requires_grad_()
    mats = mats.clone().requires_grad_()
    rho = rho.clone().requires_grad_()
    tf, tt = [], []
    for r in range(max(1, repeat)):
        t = time.perf_counter()
        img = project_patches(m, mats, rho, geometry, r % geometry.n_views, mode)
        tf.append(time.perf_counter() - t)
        img.backward(torch.ones_like(img))
        tt.append(time.perf_counter() - t)
    return _median(tf) * 1e3, _median(tt) * 1e3


@click.command()
@click.option("--quick", is_flag=True, help="10k Gaussians only, fewer repeats")
@click.option("--repeat", default=7, show_default=True, help="timed repeats per case (median)")
@click.option("--torch-n", default=5000, show_default=True, help="largest N timed in torch (scaled above)")
@click.option("--stages", is_flag=True, help="also print each kernel's device time and launches per call")
@click.option("--fastest", is_flag=True, help="also print the fastest call of each row (least disturbed on a shared machine)")
@click.option("--widths", "widths", is_flag=True,
              help="also time each case at 8 and at 16 lanes, alternating, and print the ratios")
@click.option("--n", "sizes_opt", type=int, multiple=True, help="numbers of Gaussians (default 10000 and 50000)")
@click.option("--det", "dets_opt", type=click.Choice(["128", "256"]), multiple=True, help="detector sizes (default both)")
@click.option("--beam", "beams_opt", type=click.Choice(["cone", "parallel"]), multiple=True,
              help="beams (default both)")
@click.option("--vectors", is_flag=True,
              help="also time each row's scan written as per-view vectors and with its detector tilted, "
                   "alternating with the circular one, and the CT projector pair both ways")
@device_option
def main(quick, repeat, torch_n, stages, fastest, widths, sizes_opt, dets_opt, beams_opt, vectors, devices):
    """Gaussian projector: ms, evaluations/s, fraction of the exp ceiling, speed-up over torch."""
    results = on_each_device(devices, lambda: _bench(quick, repeat, torch_n, stages, fastest, widths, sizes_opt,
                                                     dets_opt, beams_opt, vectors))
    ratio_table(results, ("fwd ms", "bwd ms"))


def _bench(quick, repeat, torch_n, stages, fastest, widths, sizes_opt, dets_opt, beams_opt, vectors=False):
    """One device's run of :func:`main`; returns {case: (forward ms, backward ms)}."""
    import torch

    from clgs.geometry import Geometry
    from clgs.ops.projector import GaussianProjector
    from clgs.reference.gaussians import covariance, precision

    torch.manual_seed(0)
    watch = HostWatch()
    if quick:
        repeat = min(repeat, 3)
        torch_n = min(torch_n, 2000)
    proj = GaussianProjector()
    wproj = {w: GaussianProjector(w) for w in (8, 16)} if widths else None
    ceiling, ceiling_cpu = _exp_ceiling(proj, max(3, repeat))
    click.echo(f"device exp ceiling (fast_exp{proj.width} probe, the projector's width): {ceiling / 1e9:.2f} G exp/s "
               f"wall, {ceiling_cpu / 1e9:.2f} G exp per CPU-second")
    if proj.width != 8:
        c8, c8_cpu = _exp_ceiling(GaussianProjector(8), max(3, repeat))
        click.echo(f"                   (fast_exp8 probe, for comparison): {c8 / 1e9:.2f} G exp/s wall, "
                   f"{c8_cpu / 1e9:.2f} G exp per CPU-second ({ceiling_cpu / c8_cpu:.2f}x per CPU-second at "
                   f"{proj.width})")
    how = "forced by $CLGS_TILE_WIDTH" if proj.forced else "from the device's native float vector width"
    click.echo(f"vector width {proj.width} ({how}); (render, backward) lanes: "
               + ", ".join(f"{b} {m} {proj.widths(b, m)}" for b in ("cone", "parallel") for m in ("affine", "exact")))
    header = (f"{'N':>6} {'det':>5} {'beam':>8} {'mode':>6} | {'fwd ms':>7} {'bwd ms':>7} "
              f"{'fwd cpu':>7} {'bwd cpu':>7} | {'fwd Geval/s':>11} {'bwd Geval/s':>11} {'exp ceil':>8} | "
              f"{'torch ms':>9} {'x torch':>7} | {'err vs exact':>12} {'exact/affine':>12}")
    click.echo(header)
    click.echo("-" * len(header))
    sizes = list(sizes_opt) or ([10_000] if quick else [10_000, 50_000])
    if any(n <= 0 for n in sizes):
        raise click.BadParameter("numbers of Gaussians must be positive", param_hint="--n")
    dets = [int(d) for d in dets_opt] or [128, 256]
    beams = list(beams_opt) or ["cone", "parallel"]
    figures = {}
    for n in sizes:
        m, s, q, rho = _scene(n)
        cov, prec = covariance(s, q).detach(), precision(s, q).detach()
        for det in dets:
            for beam in beams:
                g = Geometry.default(n_views=16, mode=beam, n_detector=det, n_voxel=128)
                useful = _useful(m, cov, g, 0)
                res = {}
                for mode in ("affine", "exact"):
                    mats = cov if mode == "affine" else prec
                    fwd, bwd, cfwd, cbwd, img, fwd_min, bwd_min = _time_kernels(proj, m, mats, rho, g, mode, repeat)
                    k = min(n, torch_n)
                    t_f, t_fb = _time_torch(m[:k], mats[:k], rho[:k], g, mode, max(1, repeat // 3))
                    t_fb *= n / k
                    res[mode] = (fwd, bwd, img)
                    figures[f"{n} {det}^2 {beam} {mode}"] = (fwd, bwd)
                    frac = useful / (0.5 * (cfwd + cbwd)) * 1e3 / ceiling_cpu
                    line = (f"{n:>6} {det:>4}^2 {beam:>8} {mode:>6} | {fwd:7.2f} {bwd:7.2f} {cfwd:7.2f} {cbwd:7.2f} | "
                            f"{useful / fwd / 1e6:11.2f} {useful / bwd / 1e6:11.2f} {frac:8.0%} | "
                            f"{t_fb:9.1f} {t_fb / (fwd + bwd):7.1f} |")
                    if mode == "exact":
                        a, e = res["affine"][2], img
                        err = float(abs(a - e).max() / max(abs(e).max(), 1e-30))
                        ratio = (fwd + bwd) / (res["affine"][0] + res["affine"][1])
                        line += f" {err:12.2e} {ratio:12.2f}"
                    click.echo(line)
                    if fastest:
                        click.echo(f"    fastest of {repeat} calls: fwd {fwd_min:.2f} ms ({useful / fwd_min / 1e6:.2f} Geval/s), "
                                   f"bwd {bwd_min:.2f} ms ({useful / bwd_min / 1e6:.2f} Geval/s)")
                    if widths:
                        r = _compare_widths(wproj, m, mats, rho, g, mode, repeat)
                        a, b = r[8], r[16]
                        click.echo(f"    8 vs 16 lanes: fwd {a[0]:.2f} / {b[0]:.2f} ms ({a[0] / b[0]:.2f}x), "
                                   f"bwd {a[1]:.2f} / {b[1]:.2f} ms ({a[1] / b[1]:.2f}x); CPU ms: fwd {a[2]:.2f} / "
                                   f"{b[2]:.2f} ({a[2] / b[2]:.2f}x), bwd {a[3]:.2f} / {b[3]:.2f} ({a[3] / b[3]:.2f}x); "
                                   f"16 lanes: {useful / b[0] / 1e6:.2f} / {useful / b[1] / 1e6:.2f} Geval/s")
                    if vectors:
                        click.echo(_vector_rows(proj, m, mats, rho, g, mode, repeat))
                    if stages:
                        ms, launches, outside = _stages(proj, m, mats, rho, g, mode, repeat)
                        for ph in ("fwd", "bwd"):
                            parts = ", ".join(f"{k} {v:.2f}" for k, v in ms[ph].items())
                            click.echo(f"    {ph}: {launches[ph]} kernel launch(es); device ms: {parts} "
                                       f"(sum {sum(ms[ph].values()):.2f}); outside the kernels {outside[ph]:.2f}")
    scaled = f" (torch on the first {torch_n} Gaussians, time scaled by N/{torch_n})"
    click.echo(f"useful evaluations: pixels within 3 sigma, summed over Gaussians; torch = fwd + autograd bwd{scaled}")
    if vectors:
        for line in ct_vector_rows(repeat):
            click.echo(line)
    click.echo(watch.summary())
    if sizes_opt or dets_opt or beams_opt:
        return figures  # a restricted run: the projector cases only
    try:
        from clgs.bench import voxelizer_rows
    except ImportError:
        return figures
    click.echo("")
    click.echo("voxelizer:")
    for row in voxelizer_rows.rows(quick):
        click.echo("  " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    from clgs.bench import field_sample_rows

    click.echo("")
    click.echo("deformation (shape model's exp(v) on a 64x33x38 grid; OpenCL ms, torch grid_sample ref_ms):")
    for row in field_sample_rows.rows(quick):
        click.echo("  " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    return figures
