"""Reconstruction methods that ``clgs reconstruct --method NAME`` can run.

A :class:`Method` has a ``name``, a ``run`` callable ``run(scan, out_dir, **options) -> dict``
(the dict holds at least ``"volume"``: (Z, Y, X) float32 in the scan's units, 1/mm; optionally
``"files"`` it wrote and ``"info"`` figures for the report), its ``options`` (:class:`Option`
records, or click parameters) and, for a method with a settings dataclass, its ``config`` (the
fields listed in its ``CLI`` are options too), and a one-line ``help``. ``out_dir`` is a folder
the method may fill with extra outputs, or None when the user asked for a single volume file.
Options left unset on the command line are not passed, so the callable's own defaults apply;
one exception: a resumed run (``--resume`` given) of a method with an ``iterations`` option gets
``iterations=None`` when ``--iterations`` is not given, meaning "the iterations the interrupted
run was started with", never a new-run default.

Registering a method from another clgs module or a script (a plugin uses the hook below)::

    from clgs.methods import Method, register
    register(Method("mine", run="mypkg.recon:run", options="mypkg.recon:OPTIONS", help="..."))

``run`` and ``options`` may be given as ``"module:attr"`` strings; they are imported only when that
method is chosen, so listing methods stays fast. A method known only by name can be registered
lazily with :func:`register_lazy` (``module`` is imported on first use and must register it, or
expose it as ``METHOD``); R2-Gaussian (``r2gs``) is declared that way, from :mod:`clgs.methods.r2gs`.
Installed plugins provide methods through their own entry-point group, ``clgs.methods``: the
object it names implements the pluggy hook ``register_methods(register)`` (see
:mod:`clgs.anatomy.hookspecs` and docs/plugins.md). The built-in methods come through the same
hook, from :mod:`.builtin`, registered in-process when this package is imported; the plugins'
are loaded when a method is first looked up (:mod:`.registry`). The older hook ``clgs_methods()``
in the group ``clgs.anatomies`` still works (deprecated).

One module per built-in method (:mod:`.fdk`, :mod:`.sart`, :mod:`.r2gs`, :mod:`.shape_guided`),
each thin: the work is in :mod:`clgs.ct` and :mod:`clgs.fit`. The command line makes the click
options (:mod:`clgs.cli.options`); this package imports neither click nor anything heavy.

May import: :mod:`clgs.fit`, :mod:`clgs.shape`, :mod:`clgs.anatomy`, :mod:`clgs.ct` and every
layer below them. Not the experiment or the CLI.
"""
from clgs.methods import builtin, registry
from clgs.methods.registry import (
    GROUP,
    Method,
    MethodError,
    Option,
    Registrar,
    describe,
    get,
    manager,
    names,
    register,
    register_lazy,
)
from clgs.methods.run import accepted_settings, check_method_settings, run_method

__all__ = ["Method", "Option", "register", "register_lazy", "get", "names", "describe", "MethodError", "GROUP",
           "Registrar", "manager", "run_method", "accepted_settings", "check_method_settings"]

# the registry's state, for tests that patch it (the dicts are shared)
_REGISTRY, _LAZY = registry._REGISTRY, registry._LAZY

manager().register_plugin(builtin, name="clgs", package="clgs")  # the built-ins, through the same hook
