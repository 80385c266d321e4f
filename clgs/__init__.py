"""clgs: sparse-view X-ray 3D reconstruction with Gaussian splatting and statistical shape priors.

The public Python API is the names below, read as ``clgs.NAME`` or ``from clgs import NAME``.
Each is loaded from its home module on first use, so ``import clgs`` (and the command line) stays
light: nothing imports torch or pyopencl until a name that needs them is asked for.

Data
    ``Scan`` (projections, geometry, optional truth; ``Scan.load`` reads clgs and R2-Gaussian
    folders), ``Geometry`` (TIGRE's names), ``Grid``, ``load_volume``, ``save_volume``.
Kernels (differentiable torch ops on OpenCL)
    ``project`` (Gaussians -> line integrals), ``voxelize``, ``voxelize_points``, ``CTProjector``
    (voxel volume projector pair).
Simulation and units
    ``simulate`` (a volume, 1/mm or HU, -> a noisy sparse-view ``Scan``, projected from a finer
    grid than the reconstruction's; also ``simulate_scan``), ``add_noise``, ``hu_to_mu``,
    ``mu_to_hu``.
Classical CT
    ``fdk``, ``sart``.
Gaussian methods
    ``reconstruct_r2gs`` (R2-Gaussian), ``reconstruct_shape_guided`` (with an anatomy's shape model).
Any registered method
    ``run_method`` (a method by name, its settings checked: the one way the command line, batches
    and experiments run one).
Figures and anatomies
    ``metrics`` (3D PSNR / SSIM, surface distance), ``plugins`` (installed anatomies:
    ``get_anatomy``, ``anatomy_names``), ``get_anatomy``, ``Anatomy``.
Errors
    ``ClgsError``: the base of every error clgs raises about its input.
"""
import importlib as _importlib
from typing import TYPE_CHECKING as _TYPE_CHECKING

__version__ = "0.1.0"

# public name -> "module" (the name is an attribute of it), "module:" (the name is the module) or
# "module:attribute" (the name is another attribute of it)
_HOMES = {
    "Scan": "clgs.io.scan",
    "Geometry": "clgs.geometry",
    "Grid": "clgs.geometry",
    "load_volume": "clgs.io.volume",
    "save_volume": "clgs.io.volume",
    "project": "clgs.ops.projector",
    "voxelize": "clgs.ops.voxelizer",
    "voxelize_points": "clgs.ops.voxelizer",
    "CTProjector": "clgs.ops.ct_projector",
    "fdk": "clgs.ct.fdk",
    "sart": "clgs.ct.sart",
    "add_noise": "clgs.ct.noise",
    "simulate": "clgs.ct.simulate:simulate_scan",
    "simulate_scan": "clgs.ct.simulate",
    "hu_to_mu": "clgs.io.units",
    "mu_to_hu": "clgs.io.units",
    "reconstruct_r2gs": "clgs.methods.r2gs",
    "reconstruct_shape_guided": "clgs.methods.shape_guided",
    "run_method": "clgs.methods.run",
    "metrics": "clgs.metrics:",
    "plugins": "clgs.anatomy.plugins:",
    "get_anatomy": "clgs.anatomy.plugins",
    "Anatomy": "clgs.anatomy.record",
    "ClgsError": "clgs.errors",
}

__all__ = sorted(_HOMES)  # noqa: PLE0605 - a list, built from the table above

if _TYPE_CHECKING:  # what the lazy loading below gives, spelled out for type checkers and editors
    from clgs import metrics, plugins  # noqa: F401
    from clgs.anatomy.plugins import get_anatomy  # noqa: F401
    from clgs.anatomy.record import Anatomy  # noqa: F401
    from clgs.ct.fdk import fdk  # noqa: F401
    from clgs.ct.noise import add_noise  # noqa: F401
    from clgs.ct.sart import sart  # noqa: F401
    from clgs.ct.simulate import simulate_scan  # noqa: F401
    from clgs.ct.simulate import simulate_scan as simulate  # noqa: F401
    from clgs.errors import ClgsError  # noqa: F401
    from clgs.geometry import Geometry, Grid  # noqa: F401
    from clgs.io.scan import Scan  # noqa: F401
    from clgs.io.units import hu_to_mu, mu_to_hu  # noqa: F401
    from clgs.io.volume import load_volume, save_volume  # noqa: F401
    from clgs.methods.r2gs import reconstruct_r2gs  # noqa: F401
    from clgs.methods.run import run_method  # noqa: F401
    from clgs.methods.shape_guided import reconstruct_shape_guided  # noqa: F401
    from clgs.ops.ct_projector import CTProjector  # noqa: F401
    from clgs.ops.projector import project  # noqa: F401
    from clgs.ops.voxelizer import voxelize, voxelize_points  # noqa: F401


def __getattr__(name):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'clgs' has no attribute {name!r}")
    module_name, colon, attr = home.partition(":")
    module = _importlib.import_module(module_name)
    value = getattr(module, attr or name) if not colon or attr else module
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOMES))
