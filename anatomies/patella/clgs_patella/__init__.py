"""clgs anatomy plugin: the left patella (knee cap), from the 26 real surfaces of LLP26.

It uses exactly the same generic code as the femur (:class:`clgs.anatomy.population.SurfacePopulation`,
the model builder, the CT simulator); only the data, the grid and the density parameters
differ. Small, so it is also what the test suite builds a model from.

Data: ``data/patella_left_LLP26_subjectNN.npz`` (NN = 00..25, 650 vertices in correspondence),
from the PyPI package ``musculoskeletal-models`` 0.2.4 (Auckland Bioengineering Institute),
MPL-2.0: see ``data/LLP26_README.md`` and ``data/LICENSE-MPL-2.0.txt``. Subjects 00-19 build
the model, 20-25 are held out. Template: vertex-wise mean of 00-19.

Frame: LLP26's frame shifted by ``FRAME_OFFSET`` so that the CT grid (centred on the knee-sized
limb, not on the patella) sits on the rotation axis; -y is anterior.

CT grid: 72 (x) x 72 (y) x 32 (z) voxels of 2 mm: 144 x 144 x 64 mm (0.17 M voxels): a slab of
the knee around the patella (about 45 x 25 x 45 mm, 11-23 voxels across).
"""
from __future__ import annotations

import os

from clgs.anatomy import Scene, population_anatomy

__version__ = "0.1.0"

DATA_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
SUBJECTS = [f"{i:02d}" for i in range(26)]
TEST_SUBJECTS = SUBJECTS[20:]
FRAME_OFFSET = (82.0, 50.0, 830.0)  # LLP26 mm (x, y, z) -> grid centre
SHAPE = (32, 72, 72)  # (Z, Y, X)
SPACING_MM = 2.0


def params():
    """Density parameters of the patella: a thin cortex (1 mm, thicker at the anterior surface
    in reality) around cancellous bone, no medullary canal; the knee as an ellipse of about
    110 x 120 mm centred behind the patella (offset 38 mm posterior, 15 mm lateral), with the
    thin anterior cover of the knee cap (3 mm muscle/tendon, 4 mm fat, 2 mm skin)."""
    from clgs.anatomy.phantom import DensityParams, SoftTissue

    return DensityParams(cortex_mid_mm=1.0, cortex_end_mm=1.0, cortex_plateau=0.0, canal_plateau=0.0,
                         trabecular=0.026, subchondral_boost=0.12, texture_scale_mm=1.5,
                         soft_tissue=SoftTissue(min_semi_axes_mm=(55.0, 50.0), margin_mm=3.0, fat_mm=4.0,
                                                skin_mm=2.0, offset_mm=(-15.0, 38.0), smooth_mm=10.0))


PLUGIN = population_anatomy(
    name="patella", summary="left patella (LLP26 real surfaces: 20 model subjects, 6 held out)", version=__version__,
    data_dir=DATA_DIR, file_pattern="patella_left_LLP26_subject{id}.npz", ids=SUBJECTS, test_ids=TEST_SUBJECTS,
    shape=SHAPE, spacing_mm=SPACING_MM, params=params, frame_offset=FRAME_OFFSET,
    scene=Scene(DSO=1000.0, DSD=1500.0, dDetector=(2.0, 2.0), n_views=50, arc_deg=180.0))
population_model = PLUGIN.population_model  # the patella's SurfacePopulation (made once)
clgs_anatomies = PLUGIN.clgs_anatomies  # the plugin's hook
