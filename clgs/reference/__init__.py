"""Plain torch references of the kernels, for tests and benchmarks.

* ``projection``: the Gaussian projector (dense first-principles reference, ray quadrature, and
  the patch-based torch version the kernel benchmark times).
* ``voxelization``: the voxelizer.
"""
