"""How sure a reconstruction is of its shape surface, vertex by vertex: the shape coefficients'
posterior (a Laplace approximation), what lies beyond the model's span, and how far the volume's
own bone surface lies from it.

The shape coefficients' posterior is approximated by a Gaussian about the fitted alpha: with the
model's prior alpha ~ N(0, I) and the projections' pixels taken as independent Gaussian noise of
the variance the fit leaves (the residual's mean square), the Gauss-Newton Hessian of the
negative log posterior is ``H = J^T J / s^2 + I`` (J: d projections / d alpha, by central
differences of renders of every view with everything else as fitted), and the covariance
``C = H^-1``. A vertex of the shape surface moves by ``G dalpha`` (G = d vertex / d alpha, (3, M),
central differences of the map); across the surface only its normal part changes the surface,
so its standard deviation there is ``sqrt(n^T G C G^T n)`` (mm): :func:`normal_sd`.

That part (``posterior_mm``) is the spread of the model's part of the surface given these views
and the fitted densities, size, residual and free Gaussians (a conditional posterior); where the
views say little about a mode, its spread stays the prior's; independent pixels make it a lower
bound when the residual has structure. The second part (``beyond_model_mm``) is what the views
cannot correct through the modes at all: a new member of the population differs from its best
M-mode approximation by a field whose covariance the model builder measured by leave-one-out
(:func:`clgs.shape.builder.beyond_span_covariance`, ``ShapeModel.beyond_cov``), sampled at the
template's vertex, ``sqrt(n^T S n)`` (times the fitted size). The two are independent, so the
model's field is ``sqrt(posterior^2 + beyond^2)``; a model built without the covariance gives the
posterior alone.

The third part (``volume_mm``) is this reconstruction's own say: each vertex's distance to the
volume's bone surface (the ``surface.stl`` the run wrote, at its bone level). Where the densities
and the free Gaussians put the bone's edge elsewhere than the shape, the shape is in doubt. It is
not independent of the model's part (the model's misses are what the densities take up), so the
field written is the larger of the two estimates of one error, ``uncertainty_mm = max(sqrt(
posterior^2 + beyond^2), volume)``, not their root sum of squares (which, on the femur, came out
twice the error, with 91 % of vertices within one standard deviation; docs/shape-model.md).

The files: ``shape_uncertainty.ply``, the shape surface (as shape_surface.stl) with a per-vertex
float property ``uncertainty_mm`` (binary PLY written by trimesh; trimesh reads it back as
``mesh.metadata['_ply_raw']['vertex']['data']['uncertainty_mm']``, meshio as
``point_data['uncertainty_mm']``), and ``shape_uncertainty.vtk``, the same as legacy VTK
polydata with the point scalar ``uncertainty_mm``, which 3D Slicer and ParaView open with its
colour map (Slicer's PLY reader keeps only positions, normals and colours).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from clgs.errors import InputError

#: the step (in standard deviations of alpha) of the central differences
STEP = 0.05
FILE_NAME = "shape_uncertainty.ply"
VTK_NAME = "shape_uncertainty.vtk"
FIELD = "uncertainty_mm"


def normal_sd(jacobian, normals, covariance) -> np.ndarray:
    """sqrt(n^T G C G^T n) per vertex: ``jacobian`` G (V, 3, M) mm per unit alpha, ``normals``
    (V, 3) unit, ``covariance`` C (M, M) of alpha."""
    g = np.einsum("vi,vim->vm", np.asarray(normals, np.float64), np.asarray(jacobian, np.float64))
    c = np.asarray(covariance, np.float64)
    if c.shape != (g.shape[1], g.shape[1]):
        raise InputError(f"covariance {c.shape} does not match the {g.shape[1]} modes of the jacobian")
    return np.sqrt(np.clip(np.einsum("vm,mn,vn->v", g, c, g), 0.0, None))


def laplace_covariance(jacobian, residual, prior_precision=None) -> tuple:
    """(C (M, M), noise variance s^2) of a Laplace approximation: ``jacobian`` (P, M) of the
    predictions, ``residual`` (P,) prediction minus measurement at the fit, the prior's precision
    (identity when None: alpha ~ N(0, I)). s^2 = |r|^2 / (P - M)."""
    J = np.asarray(jacobian, np.float64)
    r = np.asarray(residual, np.float64).reshape(-1)
    if J.ndim != 2 or len(J) != len(r):
        raise InputError(f"jacobian {J.shape} and residual {r.shape} must have one row per measurement")
    if not (np.isfinite(J).all() and np.isfinite(r).all()):
        raise InputError("the jacobian or the residual holds NaN or Inf: the fit did not converge")
    m = J.shape[1]
    prior = np.eye(m) if prior_precision is None else np.asarray(prior_precision, np.float64)
    s2 = float(r @ r) / max(len(r) - m, 1)
    h = prior + (J.T @ J) / max(s2, 1e-30)
    c = np.linalg.inv(h)
    return 0.5 * (c + c.T), s2


def map_jacobian(map_points: Callable, alpha, step: float = STEP) -> np.ndarray:
    """d map_points(alpha) / d alpha (V, 3, M) by central differences of ``step``."""
    a0 = np.asarray(alpha, np.float64)
    cols = []
    for k in range(len(a0)):
        e = np.zeros_like(a0)
        e[k] = step
        cols.append((np.asarray(map_points(a0 + e), np.float64) - np.asarray(map_points(a0 - e), np.float64))
                    / (2 * step))
    return np.stack(cols, -1)


def projection_jacobian(trainer, shape_set, step: float = STEP) -> tuple:
    """(J (P, M), residual (P,)) of every view's projection (training units) in the shape set's
    alpha, the other sets and every other parameter as fitted."""
    import torch

    n = shape_set.squarings()
    alpha = shape_set.alpha.detach().numpy().astype(np.float64)
    with torch.no_grad():
        others = [s.tensors() for s in trainer.sets if s is not shape_set]

        def render(a):
            parts = [shape_set.tensors_at(a, n)] + others
            t = tuple(torch.cat([p[i] for p in parts], 0) for i in range(4))
            out = trainer.backend.project(*t, trainer.geometry, trainer.views) * trainer.render_scale
            return out.double().numpy().reshape(-1)

        residual = render(alpha) - trainer.projections[trainer.views].double().numpy().reshape(-1)
        J = map_jacobian(lambda a: render(a)[:, None], alpha, step)[:, 0, :]
    return J, residual


def beyond_sd(shape_model, vertices, normals, size: float = 1.0) -> np.ndarray:
    """sqrt(n^T S n) (V,) mm: S the model's beyond-span covariance (``beyond_cov``, 6 components)
    at the template ``vertices``, ``normals`` (V, 3) unit; zeros for a model without one."""
    import torch

    if shape_model.beyond_cov is None:
        return np.zeros(len(vertices))
    cov = torch.as_tensor(shape_model.beyond_cov, dtype=torch.float64)
    c = shape_model.sample(cov, torch.as_tensor(np.asarray(vertices, np.float64))).numpy()  # (V, 6)
    n = np.asarray(normals, np.float64)
    xx, yy, zz, xy, xz, yz = c.T
    q = (xx * n[:, 0] ** 2 + yy * n[:, 1] ** 2 + zz * n[:, 2] ** 2
         + 2 * (xy * n[:, 0] * n[:, 1] + xz * n[:, 0] * n[:, 2] + yz * n[:, 1] * n[:, 2]))
    return float(size) * np.sqrt(np.clip(q, 0.0, None))


def volume_disagreement(vertices, volume_surface) -> np.ndarray:
    """(V,) mm: each of ``vertices``' distance to the reconstructed volume's bone surface
    ``volume_surface`` ((vertices, faces) mm, the surface.stl a run writes), to its nearest point
    (trimesh)."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(volume_surface[0], np.float64), np.asarray(volume_surface[1]), process=False)
    _, d, _ = trimesh.proximity.closest_point(mesh, np.asarray(vertices, np.float64))
    return np.asarray(d, np.float64)


