"""The hooks an anatomy plugin implements (pluggy, entry-point group ``clgs.anatomies``)."""
import pluggy

PROJECT = "clgs"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def clgs_anatomies():
    """Return a list of :class:`clgs.anatomy.Anatomy` objects this plugin provides.

    Keep it cheap: build the objects, do not load their data (loaders are lazy)."""
