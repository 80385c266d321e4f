"""``clgs bench scaling``: how an R2-Gaussian-mode training iteration grows with the number of
Gaussians and with the detector, against the linear growth the work would give.

An iteration's work is linear in the Gaussians (set-up, covariances, Adam, the TV patch's cull)
and, for the projection, in the pixels each Gaussian covers; so at a fixed detector the time
should follow ``a + b N`` and at a fixed N grow with the pixel count. The command times the same
iteration as ``clgs bench train`` on the same synthetic scene over a range of N (at 256^2) and of
detector sizes (at 50k Gaussians), fits the line to the N series by least squares, prints both
series with the fit, and draws them (``--out``).
"""
from __future__ import annotations

import click

from .devices import device_option, on_each_device
from .host import HostWatch


def _time_iteration(n, det, views, iterations, seed):
    from .train import r2gs_trainer, synthetic_scene, time_steps

    # the Gaussians keep their size in mm (as sized for 256^2): a finer detector sees each of them
    # on more pixels, as it would a real object
    geo, scan, gaussians = synthetic_scene(n, det, 128, views, "cone", seed, sized_for=256)
    trainer = r2gs_trainer(scan, gaussians, "cl", seed)
    return time_steps(trainer, iterations, warmup=3)


@click.command()
@click.option("--gaussians", "sizes", type=int, multiple=True,
              help="numbers of Gaussians [default: 10k, 25k, 50k, 100k, 200k, 400k]")
@click.option("--detectors", "dets", type=int, multiple=True, help="detector sizes [default: 128, 256, 384, 512]")
@click.option("--iterations", default=20, show_default=True, type=click.IntRange(min=1))
@click.option("--views", default=10, show_default=True, type=click.IntRange(min=1))
@click.option("--out", "-o", "plot", type=click.Path(dir_okay=False), default=None, help="write the plot here (PNG)")
@click.option("--seed", default=0, show_default=True)
@device_option
def main(sizes, dets, iterations, views, plot, seed, devices):
    """Time per training iteration against the number of Gaussians and the detector size."""
    on_each_device(devices, lambda: _bench(sizes, dets, iterations, views, plot, seed))


def _bench(sizes, dets, iterations, views, plot, seed):
    import numpy as np

    from clgs import runtime

    from .train import peak_memory_mib

    sizes = sorted(sizes or (10_000, 25_000, 50_000, 100_000, 200_000, 400_000))
    dets = sorted(dets or (128, 256, 384, 512))
    if min(sizes) <= 0 or min(dets) <= 0:
        raise click.BadParameter("sizes must be positive")
    watch = HostWatch()
    click.echo(f"device: {runtime.device_label()}; R2-Gaussian-mode iteration (bench train's scene), "
               f"{iterations} timed iterations per point")
    by_n = []
    for n in sizes:
        t = _time_iteration(n, 256, views, iterations, seed)
        by_n.append(t)
        click.echo(f"  N {n:>7d}, 256^2: {t * 1e3:8.2f} ms / it   (peak memory so far {peak_memory_mib():.0f} MiB)")
    b, a = np.polyfit(np.asarray(sizes, float), np.asarray(by_n), 1)
    click.echo(f"linear fit over N: {a * 1e3:.2f} ms + {b * 1e6:.3f} ms per 1000 Gaussians; worst departure "
               + f"{max(abs(t - (a + b * n)) / t for n, t in zip(sizes, by_n)):.0%}")
    by_det = []
    for det in dets:
        t = _time_iteration(50_000, det, views, iterations, seed)
        by_det.append(t)
        click.echo(f"  N   50000, {det}^2: {t * 1e3:8.2f} ms / it   (peak memory so far {peak_memory_mib():.0f} MiB)")
    px = np.asarray(dets, float) ** 2
    bd, ad = np.polyfit(px, np.asarray(by_det), 1)
    click.echo(f"linear fit over pixels: {ad * 1e3:.2f} ms + {bd * 1e3 * 65536:.3f} ms per 256^2 pixels")
    click.echo(f"peak resident memory of this process: {peak_memory_mib():.0f} MiB")
    click.echo(watch.summary())
    if plot:
        _plot(plot, sizes, by_n, (a, b), dets, by_det, (ad, bd))
        click.echo(f"plot: {plot}")
    return {f"N {n}": (t * 1e3,) for n, t in zip(sizes, by_n)}


def _plot(path, sizes, by_n, fit_n, dets, by_det, fit_d):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from clgs.io import atomic

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    x = np.asarray(sizes, float)
    ax1.plot(x / 1e3, np.asarray(by_n) * 1e3, "o-", label="measured")
    xs = np.linspace(0, x.max(), 50)
    ax1.plot(xs / 1e3, (fit_n[0] + fit_n[1] * xs) * 1e3, "--", label="linear fit")
    ax1.set_xlabel("Gaussians (thousands), 256^2 detector")
    ax1.set_ylabel("ms per iteration")
    ax1.legend()
    ax2.plot(dets, np.asarray(by_det) * 1e3, "o-", label="measured")
    ds = np.linspace(min(dets), max(dets), 50)
    ax2.plot(ds, (fit_d[0] + fit_d[1] * ds ** 2) * 1e3, "--", label="linear in pixels")
    ax2.set_xlabel("detector side (pixels), 50k Gaussians")
    ax2.legend()
    fig.tight_layout()
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
