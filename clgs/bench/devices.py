"""``--device`` for the benchmarks: one run per named device, in one process, so that OpenCL
implementations are compared side by side (same machine state, same scenes), then the ratios."""
from __future__ import annotations

import click


def device_option(f):
    return click.option(
        "--device", "devices", multiple=True, metavar="SPEC",
        help="OpenCL device (P:D or a piece of its name, as 'clgs info' lists them); repeat it to run "
             "the benchmark on each in turn in one process and print the ratios. Default: the "
             "automatic choice.")(f)


def on_each_device(devices, run):
    """``run()`` once per device in ``devices`` (default: the current one); [(label, result)]."""
    from clgs import runtime

    specs = list(devices) or [None]
    out = []
    for spec in specs:
        dev = runtime.use_device(spec) if spec is not None else runtime.device()
        label = runtime.device_label(dev)
        click.echo(f"== device: {label}")
        out.append((label, run()))
        click.echo("")
    return out


def ratio_table(results, columns) -> None:
    """Print each result's figures (dict: row -> tuple of numbers named by ``columns``) for every
    device, and each later device's ratio to the first."""
    if len(results) < 2:
        return
    (_, base), others = results[0], results[1:]
    click.echo("side by side (same run): " + "; ".join(f"[{i}] {label}" for i, (label, _) in enumerate(results)))
    head = f"{'case':34s}" + "".join(f"{c + f' [{i}]':>14s}" for c in columns for i in range(len(results)))
    head += "".join(f"{c + f' [{i}]/[0]':>16s}" for c in columns for i in range(1, len(results)))
    click.echo(head)
    for row, figs in base.items():
        if not all(row in r for _, r in others):
            continue
        line = f"{str(row):34s}"
        for j in range(len(columns)):
            line += "".join(f"{r[row][j]:14.2f}" for _, r in results)
        for j in range(len(columns)):
            line += "".join(f"{r[row][j] / figs[j] if figs[j] else float('nan'):16.2f}" for _, r in others)
        click.echo(line)