def shape_uncertainty(trainer, shape_set, vertices, faces, step: float = STEP, surface=None,
                      volume_surface=None) -> dict:
    """{"values" (V,) mm, "posterior" (V,), "beyond" (V,), "volume" (V,), "vertices", "faces",
    "covariance" (M, M), "noise_sd", "alpha_sd"} for the shape surface of the template
    ``vertices``/``faces`` (mm) under the fitted ``shape_set`` (see the module doc); ``surface``:
    the shape surface's vertices as written (its normals are used; None: the template's vertices
    carried by the map); ``volume_surface``: the volume's bone surface ((vertices, faces) mm), whose
    distance is the third part (zeros without one)."""
    import trimesh

    if shape_set.alpha.numel() == 0:
        raise InputError("the shape model has no modes: there is no shape coefficient to be unsure of")
    J, residual = projection_jacobian(trainer, shape_set, step)
    cov, s2 = laplace_covariance(J, residual)
    n = shape_set.squarings()
    alpha = shape_set.alpha.detach().numpy().astype(np.float64)
    G = map_jacobian(lambda a: shape_set.map_points(vertices, a, n).numpy(), alpha, step)
    moved = (shape_set.map_points(vertices, None, n).numpy().astype(np.float64) if surface is None
             else np.asarray(surface, np.float64))
    normals = trimesh.Trimesh(moved, np.asarray(faces), process=False).vertex_normals
    post = normal_sd(G, normals, cov)
    beyond = beyond_sd(shape_set.shape_model, vertices, normals, shape_set.size)
    volume = np.zeros(len(moved)) if volume_surface is None else volume_disagreement(moved, volume_surface)
    return {"values": np.maximum(np.sqrt(post ** 2 + beyond ** 2), volume), "posterior": post, "beyond": beyond,
            "volume": volume, "vertices": moved, "faces": np.asarray(faces), "covariance": cov,
            "noise_sd": float(np.sqrt(s2)), "alpha_sd": [float(x) for x in np.sqrt(np.diag(cov))]}


