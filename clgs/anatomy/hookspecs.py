"""The hooks a clgs plugin implements (pluggy, entry-point group ``clgs.anatomies``): the anatomies it
provides, and the reconstruction methods it provides; a plugin may implement either or both."""
import pluggy

PROJECT = "clgs"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def clgs_anatomies():
    """Return a list of :class:`clgs.anatomy.Anatomy` objects this plugin provides.

    Keep it cheap: build the objects, do not load their data (loaders are lazy)."""


@hookspec
def clgs_methods():
    """Return a list of :class:`clgs.methods.Method` records (reconstruction methods) this plugin
    provides. Keep it cheap: give ``run`` and ``options`` as ``"module:attr"`` strings, imported
    only when the method is chosen."""
