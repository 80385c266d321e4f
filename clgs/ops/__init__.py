"""The OpenCL operators, one module per kernel file, with their torch autograd functions.

``cl/projector.cl`` <-> :mod:`.projector` (Gaussian X-ray projector), ``cl/voxelizer.cl`` <->
:mod:`.voxelizer` (Gaussian field on a grid or at points), ``cl/tv_patch.cl`` <-> :mod:`.tv_patch`
(fused TV of the field on a patch), ``cl/ssim.cl`` <-> :mod:`.ssim` (fused L1 + SSIM image loss),
``cl/field_sampler.cl`` <-> :mod:`.field_sampler` (trilinear sampling of vector fields),
``cl/ct_projector.cl`` and its transpose ``cl/ct_backprojector.cl`` <-> :mod:`.ct_projector` (voxel
volume projector pair), ``cl/fdk.cl`` <-> :mod:`.fdk` (FDK/FBP backprojection). Every operator
class follows :class:`clgs.runtime.Operator` (docs/layout.md, "Operator contract"). Besides them
only host-side code that operators alone use: :mod:`.ct_upright` (the CT projector's upright
stand-in for tilted detectors) and :mod:`.sorting` (the gather orders of the voxelizer and the
field sampler).

May import: :mod:`clgs.runtime`, :mod:`clgs.reference` (the covariance algebra),
:mod:`clgs.metrics`, :mod:`clgs.geometry`, :mod:`clgs.errors`. Nothing higher.
"""
