"""Classical CT: a matched voxel projector pair, FDK/FBP, SART/OS-SART, the acquisition noise
model and analytic phantoms. Import the submodules (``clgs.ct.fdk`` ...) directly; this package
imports nothing heavy on its own."""
