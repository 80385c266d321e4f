"""Classical CT on OpenCL: a matched voxel projector pair, FDK/FBP, SART/OS-SART, the acquisition
noise model and analytic phantoms.

* :class:`clgs.ops.ct_projector.CTProjector` - ``forward(volume, views=None)`` (Joseph's method) and
  ``backward(projections, views=None)`` (its exact transpose, a gather);
* :func:`clgs.ct.fdk.fdk` - FDK for cone beam, FBP for parallel beam, short-scan weights, on a
  circular or a per-view geometry (:mod:`clgs.ct.fdk_views` reads the orbit off the views);
* :func:`clgs.ct.sart.sart` - SART and OS-SART;
* :func:`clgs.ct.noise.add_noise` - Poisson + electronic noise + scatter, as TIGRE's model;
* :mod:`clgs.ct.phantoms` - ellipsoid phantoms with exact line integrals.

Import the submodules directly; this package imports nothing heavy on its own.

May import: :mod:`clgs.ops`, :mod:`clgs.runtime`, :mod:`clgs.io`, :mod:`clgs.geometry`. Not fit,
methods or the CLI.
"""