def area_share_above(vertices, faces, values, threshold_mm: float) -> float:
    """The share of a surface's area whose per-vertex ``values`` exceed ``threshold_mm`` (each
    vertex standing for a third of the area of the faces around it)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    per_vertex = np.bincount(f.reshape(-1), np.repeat(area / 3.0, 3), minlength=len(v))
    total = per_vertex.sum()
    return float(per_vertex[np.asarray(values) > threshold_mm].sum() / total) if total > 0 else 0.0


def write_uncertainty_files(out_dir, vertices, faces, values, parts: dict | None = None) -> dict:
    """``shape_uncertainty.ply`` (binary PLY, vertex property ``uncertainty_mm``) and
    ``shape_uncertainty.vtk`` (legacy VTK polydata, point scalar ``uncertainty_mm``: what 3D
    Slicer shows as a model's scalars) in ``out_dir``, both in LPS with ``SPACE=LPS`` in the header
    as every clgs surface (:mod:`clgs.io.mesh`), atomically; {"ply": path, "vtk": path}.
    ``parts``: more per-vertex values (name -> (V,)) written beside it in both files."""
    from pathlib import Path

    from clgs.io import atomic
    from clgs.io.mesh import RAS_TO_LPS, check_mesh, save_mesh

    out_dir = Path(out_dir)
    values = np.asarray(values, np.float64)
    scalars = {FIELD: values, **{k: np.asarray(v, np.float64) for k, v in (parts or {}).items()}}
    ply = save_mesh(out_dir / FILE_NAME, vertices, faces, scalars=scalars)
    mesh = check_mesh(vertices, faces)
    lps = mesh.vertices * RAS_TO_LPS
    lines = ["# vtk DataFile Version 3.0", "clgs shape surface uncertainty (mm) SPACE=LPS", "ASCII",
             "DATASET POLYDATA", f"POINTS {len(lps)} float"]
    lines += [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in lps]
    lines.append(f"POLYGONS {len(mesh.faces)} {4 * len(mesh.faces)}")
    lines += [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
    lines.append(f"POINT_DATA {len(lps)}")
    for name, vals in scalars.items():  # the first is the active scalar a viewer colours by
        lines += [f"SCALARS {name} float 1", "LOOKUP_TABLE default"]
        lines += [f"{v:.9g}" for v in vals]
    vtk = atomic.write_bytes(out_dir / VTK_NAME, ("\n".join(lines) + "\n").encode("ascii"))
    return {"ply": Path(ply), "vtk": Path(vtk)}


def read_uncertainty_ply(path) -> tuple:
    """(vertices mm in clgs's frame, faces, uncertainty_mm) of a ``shape_uncertainty.ply``: the
    surface through :func:`clgs.io.mesh.load_mesh`, the values through trimesh's PLY reader."""
    import trimesh

    from clgs.io.mesh import load_mesh

    mesh = load_mesh(path)
    raw = trimesh.load(str(path), process=False)
    try:
        values = np.asarray(raw.metadata["_ply_raw"]["vertex"]["data"][FIELD], np.float64)
    except (KeyError, ValueError, IndexError) as exc:
        raise InputError(f"{path} holds no per-vertex {FIELD}: is it a clgs {FILE_NAME}?") from exc
    return mesh.vertices, mesh.faces, values.reshape(-1)


def summary(field: dict, extra: dict | None = None) -> dict:
    """Mean and largest value (mm) of the field and of its three parts, and the share of the
    surface's area above 2 mm, for the run's report."""
    def r4(x):
        return round(float(x), 4)

    v, p, b, d = (np.asarray(field[k], np.float64) for k in ("values", "posterior", "beyond", "volume"))
    out = {"file": FILE_NAME, "vtk_file": VTK_NAME, "mean_mm": r4(v.mean()), "max_mm": r4(v.max()),
           "share_above_2mm": r4(area_share_above(field["vertices"], field["faces"], v, 2.0)),
           "posterior_mean_mm": r4(p.mean()), "posterior_max_mm": r4(p.max()),
           "beyond_model_mean_mm": r4(b.mean()), "beyond_model_max_mm": r4(b.max()),
           "volume_mean_mm": r4(d.mean()), "volume_max_mm": r4(d.max()),
           "alpha_sd": [r4(x) for x in field["alpha_sd"]], "noise_sd": round(float(field["noise_sd"]), 6)}
    out.update(extra or {})
    return out
