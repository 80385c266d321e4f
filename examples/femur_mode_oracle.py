"""How close a femur shape model can come to each held-out femur, whatever the views say.

    clgs femur build-model --n-modes 10 --out femur10.npz
    python3 examples/femur_mode_oracle.py --model femur10.npz [--modes 3,5,8,10] [--subjects 20,21]

Each held-out subject is registered to the template with the model's own registration settings
(as its population was), and its velocity field projected on the model's first K modes (least
squares, :meth:`clgs.shape.model.ShapeModel.project`); the template carried by that field is
compared with the subject's surface (symmetric mean distance in mm, :func:`clgs.metrics.surface_distance`,
at the model's size: no size fitted). "registration": the subject's own field, every mode and
what lies beyond them (the floor the registration leaves). A fit from projections cannot do
better than the K-mode figure: what it loses beyond it is the fit's, not the model's.
"""
import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch
import trimesh

from clgs.anatomy.plugins import get_anatomy
from clgs.metrics import surface_distance
from clgs.shape.builder import register_subject
from clgs.shape.model import exp_velocity, load_model, read_metadata


def carried(model, template, velocity) -> trimesh.Trimesh:
    """The template's surface carried by exp(velocity) (the model's grid)."""
    p = torch.as_tensor(template.vertices, dtype=torch.float32)
    with torch.no_grad():
        u = exp_velocity(torch.as_tensor(velocity, dtype=torch.float32), model.spacing)
        v = (p + model.sample(u, p)).numpy()
    return trimesh.Trimesh(v, template.faces, process=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=None, help="model file [default: the femur plugin's]")
    ap.add_argument("--modes", default="3,5,8,10", help="mode counts, comma-separated [default: 3,5,8,10]")
    ap.add_argument("--subjects", default=None, help="held-out subject ids [default: all]")
    args = ap.parse_args()
    femur = get_anatomy("femur")
    path = args.model or femur.model_path
    model, meta = load_model(path)[0], read_metadata(path)
    settings = meta.get("settings", {})
    try:
        counts = sorted({int(k) for k in args.modes.split(",") if k.strip()})
    except ValueError:
        ap.error(f"--modes takes whole numbers separated by commas, e.g. 3,5; got {args.modes!r}")
    if not counts or counts[0] < 1:
        ap.error(f"--modes must be positive, got {args.modes!r}")
    counts = [k for k in counts if k <= model.n_modes] or [model.n_modes]
    held = list(femur.test_subjects())
    subjects = [s.strip() for s in args.subjects.split(",")] if args.subjects else held
    bad = [s for s in subjects if s not in held]
    if bad:
        ap.error(f"not held-out femur subjects: {', '.join(bad)} (held out: {', '.join(held)})")
    template = femur.load_template()
    print(f"model {path}: {model.n_modes} modes")
    print("| subject | registration | " + " | ".join(f"{k} modes" for k in counts) + " |")
    print("|---|---|" + "---|" * len(counts))
    rows = []
    scratch = tempfile.TemporaryDirectory()  # register_subject writes its cache entry there
    for sid in subjects:
        subject = femur.load_subject(sid)
        truth = trimesh.Trimesh(subject.vertices, subject.faces, process=False)
        entry = Path(scratch.name) / f"{sid}.npz"
        v = register_subject(template, subject, sid, entry, int(settings.get("max_cells", 64)),
                             settings.get("registration", {}), atlas=False)["velocity"]
        row = [surface_distance(carried(model, template, v), truth)["mean"]]
        alpha = model.project(v)
        for k in counts:
            a = alpha.clone()
            a[k:] = 0
            row.append(surface_distance(carried(model, template, model.velocity(a)), truth)["mean"])
        rows.append(row)
        print(f"| {sid} | " + " | ".join(f"{x:.2f}" for x in row) + " |", flush=True)
    print("| mean | " + " | ".join(f"{x:.2f}" for x in np.mean(rows, axis=0)) + " |")


if __name__ == "__main__":
    main()
