"""How close the femur model, at one size or with a length of its own, can come to a surface.

    python3 examples/femur_out_of_span.py span/
    python3 examples/femur_model_reach.py span/*.stl

Without the residual deformation, a fit from projections cannot bring the model's surface nearer
to a bone than the model itself reaches. This fits the model to each surface directly (no
projections, no views): the surface is first brought into the template's frame
(:func:`clgs.anatomy.alignment.align_rigid`, as ``clgs femur experiment --meshes`` does), then the
model's coefficients alpha, its size ``s`` about the template's centroid (as the shape-guided
method's ``fit_size``) and a small rigid correction are fitted by ICP (closest points on the
surface, then L-BFGS on the squared distance to their tangent planes, with a twentieth of the
squared distance to the points), once with one size and once with a second factor ``k`` along
the leg (z) as well: ``c + s * diag(1, 1, k) (x - c)``, the length apart from the girth. Each
fit's surface is compared with the surface given: the symmetric mean, p95 and Hausdorff distance in mm
(:func:`clgs.metrics.surface_distance`, the experiment's measure), and, read independently, the
mean unsigned distance of its vertices to the surface (trimesh). The method has no length factor:
the second fit says what one would reach.
"""
import argparse
import functools
import json

import numpy as np
import torch
import trimesh

from clgs.anatomy.alignment import align_rigid
from clgs.anatomy.plugins import get_anatomy
from clgs.io.mesh import MeshError, load_mesh
from clgs.metrics import surface_distance
from clgs.shape.model import exp_velocity


def skew(w):
    z = torch.zeros((), dtype=w.dtype)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


def plane_loss(opt, points, nearest, normal):
    """The squared distance of the points to the tangent planes at their nearest surface points (the
    points may slide along it), with a twentieth of the squared distance to those points."""
    opt.zero_grad()
    gap = points() - nearest
    loss = ((gap * normal).sum(1) ** 2).mean() + 0.05 * (gap ** 2).sum(1).mean()
    loss.backward()
    return loss


def fit(model, vertices, faces, target, length: bool, rounds: int, steps: int):
    """(fitted vertices, alpha, size, length factor) of the model fitted to ``target`` (a trimesh)."""
    v = torch.as_tensor(vertices, dtype=torch.float64)
    c = v.mean(0)
    extent = np.ptp(target.vertices[:, 2]) / np.ptp(vertices[:, 2])
    alpha = torch.zeros(model.n_modes, dtype=torch.float64, requires_grad=True)
    log_s = torch.tensor(np.log(extent), dtype=torch.float64, requires_grad=True)
    log_k = torch.zeros((), dtype=torch.float64, requires_grad=length)
    rot = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    shift = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    params = [alpha, log_s, rot, shift] + ([log_k] if length else [])

    def points():
        u = exp_velocity(model.velocity(alpha), model.spacing)
        p = v + model.sample(u, v)
        one = torch.ones((), dtype=p.dtype)
        p = c + torch.exp(log_s) * torch.stack([one, one, torch.exp(log_k)]) * (p - c)
        m = p.mean(0).detach()
        return (p - m) @ torch.linalg.matrix_exp(skew(rot)).T + m + shift

    for _ in range(rounds):
        with torch.no_grad():
            now = points().numpy()
        q, _, tri = trimesh.proximity.closest_point(target, now)
        nearest, normal = torch.as_tensor(q), torch.as_tensor(target.face_normals[tri])
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=steps, line_search_fn="strong_wolfe")
        opt.step(functools.partial(plane_loss, opt, points, nearest, normal))
    with torch.no_grad():
        out = points().numpy()
    return out, alpha.detach().numpy(), float(torch.exp(log_s).detach()), float(torch.exp(log_k).detach())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("surfaces", nargs="+", help="femur surfaces (STL, PLY, OBJ; mm)")
    ap.add_argument("--rounds", type=int, default=15, help="ICP rounds (closest points found again)")
    ap.add_argument("--steps", type=int, default=20, help="L-BFGS iterations a round")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args()
    if args.rounds < 1 or args.steps < 1:
        ap.error("--rounds and --steps must be at least 1")
    meshes = {}
    for path in args.surfaces:  # every file read before any fit: a bad one stops nothing half-done
        try:
            meshes[path] = load_mesh(path)
        except MeshError as exc:
            ap.error(str(exc))
    femur = get_anatomy("femur")
    template = femur.load_template()
    model = femur.load_shape_model().to(torch.float64)
    tv, tf = np.asarray(template.vertices, float), np.asarray(template.faces)
    rows = []
    print(f"{'surface':<22} {'fit':<16} {'size':>6} {'length':>7}   mean / p95 / Hausdorff (mm)   trimesh mean")
    for path, mesh in meshes.items():
        a = align_rigid(mesh.vertices, tv)
        target = trimesh.Trimesh(*a.apply_mesh(mesh.vertices, mesh.faces), process=True)
        for length in (False, True):
            pts, alpha, s, k = fit(model, tv, tf, target, length, args.rounds, args.steps)
            d = surface_distance((pts, tf), (np.asarray(target.vertices), np.asarray(target.faces)))
            independent = float(np.abs(trimesh.proximity.signed_distance(target, pts)).mean())
            name = "size and length" if length else "one size"
            print(f"{path.rsplit('/', 1)[-1]:<22} {name:<16} {s:6.3f} {k:7.3f}   "
                  f"{d['mean']:.2f} / {d['p95']:.2f} / {d['hausdorff']:.2f}            {independent:.2f}"
                  f"   alpha {np.round(alpha, 2).tolist()}")
            rows.append({"surface": path, "fit": "size_and_length" if length else "size", "size": s, "length": k,
                         "alpha": alpha.tolist(), "mean_mm": d["mean"], "p95_mm": d["p95"],
                         "hausdorff_mm": d["hausdorff"], "trimesh_vertex_mean_mm": independent})
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
