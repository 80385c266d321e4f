"""``clgs anatomies``: the installed anatomy plugins and where their models live."""
import os

import click


@click.command()
@click.option("--json", "as_json", is_flag=True, help="machine-readable output")
def anatomies(as_json):
    """List installed anatomies: name, summary, version, package, model file and whether it is built."""
    from clgs.anatomy import plugins

    found = plugins.anatomies()
    rows = []
    for name, a in found.items():
        path = a.model_path
        built, problem = bool(path) and os.path.exists(path), None
        if built:
            from clgs.shape.model import ModelFileError, read_metadata

            try:
                read_metadata(path)
            except ModelFileError as exc:
                built, problem = False, str(exc)
        rows.append({"name": name, "summary": a.summary, "version": a.version, "package": a.package,
                     "model_path": path, "built": built, "problem": problem})
    if as_json:
        import json

        click.echo(json.dumps(rows, indent=1))
        return
    if not rows:
        click.echo("no anatomy plugins installed (entry-point group 'clgs.anatomies'); "
                   "see examples/toy_plugin for how to write one")
        return
    for r in rows:
        state = "built" if r["built"] else ("unreadable" if r["problem"] else "not built")
        click.echo(f"{r['name']:12s} {r['summary']}")
        click.echo(f"{'':12s} package {r['package']} {r['version']}; model ({state}): {r['model_path'] or '-'}")
        if r["problem"]:
            click.echo(f"{'':12s} {r['problem']}")
