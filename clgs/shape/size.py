"""The bone's size before a shape-guided fit: a search of the projections over one scale factor.

A shape model built from one population (LLP26's femurs: 411-469 mm) moves a bone within that
population's shapes and sizes; a femur of 355 or 558 mm is beyond what its modes can stretch to.
The shape-guided set then also fits a size ``s`` (:class:`clgs.shape.gaussian_set.ShapeGuidedSet`),
and this module finds where ``s`` starts: the template's bone is scaled about its centroid by each
candidate, rendered with the tissue around it into every view, and the candidate whose
projections are nearest (L1) to the measured ones is kept.

The tissue around the bone is the atlas's, around the template's bone. A limb's cross-section
does not scale with its femur (the simulated limbs: at least 70 x 65 mm semi-axes, 25 mm of muscle
around the bone), but the limb runs the whole length of the scan; so the tissue is stretched along
the leg only, and only for a larger bone (a smaller one sits inside a grid that the template's
tissue already fills; what the search gives on the femur: docs/methods.md). The fit then refines
``s`` with everything else (:func:`clgs.methods.shape_guided.fit_initial_alpha`).

A femur longer or shorter for its girth than the model's takes a second factor ``k`` along the
leg (:func:`search_size_and_length`): the bone's Gaussians carried whole by ``diag(s, s, s k)``
(:func:`stretched_bone`), the tissue stretched along the leg for the bone's length as for its
size; the fit holds ``k`` (docs/methods.md, "The bone's length")."""
from __future__ import annotations

import numpy as np
import torch

#: the sizes searched (relative to the model's), 0.70 to 1.40 in steps of 0.02
SIZES = np.round(np.arange(0.70, 1.4001, 0.02), 4)
#: ``fit_size="auto"`` fits a size only when the search finds the bone this far from the model's
#: own size (LLP26's femurs lie within +-7 % of the template's length, which the modes cover; the
#: search itself scatters by a few percent)
AUTO_TOLERANCE = 0.10
#: the axis along the leg in the template's frame (x, y, z): z
LEG_AXIS = 2
#: the length factors searched with ``fit_length="on"`` (along the leg, times the size), and how
#: far from the size alone's best the sizes searched with them reach
LENGTHS = np.round(np.arange(0.90, 1.1501, 0.01), 4)
LENGTH_SIZE_REACH = 0.081
#: with ``fit_length="auto"`` a length is taken only where it lowers the search's L1 by more than
#: this share against the size alone (the lengthened shaft: 7.7 %; the held-out and the other
#: changed femurs at 2 and 5 views: at most 0.5 %; docs/results.md)
LENGTH_GAIN = 0.03


def size_centre(template) -> np.ndarray:
    """The point (x, y, z mm) a size scales about: the template surface's centroid, where the
    alignment of a user's surface puts that surface's own centroid."""
    return np.asarray(template.vertices, np.float64).mean(0)


def stretched_surroundings(centres_mm: np.ndarray, centre_mm: np.ndarray, size: float,
                           length: float = 1.0) -> np.ndarray:
    """Tissue centres (mm) stretched along the leg about ``centre_mm`` for a bone ``size`` times the
    model's, when ``size`` > 1 (unchanged otherwise; see the module doc), and by a ``length``
    factor > 1 as well (a limb runs the length of its bone; neither compresses it)."""
    out = np.array(centres_mm, np.float64, copy=True)
    k = max(float(size), 1.0) * max(float(length), 1.0)
    out[:, LEG_AXIS] = centre_mm[LEG_AXIS] + k * (out[:, LEG_AXIS] - centre_mm[LEG_AXIS])
    return out


def stretched_bone(centres_mm: np.ndarray, scales_mm: np.ndarray, quats: np.ndarray, centre_mm: np.ndarray,
                   size: float, length: float = 1.0) -> tuple:
    """(centres, scales, quaternions) of Gaussians (mm; quaternions w, x, y, z) carried by
    ``x -> c + A (x - c)``, ``A = diag(s, s, s k)`` for ``size`` s and ``length`` k along the leg.

    Each covariance ``R S^2 R^T`` becomes ``A R S^2 R^T A`` exactly (the singular values and left
    vectors of ``A R S``), so the Gaussians render the bone stretched with its density kept: with
    the scales alone multiplied, a bone made longer would be fainter by 1/k. With k = 1 it is the
    plain scaling (scales times s, rotations kept), to the last bit."""
    from scipy.spatial.transform import Rotation

    c = np.asarray(centre_mm, np.float64)
    x = np.asarray(centres_mm, np.float64)
    sc = np.asarray(scales_mm, np.float64)
    if float(length) == 1.0:
        return c + size * (x - c), sc * size, np.asarray(quats)
    a = np.full(3, float(size))
    a[LEG_AXIS] *= float(length)
    q = np.asarray(quats, np.float64)
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # (N, 3, 3), columns the Gaussian's axes
    u, sv, _ = np.linalg.svd(a[None, :, None] * rot * sc[:, None, :])
    u[np.linalg.det(u) < 0, :, 2] *= -1.0  # a rotation, not a reflection (the covariance is the same)
    q_new = Rotation.from_matrix(u).as_quat()[:, [3, 0, 1, 2]]
    return c + a * (x - c), sv, q_new.astype(np.asarray(quats).dtype)


