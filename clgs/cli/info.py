"""``clgs info``: the OpenCL devices, the one clgs chose, and library versions."""
import click


@click.command()
def info():
    """Print OpenCL platforms and devices, the chosen device and versions."""
    from clgs import runtime

    click.echo(f"clgs {__import__('clgs').__version__}")
    click.echo(runtime.describe())
