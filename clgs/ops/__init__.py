"""The OpenCL operators, one module per kernel file, with their torch autograd functions.

``cl/projector.cl`` <-> :mod:`.projector` (Gaussian X-ray projector), ``cl/voxelizer.cl`` <->
:mod:`.voxelizer` (Gaussian field on a grid or at points), ``cl/ssim.cl`` <-> :mod:`.ssim` (fused
L1 + SSIM image loss), ``cl/field_sampler.cl`` <-> :mod:`.field_sampler` (trilinear sampling of
vector fields), ``cl/ct_projector.cl`` and its transpose ``cl/ct_backprojector.cl`` <->
:mod:`.ct_projector` (voxel volume projector pair), ``cl/fdk.cl`` <-> :mod:`.fdk` (FDK/FBP
backprojection). :mod:`.gaussian_math` holds the covariance algebra they share.

May import: :mod:`clgs.runtime`, :mod:`clgs.geometry`, :mod:`clgs.errors`. Nothing higher.
"""
