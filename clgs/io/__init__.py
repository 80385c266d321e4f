"""Reading and writing scans, volumes and meshes.

* :mod:`clgs.io.atomic`: every file and folder clgs writes goes through here (temp + rename), so
  an interrupted run never leaves a half-written output behind.
* :mod:`clgs.io.scan`: the clgs scan folder (``scan.json`` + ``projections.npy`` + optional truth);
  ``Scan.load`` also reads R2-Gaussian dataset folders (:mod:`clgs.io.r2gaussian`).
* :mod:`clgs.io.volume`: volumes as ``.npy``, NIfTI, MetaImage, NRRD or DICOM series, kept where
  they lie in the world.
* :mod:`clgs.io.units`: Hounsfield units to attenuation and back, at a stated energy.
* :mod:`clgs.io.mesh`: surface meshes (STL, PLY, OBJ written in LPS with Slicer's tag; npz);
  untagged files read as LPS with a warning, or in the frame the caller names.
* :mod:`clgs.io.dicom`: volumes out as a DICOM CT series (pydicom), oriented as scanners write it;
  :mod:`clgs.io.dicom_identity`: the patient, study and frame of reference a series belongs to.

Submodules are imported on demand; this package stays light.

May import: :mod:`clgs.geometry` and :mod:`clgs.errors` only (every other layer reads and writes
through here).
"""
