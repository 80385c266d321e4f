"""Plain torch references of the kernels, for tests and benchmarks.

* ``projection``: the Gaussian projector (dense first-principles reference, ray quadrature, and
  the patch-based torch version the kernel benchmark times).
* ``voxelization``: the voxelizer.
* ``detector``: bilinear sampling of a detector image (the backprojectors' reference).
* ``gaussians``: a Gaussian's covariance and precision from its scale and rotation in torch (the
  definition the kernels are checked against, and the autograd path of ``clgs.ops.projector``).

Imports nothing of clgs but its own modules (it sits below :mod:`clgs.runtime` and
:mod:`clgs.ops`). Used by the operators' torch wrappers, tests, benchmarks, the torch backend of
:mod:`clgs.fit` and :mod:`clgs.shape`.
"""
