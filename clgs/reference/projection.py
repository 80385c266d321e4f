"""Plain torch references of the Gaussian projector (``cl/projector.cl``).

``project_dense`` evaluates every (pixel, Gaussian) pair from first principles, with the rays of
``Geometry.rays`` and, for the affine mode, the Jacobian of the projection map obtained by
automatic differentiation (not the closed form the kernel uses), so it checks the kernel's
algebra rather than repeating it. Same contract as the kernel: packed covariance (affine) or
precision (exact), output in mm-based units (scene integral / ``geometry.scale``), a Gaussian
counts where its ray passes within 3 sigma (q <= 9), and the affine cone mode culls Gaussians
whose centre is closer than 0.2 scene units to the source plane or whose 3-sigma extent along
the axis reaches it. It also returns which pixels have a pair with q within 1e-4 of the cut
(where float rounding may legitimately flip the mask).

``project_patches`` is the same math written the way one would in torch for speed (a fixed
square patch per Gaussian, scattered with ``index_add_``); the benchmark times it against the
kernels.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from clgs.reference.gaussians import unpack_sym

NEAR_PLANE = 0.2
QCUT = 9.0


def _frame(geometry, view, dtype):
    vec = torch.as_tensor(geometry.view_vectors(scene=True, views=[view])[0], dtype=dtype)
    first, det, gu, gv = vec[0:3], vec[3:6], vec[6:9], vec[9:12]
    nv, nu = geometry.nDetector
    det0 = det - (nu - 1) / 2.0 * gu - (nv - 1) / 2.0 * gv  # centre of pixel (0, 0)
    return first, det0, gu, gv


def _pixel_map(geometry, view, dtype):
    """phi(x) = (u, v, depth-like coordinate along the ray) for one point; its Jacobian is T."""
    first, det0, gu, gv = _frame(geometry, view, dtype)
    cone = geometry.mode == "cone"

    def phi(x):
        if cone:
            d = x - first
            m = torch.stack([gu, gv, -d], 1)
            sol = torch.linalg.solve(m, first - det0)  # det0 + u gu + v gv = s + lam d
            return torch.stack([sol[0], sol[1], torch.linalg.vector_norm(d)])
        r = first / torch.linalg.vector_norm(first)
        m = torch.stack([gu, gv, -r], 1)
        sol = torch.linalg.solve(m, x - det0)  # det0 + u gu + v gv = x - t r
        return torch.stack([sol[0], sol[1], (x * r).sum()])

    return phi


def affine_params(means, cov, geometry, view):
    """Per Gaussian: centre (u, v), 2D covariance S2 (N,2,2), mu (N,), visible (N,) bool."""
    from torch.func import jacrev, vmap

    phi = _pixel_map(geometry, view, means.dtype)
    centre = vmap(phi)(means)[:, :2]
    T = vmap(jacrev(phi))(means)  # (N, 3, 3)
    S = unpack_sym(cov)
    S3 = T @ S @ T.transpose(1, 2)
    S2 = S3[:, :2, :2]
    det2 = torch.linalg.det(S2)
    det3 = torch.linalg.det(S3)
    visible = (det2 > 0) & (det3 > 0)
    if geometry.mode == "cone":
        first, det0, gu, gv = _frame(geometry, view, means.dtype)
        n = torch.linalg.cross(gu, gv)
        n = n / torch.linalg.vector_norm(n)
        if ((det0 - first) @ n) < 0:
            n = -n
        tz = (means - first) @ n
        sw2 = torch.einsum("i,nij,j->n", n, S, n)
        visible &= (tz > NEAR_PLANE) & (tz * tz > 9.0 * sw2)
    mu = torch.sqrt(2 * math.pi * torch.where(visible, det3 / det2, torch.ones_like(det2)))
    return centre, S2, mu, visible


def project_dense(means, mats, densities, geometry, views, mode="affine", chunk=1 << 21):
    """(len(views), V, U) projections and a bool mask of pixels near a cut boundary."""
    dtype = means.dtype
    nv, nu = geometry.nDetector
    iu = torch.arange(nu, dtype=dtype)
    iv = torch.arange(nv, dtype=dtype)
    V_, U_ = torch.meshgrid(iv, iu, indexing="ij")
    pix = torch.stack([U_.reshape(-1), V_.reshape(-1)], 1)  # (P, 2) as (u, v)
    n = means.shape[0]
    step = max(1, chunk // max(pix.shape[0], 1))
    outs, masks = [], []
    for view in views:
        img = torch.zeros(pix.shape[0], dtype=dtype)
        near = torch.zeros(pix.shape[0], dtype=torch.bool)
        if mode == "affine":
            centre, S2, mu, vis = affine_params(means, mats, geometry, view)
            C = torch.linalg.inv(torch.where(vis[:, None, None], S2, torch.eye(2, dtype=dtype)))
            for s in range(0, n, step):
                d = pix[:, None, :] - centre[None, s:s + step]  # (P, n, 2)
                q = torch.einsum("pni,nij,pnj->pn", d, C[s:s + step], d)
                keep = (q <= QCUT) & vis[None, s:s + step]
                val = densities[s:s + step] * mu[s:s + step] * torch.exp(-0.5 * q)
                img = img + torch.where(keep, val, torch.zeros_like(val)).sum(1)
                near |= ((q - QCUT).abs() < 1e-4 * QCUT).any(1)
        else:
            o, r = geometry.rays(view, scene=True)
            o = torch.as_tensor(o.reshape(-1, 3), dtype=dtype)
            r = torch.as_tensor(r.reshape(-1, 3), dtype=dtype)
            P = unpack_sym(mats)
            for s in range(0, n, step):
                e = o[:, None, :] - means[None, s:s + step]  # (P, n, 3)
                Pr = torch.einsum("nij,pj->pni", P[s:s + step], r)
                a = (Pr * r[:, None, :]).sum(-1)
                b = (Pr * e).sum(-1)
                w = e - (b / a)[..., None] * r[:, None, :]  # closest-point residual
                q = torch.einsum("pni,nij,pnj->pn", w, P[s:s + step], w)
                val = densities[s:s + step] * torch.sqrt(2 * math.pi / a) * torch.exp(-0.5 * q)
                if geometry.mode == "cone":
                    val = val * 0.5 * torch.special.erfc(b / torch.sqrt(2 * a))
                keep = q <= QCUT
                img = img + torch.where(keep, val, torch.zeros_like(val)).sum(1)
                near |= ((q - QCUT).abs() < 1e-4 * QCUT).any(1)
        outs.append(img.reshape(nv, nu) / geometry.scale)
        masks.append(near.reshape(nv, nu))
    return torch.stack(outs), torch.stack(masks)


def exact_quadrature(means, prec, densities, geometry, view, n_steps=2001, n_sigma=8.0):
    """Exact-mode reference by trapezoid integration along every ray (float64 NumPy), no 3-sigma
    cut: per-Gaussian images (N, V, U). Each ray is sampled over +-n_sigma of the Gaussian's
    largest standard deviation around the point nearest its centre (cone: never before the
    source), so the sampling is fine whatever the scene size."""
    o, r = geometry.rays(view, scene=True)
    o = o.reshape(-1, 3)
    r = r.reshape(-1, 3)
    P = unpack_sym(torch.as_tensor(np.asarray(prec), dtype=torch.float64)).numpy()
    mu = np.asarray(means, np.float64)
    rho = np.asarray(densities, np.float64)
    u = np.linspace(-1.0, 1.0, n_steps)
    out = np.zeros((mu.shape[0], o.shape[0]))
    for i in range(mu.shape[0]):
        smax = 1.0 / np.sqrt(np.linalg.eigvalsh(P[i])[0])
        tc = ((mu[i] - o) * r).sum(1)
        lo, hi = tc - n_sigma * smax, tc + n_sigma * smax
        if geometry.mode == "cone":
            lo = np.maximum(lo, 0.0)
            hi = np.maximum(hi, 0.0)
        t = lo[:, None] + (hi - lo)[:, None] * 0.5 * (u[None, :] + 1.0)  # (P, T)
        x = o[:, None, :] + t[..., None] * r[:, None, :] - mu[i]
        q = np.einsum("pti,ij,ptj->pt", x, P[i], x)
        out[i] = rho[i] * np.trapezoid(np.exp(-0.5 * q), t, axis=1)
    return out.reshape(-1, *geometry.nDetector) / geometry.scale


def ray_min_q(means, prec, geometry, view):
    """(N, V, U) float64: each Gaussian's smallest squared Mahalanobis distance along every pixel's
    ray (over the whole line), the quantity the kernels' 3-sigma cut tests; computed here on its
    own, in plain NumPy, so tests can apply the cut independently of the kernels."""
    o, r = geometry.rays(view)
    P = unpack_sym(torch.as_tensor(prec, dtype=torch.float64)).numpy()
    mu = np.asarray(means, np.float64)
    qs = []
    for i in range(mu.shape[0]):
        e = o - mu[i]
        a = np.einsum("vui,ij,vuj->vu", r, P[i], r)
        b = np.einsum("vui,ij,vuj->vu", r, P[i], e)
        w = e - (b / a)[..., None] * r
        qs.append(np.einsum("vui,ij,vuj->vu", w, P[i], w))
    return np.stack(qs)


def project_patches(means, mats, densities, geometry, view, mode="affine", radius=None):
    """One view in plain torch, the fast way: every Gaussian evaluates a (2R+1)^2 patch around its
    projected centre (R from the largest 3-sigma radius) and the patches are summed into the
    image with ``index_add_``. Same per-pixel formulas and cut as the kernels (the exact cone
    mode without the erfc factor of Gaussians straddling the source, which benchmarks do not
    have). Differentiable by autograd."""
    dtype = means.dtype
    nv, nu = geometry.nDetector
    first, det0, gu, gv = _frame(geometry, view, dtype)
    if mode == "affine":
        centre, S2, mu, vis = affine_params(means, mats, geometry, view)
        det2 = S2[:, 0, 0] * S2[:, 1, 1] - S2[:, 0, 1] ** 2
        k0, k1, k2 = S2[:, 1, 1] / det2, -S2[:, 0, 1] / det2, S2[:, 0, 0] / det2
        amp = densities * mu * vis
        rad = 3 * torch.sqrt(torch.stack([S2[:, 0, 0], S2[:, 1, 1]], 1))
    else:
        P = unpack_sym(mats)
        phi = _pixel_map(geometry, view, dtype)
        from torch.func import vmap

        centre = vmap(phi)(means.detach())[:, :2]
        rad = torch.full_like(centre, float(radius or 4))
        amp = densities
    R = int(radius or max(1, math.ceil(float(rad.detach().max()))))
    off = torch.arange(-R, R + 1, dtype=dtype)
    base = torch.round(centre.detach())
    pu = base[:, 0:1, None] + off[None, None, :]  # (N,1,K)
    pv = base[:, 1:2, None] + off[None, :, None]  # (N,K,1)
    inside = (pu >= 0) & (pu <= nu - 1) & (pv >= 0) & (pv <= nv - 1)
    if mode == "affine":
        du = pu - centre[:, 0, None, None]
        dv = pv - centre[:, 1, None, None]
        q = k0[:, None, None] * du * du + 2 * k1[:, None, None] * du * dv + k2[:, None, None] * dv * dv
        val = amp[:, None, None] * torch.exp(-0.5 * q)
    else:
        pix = det0 + pu[..., None] * gu + pv[..., None] * gv  # (N,K,K,3)
        if geometry.mode == "cone":
            o = first.expand_as(pix)
            r = pix - first
            r = r / torch.linalg.vector_norm(r, dim=-1, keepdim=True)
        else:
            o = pix
            r = (first / torch.linalg.vector_norm(first)).expand_as(pix)
        e = o - means[:, None, None, :]
        Pr = torch.einsum("nij,nabj->nabi", P, r)
        a = (Pr * r).sum(-1)
        b = (Pr * e).sum(-1)
        w = e - (b / a)[..., None] * r
        q = torch.einsum("nabi,nij,nabj->nab", w, P, w)
        val = amp[:, None, None] * torch.sqrt(2 * math.pi / a) * torch.exp(-0.5 * q)
    keep = inside & (q <= QCUT)
    val = torch.where(keep, val, torch.zeros_like(val))
    idx = (pv.clamp(0, nv - 1) * nu + pu.clamp(0, nu - 1)).long().expand_as(val)
    img = torch.zeros(nv * nu, dtype=dtype).index_add_(0, idx.reshape(-1), val.reshape(-1))
    return img.reshape(nv, nu) / geometry.scale
