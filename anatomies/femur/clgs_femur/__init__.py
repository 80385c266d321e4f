"""clgs anatomy plugin: the left femur, from the 26 real surfaces of LLP26.

Data: ``data/femur_left_LLP26_subjectNN.npz`` (NN = 00..25, vertex correspondence), from the
PyPI package ``musculoskeletal-models`` 0.2.4 (Auckland Bioengineering Institute), MPL-2.0: see
``data/LLP26_README.md`` and ``data/LICENSE-MPL-2.0.txt``. Subjects 00-19 build the shape model
and the density atlas; 20-25 are held out for testing and never enter the model.

Template: the vertex-wise mean of subjects 00-19. The shipped ``femur_left_LLP26_mean.npz`` is
the mean of all 26 (its vertices are a permutation of the 26-subject mean, within 1e-4 mm), so
it includes the held-out subjects and is not used for the model (kept for reference only).

Frame: LLP26's frame shifted by ``FRAME_OFFSET`` so that the CT grid is centred on the scanner's
rotation axis (x, y in the axial plane, z along the leg; -y is anterior).

CT grid: 92 (x) x 80 (y) x 160 (z) voxels of 3 mm: 276 x 240 x 480 mm, 1.18 M voxels. It holds
the longest femur of the cohort (466 mm) and, for all 26 subjects with their own soft-tissue
variation, a thigh-like limb around it with air on the sides. 3 mm keeps simulation, model
building (20 registrations) and reconstruction comfortable on two CPU cores while the shaft
(about 25-30 mm across) still spans 8-10 voxels. The scanner: DSO 1000 mm, DSD 1500 mm, a flat
detector of 200 x 312 pixels of 3 mm that sees the whole volume from every angle, 0-180 degrees.
"""
from __future__ import annotations

import os

from clgs.anatomy import Scene, population_anatomy

__version__ = "0.1.0"

DATA_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
SUBJECTS = [f"{i:02d}" for i in range(26)]
TEST_SUBJECTS = SUBJECTS[20:]
FRAME_OFFSET = (100.5, 30.5, 1010.0)  # LLP26 mm (x, y, z) -> grid centre
SHAPE = (160, 80, 92)  # (Z, Y, X)
SPACING_MM = 3.0


#: a head closer than this (mm) to the shaft's axis tells no side
SIDE_MIN_OFFSET_MM = 5.0


def femur_side(vertices) -> tuple:
    """(side, offset mm) of a femur in the anatomy frame (z towards the hip, x towards the
    patient's left, as LPS): the shaft's axis is the principal axis of the middle 40 % of its
    length; the proximal 20 % (head, neck, trochanters) lies on average medial of that axis, the
    head pulling it: at -x for a left femur, +x for a right one. The offset is that mean's x
    distance from the axis (LLP26's 26 left femurs: -15 to -38 mm). Within
    ``SIDE_MIN_OFFSET_MM`` of the axis: "undecided"."""
    import numpy as np

    v = np.asarray(vertices, np.float64)
    z = v[:, 2]
    lo, length = float(z.min()), float(np.ptp(z))
    mid = v[(z > lo + 0.3 * length) & (z < lo + 0.7 * length)]
    if len(mid) < 3:  # a coarse surface with no vertices along its middle: the whole one's axis
        mid = v
    centre = mid.mean(0)
    axis = np.linalg.svd(mid - centre, full_matrices=False)[2][0]
    rel = v[z > lo + 0.8 * length] - centre
    offset = float((rel - np.outer(rel @ axis, axis)).mean(0)[0])
    if abs(offset) < SIDE_MIN_OFFSET_MM:
        return "undecided", offset
    return ("left" if offset < 0 else "right"), offset


femur_side.rule = ("the proximal 20 % of the femur's length lies medial of the shaft's axis (the head): at -x a "
                   "left femur, at +x a right one (anatomy frame, x towards the patient's left); right femurs "
                   "are mirrored into the template's side when most subjects are left, and the other way round")


def params():
    """Density parameters of the femur (see :mod:`clgs.anatomy.phantom` for the values' sources).

    Cortex 5.5 mm at mid-shaft thinning to 1.5 mm at the epiphyses (adult femoral diaphysis
    4-7 mm); medullary canal over the central half of the length; cancellous bone in the head,
    neck, trochanters and condyles; a thigh of muscle, 10 mm of subcutaneous fat and 2 mm skin."""
    from clgs.anatomy.phantom import DensityParams, SoftTissue

    return DensityParams(cortex_mid_mm=5.5, cortex_end_mm=1.5, cortex_plateau=0.22, canal_plateau=0.25,
                         canal_lining_mm=2.0, trabecular=0.027,
                         soft_tissue=SoftTissue(min_semi_axes_mm=(65.0, 60.0), margin_mm=20.0, fat_mm=10.0,
                                                skin_mm=2.0, smooth_mm=25.0))


PLUGIN = population_anatomy(
    name="femur", summary="left femur (LLP26 real surfaces: 20 model subjects, 6 held out)", version=__version__,
    data_dir=DATA_DIR, file_pattern="femur_left_LLP26_subject{id}.npz", ids=SUBJECTS, test_ids=TEST_SUBJECTS,
    shape=SHAPE, spacing_mm=SPACING_MM, params=params, frame_offset=FRAME_OFFSET, side_of=femur_side,
    scene=Scene(DSO=1000.0, DSD=1500.0, dDetector=(3.0, 3.0), n_views=50, arc_deg=180.0, surface_closing=3))
population_model = PLUGIN.population_model  # the femur's SurfacePopulation (made once)
clgs_anatomies = PLUGIN.clgs_anatomies  # the plugin's hook
