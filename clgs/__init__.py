"""clgs: sparse-view X-ray 3D reconstruction with Gaussian splatting and statistical shape priors.

Import submodules directly (``clgs.geometry``, ``clgs.ops``, ...); this package keeps its own
import light so that the command line starts fast.
"""
import os as _os

# torch's OpenMP threads spin for a while after every parallel op by default and starve PoCL's
# worker threads on the same cores (a 32^3 voxelizer block: 22-325 ms with spinning, 6-7 ms
# without); ask them to sleep instead. Read when torch loads, so it is set here, first.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
