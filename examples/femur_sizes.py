"""Write femur surfaces beyond LLP26's sizes: held-out subject 22 scaled to given lengths.

    python3 examples/femur_sizes.py sizes/ [--lengths 355,558] [--subject 22]
    clgs femur experiment --meshes sizes/ --view-sets ap-lat --out sizes_exp

Each surface is the subject's own shape at another size (its length measured along its longest
principal axis), written as STL: what a user's femur of that size looks like to the shape model.
"""
import argparse
from pathlib import Path

import clgs_femur

from clgs.anatomy.population import surface_length
from clgs.io.mesh import save_mesh


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="folder for the surfaces")
    ap.add_argument("--lengths", default="355,558", help="lengths in mm, comma-separated [default: 355,558]")
    ap.add_argument("--subject", default="22", help="LLP26 subject whose shape is scaled [default: 22]")
    args = ap.parse_args()
    try:
        lengths = [float(x) for x in args.lengths.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--lengths takes millimetres separated by commas, e.g. 355,558; got {args.lengths!r}")
    if not lengths or min(lengths) <= 0:
        ap.error(f"--lengths must be positive millimetres, got {args.lengths!r}")
    femur = clgs_femur.population_model()
    v, f = femur.mesh(args.subject)
    own = surface_length(v)
    args.out.mkdir(parents=True, exist_ok=True)
    for length in lengths:
        path = args.out / f"f{length:.0f}.stl"
        save_mesh(path, v * (length / own), f)
        print(f"{path}: subject {args.subject} ({own:.0f} mm) scaled {length / own:.3f} x to {length:.0f} mm")


if __name__ == "__main__":
    main()
