"""Write femur surfaces beyond the shape model's span: a held-out LLP26 femur changed in ways its
three modes cannot express.

    python3 examples/femur_out_of_span.py span/ [--subject 23]
    clgs femur experiment --meshes span/ --view-sets ap-lat --out span_exp

Five STL files (the femur's frame; z along the leg, proximal end up, -y anterior, the head at +x):

* ``own.stl``: the subject unchanged (the control: a femur the model reaches);
* ``neck_valgus10.stl``: the neck-shaft angle 10 degrees larger, the head and neck turned about
  the point where the neck's axis meets the shaft's, in their common plane, blended in over the
  neck's first 13 mm about the pivot (the head, a sphere fitted to it, turns whole);
* ``bowing10.stl``: the shaft bowed 10 mm anteriorly at its middle (``sin^2`` over the central 60 %
  of the length, so the ends stay as they are);
* ``bump3.stl``: a smooth bump 3 mm high (Gaussian, sigma 10 mm) along the surface normal on the
  lateral shaft, 80 mm above its middle;
* ``shaft_long15.stl``: the central 60 % of the length stretched by 15 % along the shaft's axis,
  the two ends moved apart unchanged.

Each line printed names the file and how far its surface moved (mean / largest, mm).
"""
import argparse
from pathlib import Path

import clgs_femur
import numpy as np

from clgs.io.mesh import save_mesh


def shaft_frame(v):
    """(centroid, unit axis pointing proximally (+z), position of every vertex along it (mm))."""
    c = v.mean(0)
    w, vec = np.linalg.eigh((v - c).T @ (v - c))
    a = vec[:, -1] * np.sign(vec[2, -1])
    return c, a, (v - c) @ a


def head_centre(v, c, a, s):
    """Least-squares sphere through the femoral head: the proximal 20 % of the length, beyond 35 mm
    medially (+x) from the shaft's axis."""
    rel = v - c - np.outer(s, a)  # off the axis
    top = s > s.max() - 0.2 * np.ptp(s)
    pts = v[top & (rel[:, 0] > 35.0)]
    A = np.c_[2 * pts, np.ones(len(pts))]
    sol, *_ = np.linalg.lstsq(A, (pts ** 2).sum(1), rcond=None)
    return sol[:3]


def smoothstep(t, lo, hi):
    x = np.clip((t - lo) / (hi - lo), 0.0, 1.0)
    return x * x * (3 - 2 * x)


def rotation(axis, angle):
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def neck_pivot(v):
    """(head centre, pivot): the pivot is where a line from the head centre at 125 degrees to the
    shaft (a typical neck-shaft angle) meets the shaft's axis; the neck's axis is pivot -> head."""
    c, a, s = shaft_frame(v)
    h = head_centre(v, c, a, s)
    level = c + a * ((h - c) @ a)  # the axis's point level with the head centre
    offset = np.linalg.norm(h - level)
    return h, level - a * offset / np.tan(np.radians(180.0 - 125.0))


def neck_angle(v, degrees=10.0):
    """The head and neck turned ``degrees`` about the pivot, away from the shaft (valgus), their
    weight rising from 0 to 1 between -5 and 8 mm along the neck's axis (the head, which starts
    about 9 mm along it, turns whole; measured on subject 23: the head centre's angle 125 -> 134)."""
    c, a, _ = shaft_frame(v)
    h, pivot = neck_pivot(v)
    neck = (h - pivot) / np.linalg.norm(h - pivot)
    axis = np.cross(-a, neck)  # turning about it moves the neck away from the distal shaft
    w = smoothstep((v - pivot) @ neck, -5.0, 8.0)
    out = v.copy()
    for i in np.flatnonzero(w > 0):
        out[i] = pivot + rotation(axis, np.radians(degrees) * w[i]) @ (v[i] - pivot)
    return out


def bowing(v, mm=10.0):
    c, a, s = shaft_frame(v)
    lo, hi = s.min() + 0.2 * np.ptp(s), s.max() - 0.2 * np.ptp(s)
    x = np.clip((s - lo) / (hi - lo), 0.0, 1.0)
    return v + np.outer(mm * np.sin(np.pi * x) ** 2, [0.0, -1.0, 0.0])  # -y: anterior


def bump(v, f, mm=3.0, sigma=10.0):
    import trimesh

    c, a, s = shaft_frame(v)
    normals = trimesh.Trimesh(v, f, process=False).vertex_normals
    level = np.abs(s - 80.0) < 10.0  # the lateral-most vertex 80 mm above the middle
    centre = v[np.flatnonzero(level)[np.argmin(v[level, 0])]]
    d2 = ((v - centre) ** 2).sum(1)
    return v + normals * (mm * np.exp(-d2 / (2 * sigma ** 2)))[:, None]


def longer_shaft(v, factor=1.15):
    c, a, s = shaft_frame(v)
    lo, hi = s.min() + 0.2 * np.ptp(s), s.max() - 0.2 * np.ptp(s)
    shift = np.where(s < lo, 0.0, np.where(s > hi, hi - lo, s - lo)) * (factor - 1.0)
    shift -= 0.5 * (hi - lo) * (factor - 1.0)  # about the middle, so both ends move apart
    return v + np.outer(shift, a)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="folder for the surfaces")
    ap.add_argument("--subject", default="23", help="held-out LLP26 subject to change [default: 23]")
    args = ap.parse_args()
    femur = clgs_femur.population_model()
    v, f = femur.mesh(args.subject)
    v = np.asarray(v, np.float64)
    f = np.asarray(f)
    args.out.mkdir(parents=True, exist_ok=True)
    changed = {"own": v, "neck_valgus10": neck_angle(v), "bowing10": bowing(v), "bump3": bump(v, f),
               "shaft_long15": longer_shaft(v)}
    for name, w in changed.items():
        path = args.out / f"{name}.stl"
        save_mesh(path, w, f)
        d = np.linalg.norm(w - v, axis=1)
        print(f"{path}: subject {args.subject}, moved {d.mean():.2f} mm mean, {d.max():.2f} mm at most")


if __name__ == "__main__":
    main()
