"""Build a shape model and density atlas from a population: register, PCA, atlas, one file.

1. Each subject's surface is turned into a signed distance and registered to the template
   (:func:`clgs.shape.registration.register`), giving a velocity field v_i on the model grid.
2. PCA (SVD) of the velocity fields; their compactness, leave-one-out generalisation and
   specificity, measured at the template's surface (:func:`clgs.shape.statistics.field_space_figures`);
   the mode count from them (:func:`clgs.shape.modes.choose_modes`: the fewest modes holding
   ``variance`` of the total or past which generalisation improves by less than
   ``generalisation_tol_mm``; exactly ``n_modes`` when given).
3. Density atlas: each subject's CT pulled back into template space, ``CT_i(exp(v_i)(x))`` (the
   CT pushed forward by the inverse map exp(-v_i)), then the per-voxel mean and (population)
   variance over subjects, on the template grid.
4. One versioned npz (see :mod:`clgs.shape.model`) with the population ids, settings and
   their hash, variance kept, residuals, the figures (``statistics``) and the mode decision
   (``mode_choice``), all JSON in its metadata record, and the covariance of what lies beyond the
   kept modes for a left-out subject (``beyond_cov``, :func:`beyond_span_covariance`).

Caching: if ``out_path`` exists with the same settings hash the build is skipped. Resuming:
each subject's registration (and warped CT) is saved atomically in ``<out_path>.cache/``
as soon as it is done, keyed by the subject's content and the registration settings; a
build that was interrupted picks up where it stopped. The cache is removed after a
successful build unless ``keep_cache``.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable, Iterable, Mapping

import numpy as np

from clgs.errors import InputError
from clgs.shape.template import (
    Subject,
    Template,
    box_grid,
    grid_points,
    json_array,
    json_from_array,
    mesh_to_sdf,
    save_npz_atomic,
)

# 2: the atlas samples a CT with its border value past its grid (was air)
# 3: the mode count from the population's figures (clgs.shape.modes), the figures stored
BUILDER_VERSION = 3


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def _subject_items(subjects):
    """(id, loader) pairs from a sequence of Subjects or a mapping id -> Subject | loader."""
    if isinstance(subjects, Mapping):
        items = []
        for sid, s in subjects.items():
            items.append((str(sid), s if callable(s) else (lambda s=s: s)))
        return items
    items = []
    for s in subjects:
        if not isinstance(s, Subject):
            raise TypeError("subjects must be clgs.shape.template.Subject objects (or a mapping id -> loader), "
                            f"got {type(s)}")
        items.append((s.id, lambda s=s: s))
    return items



def _safe(sid: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in sid)


def template_distance(template: Template, max_cells: int) -> np.ndarray:
    """The template's distance from its own surface on the model grid, computed exactly as the
    subjects' are (resampling template.sdf would add interpolation differences)."""
    mshape, msp, morg = template.model_grid(max_cells)
    return mesh_to_sdf(template.vertices, template.faces, mshape, msp, morg)


