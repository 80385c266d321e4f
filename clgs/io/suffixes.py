"""File suffixes of the volume formats clgs reads and writes (no imports: the command line checks
paths with them before anything heavy loads)."""

VOLUME_SUFFIXES = (".npy", ".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr", ".dcm")
ITK_SUFFIXES = (".mha", ".mhd", ".nrrd", ".nhdr")
