"""clgs: sparse-view X-ray 3D reconstruction with Gaussian splatting and statistical shape priors.

Import submodules directly (``clgs.geometry``, ``clgs.ops``, ...); this package keeps its own
import light so that the command line starts fast.
"""
__version__ = "0.1.0"
