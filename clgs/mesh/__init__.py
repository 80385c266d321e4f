"""Surfaces and volumes: meshes to labels and signed distances (:mod:`.voxels`), iso-surfaces and
surface distances (:mod:`.surface`). NumPy, SciPy, scikit-image and trimesh only.

May import: :mod:`clgs.io`, :mod:`clgs.geometry`, :mod:`clgs.errors`.
"""
