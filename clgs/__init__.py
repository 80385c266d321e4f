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
Classical CT
    ``fdk``, ``sart``, ``add_noise``.
Gaussian methods
    ``reconstruct_r2gs`` (R2-Gaussian), ``reconstruct_shape_guided`` (with an anatomy's shape model).
Figures and anatomies
    ``metrics`` (3D PSNR / SSIM, surface distance), ``plugins`` (installed anatomies:
    ``get_anatomy``, ``anatomy_names``), ``get_anatomy``, ``Anatomy``.
Errors
    ``ClgsError``: the base of every error clgs raises about its input.
"""
import importlib as _importlib
import os as _os

# torch's OpenMP threads spin for a while after every parallel op by default and starve PoCL's
# worker threads on the same cores (a 32^3 voxelizer block: 22-325 ms with spinning, 6-7 ms
# without); ask them to sleep instead. Read when torch loads, so it is set here, first.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"

# public name -> "module" (the name is an attribute of it) or "module:" (the name is the module)
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
    "reconstruct_r2gs": "clgs.methods.r2gs",
    "reconstruct_shape_guided": "clgs.methods.shape_guided",
    "metrics": "clgs.metrics:",
    "plugins": "clgs.anatomy.plugins:",
    "get_anatomy": "clgs.anatomy.plugins",
    "Anatomy": "clgs.anatomy.record",
    "ClgsError": "clgs.errors",
}

__all__ = sorted(_HOMES)


def __getattr__(name):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'clgs' has no attribute {name!r}")
    module_name, is_module, _ = home.partition(":")
    module = _importlib.import_module(module_name)
    value = module if is_module else getattr(module, name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOMES))
