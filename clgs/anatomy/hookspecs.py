"""The hooks a clgs plugin implements (pluggy project ``clgs``; mark each with ``hookimpl``).

Two entry-point groups, one per kind of plugin (a package may declare both, pointing at the same
module): ``clgs.anatomies`` (loaded by :mod:`clgs.anatomy.plugins`) for ``clgs_anatomies``,
``register_commands`` and ``register_anatomy_commands``; ``clgs.methods`` (loaded by
:mod:`clgs.methods`) for ``register_methods``. docs/plugins.md is the author's guide."""
import pluggy

PROJECT = "clgs"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def clgs_anatomies():
    """Return a list of :class:`clgs.anatomy.Anatomy` objects this plugin provides.

    Keep it cheap: build the objects, do not load their data (loaders are lazy)."""


@hookspec
def register_commands(cli):
    """Add click commands to the root command ``clgs`` (``cli``, a click group): e.g.
    ``cli.add_command(my_command)``. A name taken by a built-in command or an anatomy is refused
    (a warning) and the command left out."""


@hookspec
def register_anatomy_commands(anatomy, group):
    """Add click commands to the group ``clgs <anatomy.name>`` (``group``) of ``anatomy`` (an
    :class:`clgs.anatomy.Anatomy`, any plugin's: check ``anatomy.name``). A name taken by a
    generic anatomy command is refused (a warning) and the command left out."""


@hookspec
def clgs_methods():
    """Deprecated (entry-point group ``clgs.anatomies``): return :class:`clgs.methods.Method`
    records. Use ``register_methods`` in the group ``clgs.methods`` instead."""


@hookspec
def register_methods(register):
    """Register reconstruction methods (entry-point group ``clgs.methods``): call
    ``register(clgs.methods.Method(...))`` for each; ``register.lazy(name, module, help)`` declares
    one whose module is imported when the method is first used. Keep it cheap: give ``run`` and
    ``options`` as ``"module:attr"`` strings, imported only when the method is chosen."""
