"""``clgs info``: the OpenCL devices, the one clgs chose, and library versions."""
import click


@click.command()
def info():
    """Print OpenCL platforms and devices, the chosen device and versions.

    Exits with status 1 when no device can run clgs's kernels (or the one asked for with
    --device / CLGS_DEVICE cannot), so a set-up script stops there."""
    from clgs import runtime

    click.echo(f"clgs {__import__('clgs').__version__}")
    click.echo(runtime.describe())
    try:
        runtime.device()
    except runtime.NoOpenCLDevice:  # the reason is printed above
        raise click.ClickException("no OpenCL device to run on (the reason is above)") from None
