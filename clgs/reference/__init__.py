"""Plain torch references of the kernels, for tests and benchmarks.

* ``projection``: the Gaussian projector (dense first-principles reference, ray quadrature, and
  the patch-based torch version the kernel benchmark times).
* ``voxelization``: the voxelizer.
* ``detector``: bilinear sampling of a detector image (the backprojectors' reference).

May import: :mod:`clgs.ops` (the covariance algebra) and below. Used by tests, benchmarks, the
torch backend of :mod:`clgs.fit` and :mod:`clgs.shape`.
"""
