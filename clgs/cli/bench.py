"""``clgs bench``: benchmarks that print figures (never timed tests).

``clgs bench`` alone runs the kernel benchmark; ``clgs bench ct`` and ``clgs bench train`` the others.
Each benchmark lives in ``clgs.bench.<name>`` and exposes a click command ``main``.
"""
import importlib

import click

BENCHMARKS = {
    "kernels": ("clgs.bench.kernels", "Gaussian projector and voxelizer: ms, evaluations/s, speed-up over torch"),
    "ct": ("clgs.bench.ct", "FDK and SART: wall time and quality at 5-50 views; against scikit-image"),
    "tv-patch": ("clgs.bench.tv_patch", "TV patch: the fused device pass against the unfused path, same patches"),
    "train": ("clgs.bench.train", "training iterations per second against the same iteration in torch"),
    "scaling": ("clgs.bench.scaling", "time per training iteration against the Gaussians and the detector size"),
    "iteration-cost": ("clgs.bench.iteration_cost", "ms per iteration on a trained run's Gaussians: its settings "
                       "against variants"),
    "quality-time": ("clgs.bench.quality_time", "time to each quality level: the fast schedule against the paper's"),
    "cohort": ("clgs.bench.cohort", "time and peak memory per cohort task; runs per minute with 1 and 2 workers"),
}


class _BenchGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(BENCHMARKS)

    def get_command(self, ctx, name):
        if name not in BENCHMARKS:
            return None
        return importlib.import_module(BENCHMARKS[name][0]).main


@click.group(cls=_BenchGroup, invoke_without_command=True)
@click.pass_context
def bench(ctx):
    """Print benchmark figures (default: the kernel benchmark)."""
    if ctx.invoked_subcommand is None:
        ctx.invoke(_BenchGroup().get_command(ctx, "kernels"))