def read_cache_entry(path, sid: str, mshape) -> dict | None:
    """A subject's cached registration (arrays by name), or None when absent, damaged or stale."""
    if not os.path.exists(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            record = {k: z[k] for k in z.files}
        meta = json_from_array(record["metadata"])
        if meta.get("id") != sid or tuple(record["velocity"].shape) != (3,) + tuple(mshape):
            return None
    except Exception:  # a damaged cache entry is simply redone
        return None
    return record


def register_subject(template: Template, subject: Subject, sid: str, path, max_cells: int, reg, atlas: bool,
                     threads: int | None = 1, fixed: np.ndarray | None = None) -> dict:
    """Register one subject to the template and write its cache entry ``path`` atomically (velocity,
    the CT pulled back into template space when ``atlas``, metadata); returns the entry. The same
    wherever it runs: a build's worker processes call it with the build's settings."""
    import torch

    from clgs.shape.model import exp_velocity, sample_field
    from clgs.shape.registration import RegistrationSettings, register

    reg = reg if isinstance(reg, RegistrationSettings) else RegistrationSettings.from_dict(reg)
    mshape, msp, morg = template.model_grid(max_cells)
    if fixed is None:
        fixed = template_distance(template, max_cells)
    if subject.id != sid:
        raise InputError(f"loader for {sid!r} returned subject {subject.id!r}")
    lo = np.minimum(subject.vertices.min(0), template.bounds()[0]) - 4 * msp[0]
    hi = np.maximum(subject.vertices.max(0), template.bounds()[1]) + 4 * msp[0]
    gshape, gsp, gorg = box_grid(lo, hi, spacing=msp[0])
    moving = subject.sdf_on(gshape, gsp, gorg)
    result = register(fixed, msp, morg, moving, gsp, gorg, settings=reg, surface_points=template.vertices,
                      threads=threads)
    record = {"velocity": result.velocity}
    if atlas and subject.volume is not None:
        tpoints = grid_points(template.shape, template.spacing, template.origin).reshape(-1, 3)
        with torch.no_grad():
            u = exp_velocity(torch.as_tensor(result.velocity), msp)
            p = torch.as_tensor(tpoints, dtype=torch.float32)
            mapped = (p + sample_field(u, p, msp, morg)).numpy()
        # a CT grid ends where the scan did, not where the body does: points warped past
        # its border take the border value (clamped), not air, which would inflate the
        # atlas variance in the template's first and last slices
        record["warped_ct"] = subject.volume_at(mapped, fill=None).reshape(template.shape)
    record["metadata"] = json_array({"id": sid, "residuals": result.residuals,
                                      "subject_hash": subject.content_hash()})
    save_npz_atomic(path, record)
    return record


def population_pca(velocities: np.ndarray, variance: float | None = 0.95, n_modes: int | None = None):
    """PCA of flattened fields (n, D): (mean (D,), modes (M, D) orthonormal, sigma (M,), explained
    fraction of the total variance kept, all singular variances).

    sigma is the standard deviation of the scores (divisor n - 1), so alpha ~ N(0, I)."""
    X = np.asarray(velocities, np.float64)
    n = X.shape[0]
    if n < 2:
        raise InputError(f"PCA needs at least 2 subjects, got {n}")
    mean = X.mean(0)
    _, s, vt = np.linalg.svd(X - mean, full_matrices=False)
    var = s ** 2 / (n - 1)
    total = var.sum()
    keep = var > max(total, 1e-30) * 1e-12
    var, vt = var[keep], vt[keep]
    if n_modes is not None:
        if n_modes < 1:
            raise InputError(f"n_modes must be >= 1, got {n_modes}")
        m = min(int(n_modes), len(var))
    else:
        if variance is None or not (0 < variance <= 1):
            raise InputError(f"variance must be in (0, 1], got {variance}")
        if len(var) == 0:
            m = 0
        else:
            frac = np.cumsum(var) / total
            m = int(np.searchsorted(frac, variance - 1e-12) + 1)
            m = min(m, len(var))
    if m == 0:  # identical subjects: a model with no variation
        return mean, np.zeros((0, X.shape[1])), np.zeros(0), 1.0, var
    kept = float(var[:m].sum() / total) if total > 0 else 1.0
    return mean, vt[:m], np.sqrt(var[:m]), kept, var


#: the figures are measured at up to this many of the template's surface vertices (evenly spread)
FIGURE_POINTS = 4000


def surface_measure(template: Template, mshape, msp, morg, max_points: int = FIGURE_POINTS):
    """A linear map from flattened velocity fields (k, 3 * Z * Y * X) on the model grid to their
    values (k, P * 3) mm at the template's surface vertices (at most ``max_points``, evenly
    spread; trilinear): what moves the surface, where the model's figures are measured."""
    import torch

    from clgs.fit.fixed_points import FixedPointSampler

    pts = np.asarray(template.vertices, np.float64)
    pts = pts[np.linspace(0, len(pts) - 1, min(len(pts), max_points)).astype(int)]
    vox = (pts - np.asarray(morg, float)[::-1]) / np.asarray(msp, float)[::-1]
    sampler = FixedPointSampler(vox, tuple(mshape), torch.float64)

    def measure(rows):
        rows = np.asarray(rows, np.float64)
        fields = torch.as_tensor(rows.reshape(len(rows), 3, *mshape))
        return np.stack([sampler(f).numpy().reshape(-1) for f in fields])

    return measure


def model_figures(V, template, mshape, msp, morg, variance, tolerance_mm, n_modes, max_modes: int = 10):
    """(figures, mode choice, variance spectrum) of velocity fields V (N, D): the figures of
    :func:`clgs.shape.statistics.field_space_figures` measured at the template's surface (None
    with fewer than 3 subjects) plus ``compactness_all`` (every mode's cumulative share) and
    where they were measured; the choice of :func:`clgs.shape.modes.choose_modes`."""
    from clgs.shape.modes import choose_modes
    from clgs.shape.statistics import field_space_figures

    _, _, _, _, all_var = population_pca(V, variance=1.0)
    total = float(all_var.sum())
    compact_all = [float(c) for c in np.cumsum(all_var) / total] if total > 0 else []
    figures = None
    if len(V) >= 3 and len(all_var):
        measure = surface_measure(template, mshape, msp, morg)
        figures = field_space_figures(V, measure, max_modes=max_modes, n_samples=100)
        n_points = min(len(template.vertices), FIGURE_POINTS)
        figures.update(compactness_all=compact_all,
                       measured_at=f"{n_points} of the template's {len(template.vertices)} surface vertices")
    choice = choose_modes(figures or {"compactness_all": compact_all}, len(all_var), variance, tolerance_mm,
                          n_modes)
    return figures, choice, all_var


def beyond_span_covariance(V, n_modes: int, mshape) -> np.ndarray | None:
    """(6, Z, Y, X) float32 mm^2: per grid point, the covariance (xx, yy, zz, xy, xz, yz) of the
    part of a left-out subject's velocity field that the ``n_modes``-mode PCA of the others does
    not reach (leave-one-out over the rows of V (N, 3 * Z * Y * X)): what lies beyond the model's
    span for a new member of the population. None with fewer than 3 subjects."""
    X = np.asarray(V, np.float64)
    n = len(X)
    if n < 3:
        return None
    acc = np.zeros((6,) + tuple(mshape))
    for i in range(n):
        rest = np.delete(X, i, 0)
        m = rest.mean(0)
        vt = np.linalg.svd(rest - m, full_matrices=False)[2][:n_modes]
        r = (X[i] - m) - ((X[i] - m) @ vt.T) @ vt
        r = r.reshape((3,) + tuple(mshape))
        for k, (a, b) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
            acc[k] += r[a] * r[b] / n
    return acc.astype(np.float32)


def build_model(template, subjects, out_path, *args, **kwargs) -> str:
    """:func:`_build_model` holding the model file's lock (:mod:`clgs.io.outputs`): a second build
    of the same file started meanwhile waits for the first, then finds its model up to date."""
    import contextlib

    from clgs.io.outputs import lock

    with contextlib.ExitStack() as held:
        # a folder that takes no lock file (read-only): an up-to-date model is still read
        with contextlib.suppress(OSError):
            held.enter_context(lock(out_path, "the model file", wait=True))
        from clgs.progress import enabled

        held.enter_context(enabled(kwargs.get("progress", True)))  # progress=False: no phase lines either
        return _build_model(template, subjects, out_path, *args, **kwargs)


def _build_model(template: Template, subjects: Iterable[Subject] | Mapping, out_path,
                variance: float = 0.95, n_modes: int | None = None, max_cells: int = 64,
                generalisation_tol_mm: float | None = 0.05,
                registration: dict | None = None, atlas: bool = True, force: bool = False,
                keep_cache: bool = False, progress: bool = True, extra_meta: dict | None = None,
                on_subject: Callable | None = None, threads: int | None = 1,
                run_registrations: Callable | None = None) -> str:
    """Register every subject to the template, PCA the velocities, average the CTs; write one file.

    template: the reference :class:`Template`. subjects: Subjects, or a mapping id -> Subject or
    zero-argument loader (loaded one at a time; only loaded when not cached).
    out_path: the model file (.npz). variance, generalisation_tol_mm, n_modes: the mode rule
    (:func:`clgs.shape.modes.choose_modes`; n_modes wins, a tolerance of None or 0 leaves the
    variance rule alone).
    max_cells: model grid cells along the template box's longest side. registration: keyword
    settings of :class:`clgs.shape.registration.RegistrationSettings`. atlas: build the density atlas
    from subjects' CT volumes (skipped with a note when no subject has one). force: rebuild even
    if an up-to-date file exists. on_subject(i, id): called after each subject (tests use it).
    threads: torch threads per registration (1: small fields, and a shared machine).
    run_registrations(jobs): registers the subjects not cached yet elsewhere (e.g. as tasks on a
    Dask cluster, :mod:`clgs.cohort.registration`): each job (a dict: id, cache_path, max_cells,
    registration, atlas, threads, template_hash) is done by :func:`register_subject` on the same
    template and writes its cache entry; the build then reads them. Returns out_path.

    Long because it is the pipeline's script: cache check, registration of every subject,
    PCA, atlas and metadata, each a call to a helper, with progress and caching around them.
    """
    from clgs.progress import progress_bar
    from clgs.shape.model import DensityAtlas, ModelFileError, ShapeModel, read_metadata, save_model
    from clgs.shape.registration import RegistrationSettings

    out_path = os.fspath(out_path)
    items = _subject_items(subjects)
    ids = [sid for sid, _ in items]
    if len(set(ids)) != len(ids):
        raise InputError(f"subject ids must be unique, got {ids}")
    if len(items) < 2:
        raise InputError(f"a shape model needs at least 2 subjects, got {len(items)}")
    reg = RegistrationSettings.from_dict(registration)
    from clgs.shape.modes import choose_modes

    choose_modes(None, 1, variance, generalisation_tol_mm, n_modes)  # a bad rule fails now, not after the work
    mshape, msp, morg = template.model_grid(max_cells)
    reg_key = {"builder": BUILDER_VERSION, "template": template.content_hash(), "max_cells": int(max_cells),
               "registration": reg.to_dict(), "atlas": bool(atlas)}
    settings = dict(reg_key, population=ids, variance=None if n_modes is not None else float(variance),
                    n_modes=None if n_modes is None else int(n_modes),
                    generalisation_tol_mm=None if n_modes is not None or not generalisation_tol_mm
                    else float(generalisation_tol_mm))
    settings_hash = _hash(settings)

    if not force and os.path.exists(out_path):  # up to date: nothing to do
        try:
            if read_metadata(out_path).get("settings_hash") == settings_hash:
                return out_path
        except ModelFileError:
            pass  # unreadable or another format: rebuild

    cache = out_path + ".cache"
    os.makedirs(cache, exist_ok=True)
    reg_hash = _hash(reg_key)
    fixed = template_distance(template, max_cells)
    velocities, residuals, warped_sum, warped_sq, n_ct = [], {}, None, None, 0
    paths = {sid: os.path.join(cache, f"{_safe(sid)}-{reg_hash}.npz") for sid, _ in items}
    if run_registrations is not None:
        missing = [sid for sid, _ in items if read_cache_entry(paths[sid], sid, mshape) is None]
        if missing:  # elsewhere (e.g. worker processes), each writing its cache entry
            run_registrations([{"id": sid, "cache_path": paths[sid], "max_cells": int(max_cells),
                                "registration": reg.to_dict(), "atlas": bool(atlas), "threads": threads,
                                "template_hash": template.content_hash()} for sid in missing])
    bar = progress_bar(items, desc=f"registering to {template.name or 'template'}", unit="subject",
                       disable=not progress)
    for i, (sid, loader) in enumerate(bar):
        path = paths[sid]
        record = read_cache_entry(path, sid, mshape)
        if record is None:
            record = register_subject(template, loader(), sid, path, max_cells, reg, atlas, threads, fixed=fixed)
        meta = json_from_array(record["metadata"])
        velocities.append(np.asarray(record["velocity"], np.float32).reshape(-1))
        residuals[sid] = meta["residuals"]
        if "warped_ct" in record:
            w = np.asarray(record["warped_ct"], np.float64)
            warped_sum = w if warped_sum is None else warped_sum + w
            warped_sq = w * w if warped_sq is None else warped_sq + w * w
            n_ct += 1
        if progress:
            bar.set_postfix(surface_mm=f"{meta['residuals'].get('surface_mean_mm', float('nan')):.2f}")
        if on_subject is not None:
            on_subject(i, sid)

    V = np.stack(velocities)
    figures, choice, all_var = model_figures(V, template, mshape, msp, morg, variance, generalisation_tol_mm,
                                             n_modes)
    mean, modes, sigma, kept, all_var = population_pca(V, n_modes=choice["n_modes"]) if choice["n_modes"] else \
        population_pca(V, variance=1.0)
    # how well the kept modes reproduce each training field (mm, RMS over the grid)
    C = V.astype(np.float64) - mean
    recon = C @ modes.T @ modes if len(modes) else np.zeros_like(C)
    pca_rms = np.sqrt(((C - recon) ** 2).reshape(len(V), -1, ).mean(1))
    for sid, r in zip(ids, pca_rms):
        residuals[sid]["pca_rms_mm"] = float(r)
    model = ShapeModel(mean.reshape(3, *mshape), modes.reshape(-1, 3, *mshape), sigma, msp, morg,
                       beyond_cov=beyond_span_covariance(V, len(modes), mshape))
    density = None
    if atlas and n_ct:
        m = warped_sum / n_ct
        var = np.maximum(warped_sq / n_ct - m * m, 0.0)
        var[var < 1e-12 * max(float(np.abs(m).max()) ** 2, 1e-30)] = 0.0  # round-off of identical inputs
        density = DensityAtlas(m.astype(np.float32), var.astype(np.float32), template.spacing, template.origin)
    meta = dict(extra_meta or {})
    meta.update(population=ids, settings=settings, settings_hash=settings_hash, variance_kept=kept,
                variance_spectrum=[float(x) for x in all_var], residuals=residuals, template_name=template.name,
                statistics=figures, mode_choice=choice,
                template_hash=template.content_hash(), atlas_subjects=n_ct,
                atlas_note="" if (density is not None or not atlas) else "no subject had a CT volume: no atlas")
    save_model(out_path, model, density, meta)
    if not keep_cache:
        shutil.rmtree(cache, ignore_errors=True)
    return out_path


build_model.__wrapped__ = _build_model
build_model.__doc__ = f"{build_model.__doc__}\n\n{_build_model.__doc__}"
