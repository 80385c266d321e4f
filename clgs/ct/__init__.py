"""Classical CT on OpenCL: a matched voxel projector pair, FDK/FBP, SART/OS-SART, the acquisition
noise model and analytic phantoms.

* :class:`clgs.ct.projector.CTProjector` - ``forward(volume, views=None)`` (Joseph's method) and
  ``backward(projections, views=None)`` (its exact transpose, a gather);
* :func:`clgs.ct.fdk.fdk` - FDK for cone beam, FBP for parallel beam, short-scan weights;
* :func:`clgs.ct.sart.sart` - SART and OS-SART;
* :func:`clgs.ct.noise.add_noise` - Poisson + electronic noise + scatter, as TIGRE's model;
* :mod:`clgs.ct.phantoms` - ellipsoid phantoms with exact line integrals.

Import the submodules directly; this package imports nothing heavy on its own.
"""


def check_projections(projections, geometry, who: str):
    """``projections`` as an array after the checks every reconstruction needs: a Geometry,
    shape (n_views, V, U) with at least one view matching it, finite values. ``who`` names the
    caller in the errors."""
    import numpy as np

    from clgs.geometry import Geometry

    if not isinstance(geometry, Geometry):
        raise TypeError(f"{who} needs a clgs.geometry.Geometry, got {type(geometry).__name__}")
    p = np.asarray(projections)
    if p.ndim != 3 or p.shape[0] == 0:
        raise ValueError(f"projections must be (n_views, V, U) with at least one view, got shape {p.shape}")
    if p.shape != geometry.projection_shape:
        raise ValueError(f"projections have shape {p.shape}, the geometry expects {geometry.projection_shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("projections contain NaN or Inf values; clean or mask them before reconstructing")
    return p

