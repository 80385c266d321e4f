"""The density atlas scaled to the scan: one factor for the bone, one for the rest.

An atlas holds the densities of the CTs it was built from. A user's scan measures another
spectrum, another detector calibration, another patient: its bone may be denser and its tissue
lighter than the atlas says, and the density prior then pulls the volume towards densities the
scan does not have (a held-out femur with its bone 1.2 times denser and the rest 0.85 times:
docs/results.md, "The density prior's weight").

Once the bone is registered, the atlas's projections are linear in its densities: the measured
views ``y`` are about ``b A(bone) + t A(rest)``, ``A`` the voxel projector
(:class:`clgs.ops.ct_projector.CTProjector`), ``bone`` and ``rest`` the atlas carried onto the
scan's grid by the registered shape (inside the template's bone, and outside it). The
least-squares ``(b, t)`` over every pixel of every training view scale the atlas the prior holds
the field to (inside the template's bone ``b``, outside it ``t``) and the start's densities
(the bone's Gaussians by ``b``, the atlas's tissue by ``t``). They never read the scan's truth."""
from __future__ import annotations

import math

import numpy as np
import torch

from clgs.errors import InputError
from clgs.fit.gaussians import inverse_softplus

#: the factors are clipped to this range: beyond it the atlas is not the scan's anatomy, or the
#: registration missed the bone, and scaling would only hide that
FACTOR_RANGE = (0.5, 2.0)


def atlas_projections(projector, bone: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A bone, A rest): every view of the atlas's two parts (volumes on the scan's grid, per mm)."""
    return projector.forward(np.ascontiguousarray(bone, np.float32)), projector.forward(
        np.ascontiguousarray(rest, np.float32))


def fit_factors(bone, rest, target) -> tuple[float, float | None]:
    """(b, t) minimising ``|b bone + t rest - target|^2`` over every pixel (float64 normal
    equations); ``rest`` None, or holding nothing, or parallel to ``bone``: ``t`` is None and ``b``
    is the one factor of the bone alone. Both clipped to :data:`FACTOR_RANGE`."""
    lo, hi = FACTOR_RANGE
    pb = np.asarray(bone, np.float64).reshape(-1)
    y = np.asarray(target, np.float64).reshape(-1)
    bb = float(pb @ pb)
    if not math.isfinite(bb) or bb <= 0:
        raise InputError("the bone's projections are empty or not finite: the atlas cannot be scaled to this "
                         "scan (is the bone in the views? --set atlas_calibration=off runs without)")
    if rest is not None:
        pt = np.asarray(rest, np.float64).reshape(-1)
        tt, bt = float(pt @ pt), float(pb @ pt)
        det = bb * tt - bt * bt
        if tt > 0 and det > 1e-9 * bb * tt:
            by, ty = float(pb @ y), float(pt @ y)
            b = (tt * by - bt * ty) / det
            t = (bb * ty - bt * by) / det
            if not (math.isfinite(b) and math.isfinite(t)):
                raise FloatingPointError("the atlas calibration's factors are not finite")
            return float(np.clip(b, lo, hi)), float(np.clip(t, lo, hi))
    b = float(pb @ y) / bb
    if not math.isfinite(b):
        raise FloatingPointError("the atlas calibration's bone factor is not finite")
    return float(np.clip(b, lo, hi)), None


def scale_densities(gset, factor: float) -> None:
    """Multiply a Gaussian set's (activated) densities by ``factor``, in place."""
    if factor == 1.0 or len(gset) == 0:
        return
    raw = gset.params["densities"]
    with torch.no_grad():
        scaled = inverse_softplus(torch.nn.functional.softplus(raw.detach()) * float(factor))
    gset.params["densities"] = scaled.clone().requires_grad_(raw.requires_grad)
