"""clgs's own reconstruction methods, registered through the same hook a method plugin implements
(``register_methods``, :mod:`clgs.anatomy.hookspecs`); :mod:`clgs.methods` registers this module
in-process. Nothing heavy is imported: ``run`` and ``options`` are ``"module:attr"`` strings, and
R2-Gaussian and the shape-guided method are declared by module (imported when chosen)."""
from clgs.anatomy.hookspecs import hookimpl
from clgs.ct.filter_names import FILTERS as _FILTERS
from clgs.limits import MAX_ITERATIONS


@hookimpl
def register_methods(register):
    from clgs.methods.registry import Method, Option

    register(Method(
        "fdk", "clgs.methods.fdk:run", help="FDK filtered backprojection (fast, streaky at few views)",
        options=[
            Option("--filter", "filter", "choice", "FDK ramp filter window", default="ram-lak", choices=_FILTERS),
            Option("--short-scan", "short_scan", "choice",
                   "redundancy (Parker-like) weights for arcs short of a full circle", default="auto",
                   choices=("auto", "on", "off")),
        ],
    ))
    register(Method(
        "sart", "clgs.methods.sart:run", help="SART / OS-SART iterative reconstruction (non-negative)",
        options=[
            Option("--iterations", "iterations", "int", "number of SART iterations (full passes over the views)",
                   min=1, max=MAX_ITERATIONS),
            Option("--subsets", "subsets", "int", "ordered subsets per iteration (1 = SART, more = OS-SART)", min=1,
                   max=MAX_ITERATIONS),
            Option("--relaxation", "relaxation", "float", "relaxation factor of each update, in (0, 2)", min=0,
                   max=2, min_open=True, max_open=True),
        ],
    ))
    register.lazy("r2gs", "clgs.methods.r2gs",
                  help="R2-Gaussian: radiative Gaussian splatting (slow, best at few views)")
    register.lazy("shape", "clgs.methods.shape_guided",
                  help="shape-guided Gaussian splatting with an anatomy's shape model and density atlas")