def search_size(scan, backend, value_scale: float, bone, tissue=None, centre_mm=None, sizes=SIZES,
                length: float = 1.0) -> tuple:
    """(best size, L1 per size) of the bone ``bone`` (a ShapeInit: mm, atlas units) scaled about
    ``centre_mm`` with ``tissue`` (a ShapeInit or None) stretched as :func:`stretched_surroundings`
    says, against every view of ``scan``; ``backend`` a :class:`clgs.fit.trainer.Backend`. With a
    ``length`` factor the bone is also that much longer along the leg at every size."""
    geo = scan.geometry
    n = len(bone.centres)
    parts = [bone] if tissue is None else [bone, tissue]
    centres = np.concatenate([p.centres for p in parts]).astype(np.float64)
    scales = np.concatenate([p.scales for p in parts]).astype(np.float64)
    quats = np.concatenate([p.quats for p in parts]).astype(np.float32)
    dens = torch.as_tensor(np.concatenate([p.densities for p in parts]) * value_scale, dtype=torch.float32)
    target = torch.as_tensor(np.asarray(scan.projections, np.float32) * np.float32(geo.scale * value_scale))
    views = list(range(target.shape[0]))
    losses = []
    if float(length) != 1.0:  # the stretch's rotations and scales at size 1 (a size scales them after)
        _, long_scales, long_quats = stretched_bone(centres[:n], scales[:n], quats[:n], centre_mm, 1.0, length)
    for s in sizes:
        c, sc, q = centres.copy(), scales.copy(), quats.copy()
        if float(length) == 1.0:
            c[:n], sc[:n], q[:n] = stretched_bone(centres[:n], scales[:n], quats[:n], centre_mm, s)
        else:
            k = np.full(3, float(s))
            k[LEG_AXIS] *= float(length)
            c[:n], sc[:n], q[:n] = centre_mm + k * (centres[:n] - centre_mm), long_scales * s, long_quats
        if tissue is not None:
            c[n:] = stretched_surroundings(centres[n:], centre_mm, s, length)
        with torch.no_grad():
            render = backend.project(torch.as_tensor(geo.world_to_scene(c), dtype=torch.float32),
                                     torch.as_tensor(sc * geo.scale, dtype=torch.float32), torch.as_tensor(q),
                                     dens, geo, views) * geo.scale
        losses.append(float((render - target).abs().mean()))
    losses = np.asarray(losses)
    if not np.all(np.isfinite(losses)):
        raise FloatingPointError("the size search's projections are not finite")
    return float(sizes[int(np.argmin(losses))]), losses


def search_size_and_length(scan, backend, value_scale: float, bone, tissue=None, centre_mm=None, sizes=SIZES,
                           lengths=LENGTHS, gain: float = 0.0) -> tuple:
    """(best size, best length factor, the size alone's best, the share by which that length
    lowers the L1) by L1 over every view: the size alone first (:func:`search_size`), then each
    length factor with the sizes within ``LENGTH_SIZE_REACH`` of that best (a femur longer for its
    girth comes out as a larger size alone: the girth is then nearer the model's). Where no length
    lowers the L1 by more than ``gain`` (a share) against the size alone, the length is 1 and the
    size the size alone's."""
    alone, losses = search_size(scan, backend, value_scale, bone, tissue, centre_mm, sizes)
    l0 = float(np.min(losses))
    best = (l0, alone, 1.0)
    near = np.asarray([s for s in sizes if abs(s - alone) <= LENGTH_SIZE_REACH])
    for k in lengths:
        if k == 1.0:
            continue
        size, ls = search_size(scan, backend, value_scale, bone, tissue, centre_mm, near, length=float(k))
        if float(np.min(ls)) < best[0]:
            best = (float(np.min(ls)), size, float(k))
    share = 1.0 - best[0] / l0 if l0 > 0 else 0.0
    if share <= gain:
        return alone, 1.0, alone, share
    return best[1], best[2], alone, share
