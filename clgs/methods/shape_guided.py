"""Shape-guided Gaussian splatting (Poudel et al.): Gaussians bound to an anatomy's shape model.

Two sets of Gaussians are optimised together against the projections:

* ``shape`` (Gs): laid out on the template (:mod:`clgs.shape.initialise`); their centres follow the
  shape model, ``p_j = p_ref_j + u(alpha)(p_ref_j)`` with ``u = exp(v(alpha)) - id``, so one
  vector ``alpha`` of mode coefficients moves all of them at once and keeps the bone a plausible
  bone. Their scale, rotation and density are free. They are never densified.
* ``free`` (Gz): R2-Gaussian's Gaussians (densified, every parameter free) for everything the
  anatomy's bone does not explain. With a density atlas they start on the atlas's tissue around
  the template's bone (``free_init="atlas"``, :func:`clgs.shape.initialise.initialise_surroundings`);
  otherwise (or ``"fdk"``) on the FDK volume outside the template's bone, as R2-Gaussian does.

Before training, alpha is registered to the projections with everything else fixed
(:func:`fit_initial_alpha`, ``alpha_init_iterations``); the paper starts from alpha = 0, from
where the other parameters absorb the shape difference before alpha can move.

Loss: ``L1 + 0.25 D-SSIM + 0.05 TV + lambda_shape |alpha|^2 + lambda_density L_density`` (the
paper's ``lambda_shape`` is 1e-4; the default is 0, see :data:`PAPER_LAMBDA_SHAPE`) with
``L_density = mean_x m(x) w(x) (V(x) - atlas_mean(x'))^2``, ``w = exp(-atlas_var(x') / s^2)``,
over a random strided sub-grid covering the volume (a fresh offset every iteration), ``x'`` the
point carried back into the template by the current deformation (two fixed-point steps of
``x' = x - u(x')``). ``density_prior_field="all"`` (default): ``V`` is the whole model's field
and ``m = 1`` (the atlas holds the tissue around the bone too; an atlas of the bone alone falls
back to ``"shape"``); ``"shape"``: ``V = V_s`` the field of the shape set alone and ``m`` the
template's bone mask at ``x'``, the paper's form.

The bone's size is fitted with alpha (``fit_size="on"``, :mod:`clgs.shape.size`): a search over
sizes against the projections gives its start, the registration and training refine it.
``"off"`` is the paper's form. Where these choices depart from the paper, and what each gave on
the femur: docs/methods.md.

The scan's world frame is taken to be the template's frame (the anatomy's own simulator scans in
it; a user's mesh is aligned to the template first). The ablation switches: ``shape_prior=False``
turns the shape set into ordinary free-moving Gaussians (positions learnt directly, "density init
only"); ``density_prior=False`` drops ``L_density``.

Units are those of :mod:`clgs.methods.r2gs` (training units: scene lengths, values x ``value_scale``);
the atlas is converted the same way.
"""
from __future__ import annotations

import dataclasses
import functools
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from clgs.anatomy import AnatomyParts, plugins
from clgs.anatomy.bone_level import choose_level, with_closing
from clgs.anatomy.evaluation import LEVEL_KEYS, bone_surface, write_bone_surface
from clgs.errors import InputError
from clgs.fit import losses as L
from clgs.fit.assembly import (
    fdk_volume,
    make_trainer,
    projection_losses,
    restore,
    scale_bounds_for,
    value_scale_from,
    volume_box,
)
from clgs.fit.config import GaussianFitConfig, run_config, run_folder, setting
from clgs.fit.estimate import run_clock
from clgs.fit.gaussians import GaussianSet, Schedule, init_from_volume, r2gs_schedules
from clgs.fit.outputs import gaussians_in_scan_units, voxelize_volume
from clgs.fit.outputs import write_outputs as write_common
from clgs.fit.trainer import Backend, LossTerm, Trainer
from clgs.fit.training_log import TrainingLog
from clgs.io import atomic
from clgs.io.mesh import load_mesh, save_mesh
from clgs.io.scan import Scan
from clgs.methods import Method, Option
from clgs.methods.gaussian import RUN_OPTIONS, method_output
from clgs.ops.field_sampler import default_sampler
from clgs.progress import enabled, phase
from clgs.shape.gaussian_set import ShapeGuidedSet
from clgs.shape.initialise import ShapeInit, initialise, initialise_surroundings, sample_surrounding_centres
from clgs.shape.priors import DensityPrior, random_subgrid, residual_prior_term, shape_prior_term
from clgs.shape.size import (
    AUTO_TOLERANCE,
    LEG_AXIS,
    LENGTH_GAIN,
    search_size,
    search_size_and_length,
    size_centre,
    stretched_bone,
    stretched_surroundings,
)

# The paper's weight of the shape prior |alpha|^2. Against a loss that is a mean over one view's
# pixels it is not a prior of the views' likelihood but a pull of its own: once the densities and
# the free Gaussians have taken up the shape difference, the views' gradient on alpha is small and
# the pull, stepped at Adam's full rate, draws alpha back towards the mean shape (on the femur, AP +
# lateral: alpha from (-0.50, -0.14, 0.35) after the registration to (-0.02, -0.02, -0.01) after
# 1000 iterations, the model surface 1.17 -> 1.47 mm from the truth; at 0, (-0.95, -0.20, 0.83) and
# 0.98 mm). As a Bayesian prior, N(0, I) weighs against the likelihood of every pixel of every view
# (the surface's Laplace posterior, clgs.shape.uncertainty, pins alpha to +-0.005 from two views):
# on a mean over pixels that is a weight orders of magnitude below 1e-4. Hence 0 by default;
# docs/methods.md has the figures.
PAPER_LAMBDA_SHAPE = 1e-4


@dataclass
class ShapeGuidedConfig(GaussianFitConfig):
    """The paper's defaults (35k shape-guided + 15k free Gaussians, 30k iterations); the settings
    shared with R2-Gaussian mode (densification, loss weights, ...) are :class:`GaussianFitConfig`'s."""

    n_shape: int = setting(35_000, "--shape-gaussians", "shape-guided Gaussians", min=1)
    n_free: int = setting(15_000, "--free-gaussians", "free (R2-Gaussian) Gaussians at the start")
    tau: float = setting(0.5, "--tau", "thinning along the surface normal", max=1)
    boundary_weight: float = 4.0
    # bind the shape set to the shape model (False: "density init only")
    shape_prior: bool = setting(True, "--shape-prior",
                                "bind the shape-guided Gaussians to the shape model")
    density_prior: bool = setting(True, "--density-prior", "atlas density prior")
    # "atlas": the atlas's tissue around the bone; "fdk": R2-Gaussian's FDK start
    free_init: str = setting("atlas", "--free-init",
                             "start the free Gaussians on the atlas's tissue around the bone, or on the FDK")
    # the tissue the registration holds fixed around the bone: "free" the free set's start (the
    # run's own), "fdk" the FDK outside the template's bone (the run still trains from its own),
    # "auto" the FDK's where the views cover a half-turn (registration_tissue)
    register_tissue: str = setting("auto", "--register-tissue",
                                   "tissue held fixed around the bone while alpha (and the size) are registered: "
                                   "the free Gaussians' start (free), the FDK outside the template's bone (fdk), or "
                                   "auto: fdk where no two neighbouring views are more than 40 degrees apart, "
                                   "free otherwise")
    # with the FDK's tissue: registrations in a row, each from the one before, each after the first
    # holding the FDK outside the bone where the template's and every fitted one so far (grown by
    # pass_hole_margin_mm) agree (fit_alpha_in_passes says why; docs/results.md has the figures:
    # 3 brings every held-out femur under 1 mm at 5 views and leaves the out-of-span ones as one
    # pass did; 1: the registration before passes existed)
    register_passes: int = 3
    # how far (mm, the template's frame) outside a fitted bone a later pass still leaves the FDK out
    # of the tissue it holds (_free_init_volume; 0: the hole follows the fitted bones' surfaces,
    # as the passes first did)
    pass_hole_margin_mm: float = 3.0
    # alpha-only registration before training (0: start at alpha = 0)
    alpha_init_iterations: int = setting(100, "--alpha-init-iterations",
                                         "iterations registering alpha to the projections before training "
                                         "(0: alpha = 0)")
    # "all": the whole model against the atlas; "shape": Gs in the bone
    density_prior_field: str = setting("all", "--density-prior-field",
                                       "field held to the atlas: the whole model, or the shape-guided Gaussians inside "
                                       "the bone (the paper)")
    # a size fitted with alpha (clgs.shape.size): "on" always, "auto" only when the projections say
    # the bone is beyond the model's sizes (more than 10 % from them), "off" never (the paper)
    fit_size: str = setting("on", "--fit-size",
                            "fit the bone's size with its shape: on, auto (only when the projections show a bone "
                            "more than 10% larger or smaller than the model's), off (the paper)")
    # a length of the bone's own along the leg, searched with the size (clgs.shape.size
    # .search_size_and_length) and held through the fit: "auto" takes it where the size is fitted
    # and the length lowers the search's L1 by more than LENGTH_GAIN (3 %), "on" (needs fit_size
    # "on") wherever it lowers it at all, "off" the one size (docs/methods.md, "The bone's length")
    fit_length: str = setting("auto", "--fit-length",
                              "fit a length of the bone's own along the leg with its size: auto (only where the "
                              "projections show a bone clearly longer or shorter for its girth than the model's), "
                              "on, off (one size)")
    # the length factor of this run (set by the search with fit_length "auto" or "on", or given:
    # held fixed either way; None: none)
    length_factor: float | None = None
    # a smooth residual deformation beyond the model's span (clgs.shape.residual): "on" registers it
    # after alpha and trains it with everything else; "off" (the paper) keeps the bone in the span;
    # "auto" (residual_for): on where the views cover a half-turn (5 over 180 degrees and more),
    # where it brought the femurs' surfaces closer, off from sparser views (docs/results.md)
    residual: str = setting("auto", "--residual",
                            "a smooth deformation beyond the shape model's span (a cubic B-spline on the template, "
                            "bending-regularised), fitted after the shape coefficients: on, off (the paper), or "
                            "auto: on where no two neighbouring views are more than 40 degrees apart, off otherwise")
    # the limb's outline measured in the views (clgs.shape.limb): "auto" carries the atlas's tissue
    # onto it (the free Gaussians' start and the density prior, which then holds the limb's edge
    # there) where the outline is measured on at least half the scan's slices; "off" the atlas's
    # own limb (the paper)
    limb_outline: str = setting("auto", "--limb-outline",
                                "measure the limb's outline per slice from the views' silhouettes and carry the "
                                "atlas's tissue onto it: auto (where the outline is measured on at least half the "
                                "slices), off (the atlas's own limb, the paper)")
    # the shape surface's per-vertex standard deviation (clgs.shape.uncertainty): written beside it
    uncertainty: str = setting("on", "--uncertainty",
                               "write shape_uncertainty.ply/.vtk: the shape surface's per-vertex standard deviation "
                               "along its normal (mm: the shape coefficients' Laplace posterior with the model's "
                               "leave-one-out spread, or the distance to the volume's bone surface, the larger): "
                               "on, off")
    residual_points: int = setting(16, "--residual-points",
                                   "the residual's control points along the template's longest side", min=4)
    residual_init_iterations: int = 100  # the residual's registration (alpha fixed) before training
    lambda_residual: float = 1e-5  # weight of the residual's prior (per mm^2)
    residual_bending: float = 1.0  # its bending energy's weight against its magnitude (x h^4)
    residual_bending_start: float = 10.0  # the bending weight starts this many times higher, decays to 1x
    lr_residual: float = 0.2  # mm per Adam step (to 10 % over its registration, in training to 1 % by the midpoint)
    # the shape prior's weight, 0 by default (the paper: PAPER_LAMBDA_SHAPE): see there why
    lambda_shape: float = setting(0.0, "--lambda-shape",
                                  "weight of the shape prior |alpha|^2 against the mean projection loss "
                                  "(the paper: 1e-4)")
    lambda_density: float = 0.5
    # the atlas's densities scaled to the scan (clgs.shape.calibration): "fit" a factor for the bone
    # and one for the rest from the registered start's projections, "off" the atlas as it is (the
    # paper); the factors (fitted, or given with --set) are kept in the run's settings, so a resumed
    # run holds the field to the same atlas
    atlas_calibration: str = setting("off", "--atlas-calibration",
                                     "scale the density atlas to the scan: fit one factor for the bone and one for "
                                     "the tissue around it from the registered start's projections (fit), or use "
                                     "the atlas as it is (off, the paper)")
    atlas_bone_factor: float | None = None
    atlas_rest_factor: float | None = None
    density_s: float = 0.05
    density_points: int = 32  # sub-grid points per axis for L_density
    lr_alpha: float = 0.1
    lr_size: float = 0.002  # log-size, with alpha's schedule (0.005 to 10 % in the registration)
    alpha_freeze: int = 50
    lr_density: float = 0.01
    lr_scale: float = 0.005
    lr_rotation: float = 0.01

    CLI = ("iterations", "schedule", "seed", "backend", "projector_mode", "lambda_tv", "lambda_dssim", "log_every",
           "log_early", "checkpoint_every", "max_gaussians", "n_shape", "n_free", "tau", "shape_prior", "density_prior",
           "density_prior_field", "free_init", "register_tissue", "alpha_init_iterations", "fit_size", "fit_length",
           "residual", "residual_points", "limb_outline", "uncertainty", "lambda_shape", "atlas_calibration")
    KIND = "shape-guided"
    FAST_ITERATIONS = 4_000  # the fast schedule's run (clgs.fit.schedule; docs/schedules.md)
    FAST_STOP_EVERY = 250
    CHOICES = {**GaussianFitConfig.CHOICES, "free_init": ("atlas", "fdk"), "register_tissue": ("auto", "free", "fdk"),
               "density_prior_field": ("all", "shape"),
               "fit_size": ("auto", "on", "off"), "fit_length": ("auto", "on", "off"),
               "residual": ("auto", "on", "off"), "uncertainty": ("on", "off"), "limb_outline": ("auto", "off"),
               "atlas_calibration": ("fit", "off")}
    POSITIVE = GaussianFitConfig.POSITIVE | {"tau", "density_s", "atlas_bone_factor", "atlas_rest_factor",
                                             "length_factor"}
    AT_LEAST = {**GaussianFitConfig.AT_LEAST, "density_points": 2, "residual_points": 4, "register_passes": 1}

    def __post_init__(self):
        super().__post_init__()
        # a length is a factor of a fitted size: refused here, before any work, where none is fitted
        if self.fit_size != "on" and (self.fit_length == "on" or self.length_factor is not None):
            what = "fit_length=on" if self.length_factor is None else "a length_factor"
            raise InputError(f"{what} needs fit_size=on (the length is a factor of the size), got fit_size="
                             f"{self.fit_size}; set fit_size=on, or fit_length=auto (the default) to fit a length "
                             "only with a fitted size")


# ---------------------------------------------------------------------- schedules
def shape_schedules(cfg: ShapeGuidedConfig, iterations: int, *, free_means: bool) -> dict:
    """The paper's learning rates for the shape set: alpha 0.1 decaying to 1% by the midpoint and
    frozen for the first ``alpha_freeze`` iterations (a fitted size the same way from ``lr_size``);
    density and scale constant; rotation to 10%."""
    half = max(iterations // 2 - cfg.alpha_freeze, 1)
    sched = {
        "alpha": Schedule(cfg.lr_alpha, cfg.lr_alpha * 0.01, half, start=cfg.alpha_freeze, frozen_before_start=True),
        "log_size": Schedule(cfg.lr_size, cfg.lr_size * 0.01, half, start=cfg.alpha_freeze, frozen_before_start=True),
        "log_length": Schedule(0.0),  # held where the search put it
        "residual": Schedule(cfg.lr_residual, cfg.lr_residual * 0.01, half, start=cfg.alpha_freeze,
                             frozen_before_start=True),
        "densities": Schedule(cfg.lr_density),
        "scales": Schedule(cfg.lr_scale),
        "quats": Schedule(cfg.lr_rotation, cfg.lr_rotation * 0.1, iterations),
    }
    if free_means:
        sched["means"] = r2gs_schedules(iterations, cfg.lr_factor)["means"]
    return sched


# ---------------------------------------------------------------------- priors
@dataclass
class ShapeGuidedResult:
    volume: np.ndarray
    gaussians: dict
    alpha: np.ndarray
    log: TrainingLog
    trainer: Trainer = field(repr=False)
    value_scale: float
    interrupted: bool
    out_dir: Path | None
    summary: str
    seconds: float
    surface: dict | None = None  # the bone surface written (clgs.anatomy.evaluation.write_bone_surface)
    displacement: dict | None = None  # displacement_report: the surface's model and residual parts
    uncertainty: dict | None = None  # the shape surface's uncertainty summary (clgs.shape.uncertainty.summary)


def _free_init_volume(fdk, geometry, template, size=None, centre_mm=None, to_template=None,
                      margin_mm=0.0, length: float = 1.0) -> np.ndarray:
    """The FDK volume with the template's bone blanked out (free Gaussians start outside it); with
    ``size`` > 1, the bone scaled by it about ``centre_mm`` (a larger bone's ends stay blanked);
    with ``to_template`` (a map of points (N, 3) mm to the template's, or a list of them, None in
    it standing for the template's own bone as above), only where every map's bone lies (the bones
    fitted so far: :func:`fit_alpha_in_passes`), a fitted bone's grown by ``margin_mm`` (mm in the
    template's frame). A ``length`` factor stretches the template's bone along the leg as well.

    Why the margin (``pass_hole_margin_mm``, 3): where a fitted bone's surface lies a little inside
    the true bone, a hole that follows it holds the FDK's bone there as tissue, which pushes the
    bone further off (the lengthened shaft of examples/femur_out_of_span.py, 5 views,
    registration alone: 1.25 -> 1.49 mm after three passes; 1.27 with 3 mm); grown, the hole
    shrinks only where a fitted bone lies clearly inside the template's (subject 24's ends: 0.74
    mm after three passes, 1.22 after one; docs/results.md)."""
    pts = geometry.volume_grid(scene=False).points().reshape(-1, 3)
    k = np.full(3, max(float(size or 1.0), 1.0))
    k[LEG_AXIS] *= max(float(length), 1.0)
    maps = to_template if isinstance(to_template, (list, tuple)) else [to_template]
    inside = np.ones(fdk.shape, bool)
    for m in maps:
        if m is not None:
            inside &= template.sdf_at(m(pts)).reshape(fdk.shape) < margin_mm
            continue
        q = centre_mm + (pts - centre_mm) / k if np.any(k > 1.0) else pts
        inside &= template.sdf_at(q).reshape(fdk.shape) < 0
    vol = np.array(fdk, np.float32, copy=True)
    vol[inside] = float(vol.min())
    return vol


#: ``register_tissue="auto"`` registers against the FDK's tissue where no gap between neighbouring
#: views (modulo a half-turn) is wider than this: 5 views over 180 degrees (36) and more; not AP +
#: lateral (90), whose two-view FDK is mostly streaks (docs/methods.md has the figures)
AUTO_FDK_GAP_DEG = 40.0


def widest_view_gap_deg(angles) -> float:
    """The widest angle (degrees) between neighbouring views, their angles taken modulo a half-turn
    (a view and its opposite see the same lines): 180 for a single view."""
    a = np.sort(np.mod(np.degrees(np.asarray(angles, np.float64).reshape(-1)), 180.0))
    if a.size < 2:
        return 180.0
    return float(np.max(np.diff(np.concatenate([a, [a[0] + 180.0]]))))


def registration_tissue(choice: str, angles) -> str:
    """The tissue the registration holds for the setting ``choice`` on a scan of views at ``angles`` (radians):
    ``"free"`` or ``"fdk"`` as given; ``"auto"`` the FDK's where the views leave no gap wider than
    :data:`AUTO_FDK_GAP_DEG`, the free set's start otherwise.

    Why: the atlas's tissue has a hole the template's bone's shape, and a bone shorter than the
    template is fitted long to fill it (subject 24, 405 mm, 5 views: 421 mm, model surface 1.67 mm
    after the registration); the FDK's tissue (capped, :func:`tissue_ceiling`) pulls it less (1.22
    mm), but from AP + lateral views the FDK is streaks, and the fit then did worse than against the
    atlas's tissue (docs/results.md)."""
    if choice != "auto":
        return choice
    return "fdk" if covers_a_half_turn(angles) else "free"


def covers_a_half_turn(angles) -> bool:
    """Whether views at ``angles`` (radians) leave no gap wider than :data:`AUTO_FDK_GAP_DEG`: where
    the ``"auto"`` settings hold the FDK's tissue (:func:`registration_tissue`) and fit the residual
    (:func:`residual_for`)."""
    return widest_view_gap_deg(angles) <= AUTO_FDK_GAP_DEG


def residual_for(choice: str, angles) -> str:
    """Whether a run on views at ``angles`` (radians) fits the residual deformation for the setting
    ``choice``: ``"on"`` or ``"off"`` as given; ``"auto"`` on where the views leave no gap wider than
    :data:`AUTO_FDK_GAP_DEG` (where the registration holds the FDK's tissue in passes), off otherwise.

    Why: from 5 views over a half-turn, after the three registration passes, the residual brought
    the six held-out femurs' model surfaces from 0.69 to 0.65 mm mean and the out-of-span ones from
    0.83 to 0.81 (the bowed shaft 1.07 -> 1.00 mm), the 3D PSNR within 0.07 dB, for about a fifth
    more time; from 10 views it is a wash (0.68 -> 0.65 mm, -0.06 dB); from AP + lateral views it
    adds nothing on average (docs/results.md)."""
    if choice != "auto":
        return choice
    return "on" if covers_a_half_turn(angles) else "off"


def fdk_tissue(fdk, geometry, template, cfg, set_kw: dict, size=None, centre_mm=None, ceiling=None,
               to_template=None) -> GaussianSet:
    """Free Gaussians (``cfg.n_free``) on the FDK outside the template's bone (:func:`_free_init_volume`),
    its values capped at ``ceiling`` (1/mm; None: not capped): the free set's start with
    ``free_init="fdk"``, and the tissue held while alpha is registered with ``register_tissue="fdk"``
    (capped at :func:`tissue_ceiling`)."""
    vol = _free_init_volume(fdk, geometry, template, size, centre_mm, to_template, cfg.pass_hole_margin_mm,
                            length=getattr(cfg, "length_factor", None) or 1.0)
    if ceiling is not None:
        vol = np.minimum(vol, np.float32(ceiling))
    vol = vol * cfg.value_scale
    with phase(f"placing {cfg.n_free} Gaussians on the FDK"):
        return init_from_volume(vol, geometry.volume_grid(scene=True), n_gaussians=cfg.n_free,
                                threshold=cfg.init_threshold, density_factor=cfg.density_factor,
                                seed=cfg.seed + 1, **set_kw)


def _to_template_np(bound):
    """Points (N, 3) mm of the subject -> the template's, through a registered shape set's map."""
    def carry(pts):
        with torch.no_grad():
            out = [bound.to_template(torch.as_tensor(c, dtype=torch.float32)).numpy()
                   for c in np.array_split(np.asarray(pts, np.float32), max(1, len(pts) // 500_000))]
        return np.concatenate(out).astype(np.float64)
    return carry


def tissue_ceiling(bone, tissue, template, shell_mm=(3.0, 10.0)) -> float:
    """Halfway between the atlas's tissue around the bone and its bone (atlas units, 1/mm): the
    median atlas value at the surroundings' Gaussians ``tissue`` ``shell_mm`` outside the template's
    surface, and at the bone's Gaussians ``bone`` (ShapeInits; a Gaussian's atlas value is its
    density times its overlap). On the femur: 0.020 and 0.030, so 0.025.

    Why: the FDK's tissue is held still while the bone is registered, and where the bone lies
    outside the template (a femoral head moved 9 mm: neck_valgus10 of examples/femur_out_of_span.py)
    the FDK has bone there, which then explains that bone's projections so that the shape need not
    go there (model surface 3.36 mm after the registration, 5 views). Capped below the bone, the
    tissue holds no bone (0.98 mm; 0.85 against the atlas's tissue)."""
    def atlas_values(s):
        return s.densities * np.maximum(s.overlap, 1.0)

    d = template.sdf_at(tissue.centres)
    near = (d > shell_mm[0]) & (d < shell_mm[1])
    around = atlas_values(tissue)
    level = float(np.median(around[near] if near.any() else around))
    return 0.5 * (level + float(np.median(atlas_values(bone))))


def field_sampler(backend: str):
    """The deformation's sampler for a run's backend: OpenCL with ``cl``, torch's otherwise."""
    if backend == "cl":
        return default_sampler()
    return None


def fit_initial_alpha(scan, shape_model, cfg: ShapeGuidedConfig, init, free=None, size=None,
                      centre_mm=None, alpha=None) -> tuple:
    """(alpha, size) of the atlas-based start registered to the projections: the shape set's start
    ``init`` (a ShapeInit, mm and atlas units) moves with alpha (and a size, starting from ``size``
    about ``centre_mm``, when one is fitted; None otherwise), the free set's start ``free`` stays
    where it is, and only alpha (and the size) is optimised (L1 + D-SSIM + the shape prior, Adam,
    one view per iteration, lr ``lr_alpha`` decaying to 10% over ``alpha_init_iterations``).

    Why: trained from alpha = 0 with everything else free, the densities and the free Gaussians
    absorb the shape difference within a few dozen iterations and alpha stalls near 0. Fitting
    alpha first, with the atlas's densities fixed, is a registration of the atlas's bone to the
    projections; the main run then refines alpha (figures: docs/methods.md).
    The tissue around the bone is left in place: carried by the bone's deformation it made the
    fit follow the limb's outline instead (alpha_1 +0.22, model surface 4.0 mm)."""

    return _alpha_and_size(register_alpha(scan, shape_model, cfg, init, free, size, centre_mm, alpha))


def register_alpha(scan, shape_model, cfg: ShapeGuidedConfig, init, free=None, size=None, centre_mm=None,
                   alpha=None):
    """The registered shape set of :func:`fit_initial_alpha` (its alpha, size and map to the template)."""
    k = int(cfg.alpha_init_iterations)
    sched = {"alpha": Schedule(cfg.lr_alpha, cfg.lr_alpha * 0.1, k),
             "log_size": Schedule(2.5 * cfg.lr_size, 0.25 * cfg.lr_size, k)}
    return _register(scan, shape_model, cfg, init, free, sched, k, size=size, centre_mm=centre_mm, alpha=alpha)


def _alpha_and_size(bound) -> tuple:
    """(alpha, size or None) of a registered shape set."""
    return bound.alpha.detach().numpy().copy(), (bound.size if bound.fits_size else None)


def fit_alpha_in_passes(scan, shape_model, cfg: ShapeGuidedConfig, init, held, size, centre_mm, fdk_held=None):
    """(alpha, size, the tissue last held) of :func:`fit_initial_alpha`, repeated
    ``cfg.register_passes`` times when the tissue held is the FDK's (``fdk_held``: a list of maps,
    points of the subject to the template's -> that tissue; None: once, against ``held``).

    Why: the FDK's tissue leaves out the template's bone, and a femur shorter than the template
    (subject 24: 405 mm, the template 434) is fitted long to fill that hole (413 mm, model surface
    1.22 mm after one registration, 5 views). Each later pass starts from the alpha and size before
    and holds the FDK outside the bone only where the template's bone and every bone fitted so far
    agree: the hole shrinks to the bone (registration alone: 0.74 mm after three passes) and never grows,
    since a hole that followed a bone fitted too large let it grow again at the next pass (the
    lengthened shaft of examples/femur_out_of_span.py 1.25 -> 1.69 -> 2.74 mm). A later pass runs
    at a tenth of the first's learning rates (``LATER_PASS_LR``), and a fitted bone's hole is
    grown by ``cfg.pass_hole_margin_mm`` so that the FDK of bone the fit just misses is not held as
    tissue (without the margin the shapes the model cannot reach lost: a bowed shaft 1.08 -> 1.20
    mm, trained; with it 1.06, and every held-out femur under 1 mm from 5 views, 0.68 mm mean;
    docs/results.md)."""
    passes = cfg.register_passes if fdk_held is not None else 1
    if passes == 1:
        alpha, size = fit_initial_alpha(scan, shape_model, cfg, init, held, size=size, centre_mm=centre_mm)
        return alpha, size, held
    fitted = register_alpha(scan, shape_model, cfg, init, held, size=size, centre_mm=centre_mm)
    maps: list = [None]
    refine = dataclasses.replace(cfg, lr_alpha=cfg.lr_alpha * LATER_PASS_LR, lr_size=cfg.lr_size * LATER_PASS_LR)
    for _ in range(passes - 1):
        maps = maps + [_to_template_np(fitted)]
        held = fdk_held(to_template=maps)
        alpha, size = _alpha_and_size(fitted)
        fitted = register_alpha(scan, shape_model, refine, init, held, size=size, centre_mm=centre_mm, alpha=alpha)
    return (*_alpha_and_size(fitted), held)


#: the learning rates of a later registration pass, times the first's: where the first's decay
#: ended. At the first's own rates a later pass starts a new search from a converged fit, and on
#: subject 21 from 10 views it leapt to another (model surface 0.63 -> 5.52 mm, the size 0.99 ->
#: 1.08); at a tenth it refines (0.54 mm; subject 24 from 5 views 0.69 against 0.75)
LATER_PASS_LR = 0.1


def fit_initial_residual(scan, shape_model, cfg: ShapeGuidedConfig, init, free, alpha, size=None,
                         centre_mm=None) -> np.ndarray:
    """The residual's coefficients registered to the projections after alpha (and the size) have
    been (:func:`fit_initial_alpha`): they stay fixed, and only the residual moves the atlas's bone,
    for ``residual_init_iterations`` (L1 + D-SSIM + its prior, the bending weight decaying from
    ``residual_bending_start`` times its final value; lr ``lr_residual`` decaying to 10 %).

    Why a registration of its own: as for alpha, the densities and the free Gaussians of the main
    run absorb a shape difference within a few dozen iterations, and what they have absorbed the
    residual cannot take back; with alpha fixed, what the residual explains is what the modes
    could not."""
    k = int(cfg.residual_init_iterations)
    sched = {"residual": Schedule(cfg.lr_residual, cfg.lr_residual * 0.1, k)}
    bound = _register(scan, shape_model, cfg, init, free, sched, k, size=size, centre_mm=centre_mm, alpha=alpha,
                      residual=residual_grid(shape_model, cfg))
    return bound.params["residual"].detach().clone()


def residual_grid(shape_model, cfg: ShapeGuidedConfig):
    """The residual's B-spline grid on the model's grid (None with ``residual="off"``)."""
    from clgs.shape.residual import ResidualGrid

    if cfg.residual != "on":
        return None
    return ResidualGrid(shape_model.shape, shape_model.spacing, cfg.residual_points)


def _register(scan, shape_model, cfg, init, free, moving: dict, k: int, *, size, centre_mm, alpha=None,
              residual=None) -> ShapeGuidedSet:
    """The shape set on ``init`` with only the parameters of ``moving`` (name -> Schedule) optimised
    against the projections for ``k`` iterations, the free set's start ``free`` fixed."""
    what = "the residual" if "residual" in moving else "the shape model"
    if "log_size" in moving and size is not None:
        what += " and size"
    with phase(f"preparing the registration of {what}"):  # the first one also sets up torch's optimiser
        bound, trainer = _registration(scan, shape_model, cfg, init, free, moving, k, size=size,
                                       centre_mm=centre_mm, alpha=alpha, residual=residual,
                                       desc=f"registering {what} to the projections")
    trainer.fit()
    return bound


def _registration(scan, shape_model, cfg, init, free, moving: dict, k: int, *, size, centre_mm, alpha, residual,
                  desc) -> tuple:
    """(the shape set, its trainer) of :func:`_register`."""
    geo = scan.geometry
    frozen = Schedule(0.0)
    sched = {name: moving.get(name, frozen) for name in ("alpha", "log_size", "log_length", "residual", "densities",
                                                          "scales", "quats")}
    bound = ShapeGuidedSet(init.centres, (init.scales * geo.scale).astype(np.float32), init.quats.astype(np.float32),
                           (init.densities * cfg.value_scale).astype(np.float32), shape_model=shape_model,
                           geometry=geo, box=volume_box(geo),
                           scale_bounds=scale_bounds_for(geo, cfg.scale_bounds, cfg.scale_floor), schedules=sched,
                           name="registration", sampler=field_sampler(cfg.backend), size=size,
                           size_centre_mm=centre_mm, alpha=alpha, residual=residual,
                           length=cfg.length_factor if size is not None else None)
    for name, p in bound.params.items():  # no gradients wanted: a cheaper backward
        if name not in moving:
            p.requires_grad_(False)
    sets: list = [bound]
    if free is not None and len(free) > 0:
        sets.append(_Frozen(free))
    image = L.ImageTerms(dssim=cfg.lambda_dssim > 0)
    losses = [LossTerm("l1", 1.0, image.l1, per_view=True),
              LossTerm("dssim", cfg.lambda_dssim, image.dssim, per_view=True)]
    if "alpha" in moving:
        losses.append(LossTerm("shape", cfg.lambda_shape, shape_prior_term("registration")))
    if "residual" in moving:
        losses.append(LossTerm("residual", cfg.lambda_residual,
                               residual_prior_term(cfg.residual_bending, cfg.residual_bending_start, k,
                                                   "registration")))
    projections = np.asarray(scan.projections, np.float32) * np.float32(geo.scale * cfg.value_scale)
    trainer = Trainer(sets, geo, projections, losses, iterations=k, backend=Backend(cfg.backend, cfg.projector_mode),
                      render_scale=geo.scale, seed=cfg.seed, log_every=0, progress=True, estimate=False,
                      desc=desc)
    return bound, trainer


class _Frozen:
    """A Gaussian set seen through fixed (detached) tensors, with nothing to optimise."""

    def __init__(self, gset):
        self.name = "fixed"
        with torch.no_grad():
            self._tensors = tuple(t.detach().clone() for t in gset.tensors())

    def __len__(self):
        return int(self._tensors[0].shape[0])

    def tensors(self):
        return self._tensors

    def parameters(self):
        return []

    def state_dict(self):
        return {}

    def load_state_dict(self, state):
        pass


def build_trainer(scan, anatomy_parts, cfg: ShapeGuidedConfig, out_dir=None, *, progress=False, fdk=None,
                  state=None) -> Trainer:
    """Initial sets, losses and trainer for one scan. ``anatomy_parts``: a
    :class:`clgs.anatomy.AnatomyParts` (or an Anatomy, loaded); the shape model or atlas may be
    None, and their terms are then left out.

    Start (a new run): the shape set on the template (:func:`clgs.shape.initialise.initialise`); the free
    set on the atlas's tissue around the bone (``free_init="atlas"``, with an atlas that has some)
    or on the FDK outside the template's bone (``"fdk"``, or without one); then, bound to a shape model,
    alpha registered to the projections (:func:`fit_initial_alpha`).

    Long because each branch (resumed, shape prior on or off, free set from the atlas or the FDK)
    builds the same three pieces in its own order; the pieces themselves are helpers.
    """

    if cfg.free_init not in ("atlas", "fdk"):
        raise InputError(f"free_init must be 'atlas' or 'fdk', got {cfg.free_init!r}")
    cfg.residual = residual_for(cfg.residual, scan.geometry.angles)  # the run's config records what it did
    template, shape_model, atlas = AnatomyParts.of(anatomy_parts)
    geo = scan.geometry
    box = volume_box(geo)
    iters = cfg.schedule_iterations or cfg.iterations
    new_free = state is None and cfg.n_free > 0

    def need_fdk():
        nonlocal fdk
        fdk = fdk_volume(scan) if fdk is None else fdk
        return fdk

    if cfg.value_scale is None:
        cfg.value_scale = value_scale_from(need_fdk())
    bound = cfg.shape_prior and shape_model is not None
    sched = shape_schedules(cfg, iters, free_means=not bound)
    fsched = r2gs_schedules(iters, cfg.lr_factor)
    bounds = scale_bounds_for(geo, cfg.scale_bounds, cfg.scale_floor)
    free_kw = dict(box=box, scale_bounds=bounds, schedules=fsched, name="free", densify=True)
    free, alpha0, theta0, size, centre = None, None, None, None, size_centre(template)
    warp = limb_warp(scan, cfg, template, atlas)
    if state is None:
        with phase(f"placing {cfg.n_shape} Gaussians on the template"):
            init = initialise(template, atlas, geo, cfg.n_shape, tau=cfg.tau, boundary_weight=cfg.boundary_weight,
                              seed=cfg.seed, backend=cfg.backend)
        outside = None
        if new_free and cfg.free_init == "atlas" and atlas is not None:
            with phase(f"placing {cfg.n_free} Gaussians on the atlas's tissue"):
                outside = initialise_surroundings(init, template, atlas, geo, cfg.n_free,
                                                  threshold=cfg.init_threshold, seed=cfg.seed + 1,
                                                  backend=cfg.backend)
        blend = warp.blend(outside.centres) if warp is not None and outside is not None else None
        if bound:
            size = choose_size(scan, cfg, init, outside, centre)
        if size is not None:  # the bone's Gaussians at its size, the tissue along its length
            if cfg.length_factor is None:
                init = dataclasses.replace(init, scales=init.scales * size)
            else:  # and its length: each Gaussian's covariance carried by the stretch
                _, sc, q = stretched_bone(init.centres, init.scales, init.quats, centre, size, cfg.length_factor)
                init = dataclasses.replace(init, scales=sc.astype(init.scales.dtype), quats=q)
            if outside is not None:
                outside = dataclasses.replace(outside, centres=stretched_surroundings(outside.centres, centre, size,
                                                                                      cfg.length_factor or 1.0))
        if outside is not None:
            free = free_set(geo, outside, cfg, free_kw)
        elif new_free:  # "fdk", or an atlas of the bone alone
            free = fdk_tissue(need_fdk(), geo, template, cfg, free_kw)
        held = free  # the tissue the registrations hold fixed
        # the atlas's limb carried onto the scan's outline: the training's start only (the size
        # search and the registrations hold the atlas's own, as without: carried there, a short
        # femur, held-out subject 24, was fitted larger, 0.951 -> 0.972, 1.38 -> 1.69 mm from AP +
        # lateral; docs/results.md)
        if blend is not None and outside is not None:
            free = free_set(geo, carried_tissue(warp, outside, blend, centre, size, cfg.length_factor), cfg, free_kw)
        registering = bound and (cfg.alpha_init_iterations > 0
                                 or (cfg.residual == "on" and cfg.residual_init_iterations > 0))
        fdk_held = None  # to_template=[maps] -> the FDK's tissue outside the bone they agree on
        if registering and outside is not None and registration_tissue(cfg.register_tissue, geo.angles) == "fdk":
            fdk_held = functools.partial(fdk_tissue, need_fdk(), geo, template, cfg, free_kw, size=size,
                                         centre_mm=centre, ceiling=tissue_ceiling(init, outside, template))
            held = fdk_held(to_template=[None])
        if bound and cfg.alpha_init_iterations > 0:
            alpha0, size, held = fit_alpha_in_passes(scan, shape_model, cfg, init, held, size, centre, fdk_held)
        if bound and cfg.residual == "on" and cfg.residual_init_iterations > 0:
            theta0 = fit_initial_residual(scan, shape_model, cfg, init, held, alpha0, size=size, centre_mm=centre)
    else:
        n = state["sets"]["shape"]["scales"].shape[0]
        size = 1.0 if "log_size" in state["sets"]["shape"] else None  # the checkpoint holds its value
        init = None
    if init is not None:
        scales, dens, quats, centres = (init.scales * geo.scale, init.densities * cfg.value_scale, init.quats,
                                        init.centres)
    else:
        scales, dens = np.full((n, 3), 0.01), np.full(n, 0.01)
        quats, centres = np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros((n, 3))
    common = dict(box=box, scale_bounds=bounds, name="shape")
    shape_set: GaussianSet
    if bound:
        shape_set = ShapeGuidedSet(centres, scales.astype(np.float32), quats.astype(np.float32),
                                   dens.astype(np.float32), shape_model=shape_model, geometry=geo,
                                   schedules=sched, alpha=alpha0, sampler=field_sampler(cfg.backend), size=size,
                                   size_centre_mm=centre, residual=residual_grid(shape_model, cfg),
                                   residual_theta=theta0,
                                   length=cfg.length_factor if size is not None else None, **common)
    else:
        shape_set = GaussianSet(geo.world_to_scene(centres).astype(np.float32), scales.astype(np.float32),
                                quats.astype(np.float32), dens.astype(np.float32), schedules=sched,
                                densify=False, **common)
    sets: list = [shape_set]
    if cfg.n_free > 0:
        if free is None:  # resuming: the checkpoint fills it
            e = np.zeros((0, 3), np.float32)
            free = GaussianSet(e, e, np.zeros((0, 4), np.float32), np.zeros(0, np.float32), raw=True, **free_kw)
        sets.append(free)
    prior_field = cfg.density_prior_field
    # an atlas of the bone alone says nothing about the tissue around it: the whole field must not
    # be pulled to its zeros there
    if (prior_field == "all" and cfg.density_prior and atlas is not None
            and len(sample_surrounding_centres(template, atlas, 1, threshold=cfg.init_threshold)) == 0):
        prior_field = "shape"
    losses = projection_losses(cfg)
    if bound:
        losses.append(LossTerm("shape", cfg.lambda_shape, shape_prior_term()))
    if bound and cfg.residual == "on":
        losses.append(LossTerm("residual", cfg.lambda_residual,
                               residual_prior_term(cfg.residual_bending, cfg.residual_bending_start,
                                                   max(iters // 2, 1))))
    if atlas is not None:
        with phase("the density prior's atlas on the scan's grid"):
            prior = DensityPrior(atlas, template, geo, cfg.value_scale, cfg.density_s, cfg.density_points,
                                 field=prior_field, factors=atlas_factors(cfg), limb=warp)
        if state is None:
            calibrate_atlas(scan, cfg, prior, shape_set, free if outside is not None else None)
        if cfg.density_prior:
            losses.append(LossTerm("density", cfg.lambda_density, prior))
    return make_trainer(scan, cfg, sets, losses, out_dir, progress)


def free_set(geo, tissue: ShapeInit, cfg: ShapeGuidedConfig, free_kw: dict) -> GaussianSet:
    """The free Gaussians of a start laid out on the atlas's tissue (``tissue``: mm, atlas units)."""
    return GaussianSet(geo.world_to_scene(tissue.centres).astype(np.float32),
                       (tissue.scales * geo.scale).astype(np.float32), tissue.quats.astype(np.float32),
                       (tissue.densities * cfg.value_scale).astype(np.float32), **free_kw)


def limb_warp(scan, cfg: ShapeGuidedConfig, template, atlas):
    """The atlas's limb carried onto the scan's outline (:class:`clgs.shape.limb.LimbWarp`) with
    ``limb_outline="auto"``, an atlas with tissue around the bone and the whole field held to it;
    None otherwise, or where the outline is measured on fewer than half the scan's slices (said)."""
    if cfg.limb_outline == "off" or atlas is None or not cfg.density_prior or cfg.density_prior_field != "all":
        return None
    from clgs.shape import limb as L

    directions = L.view_directions(scan.geometry)
    if not L.spread_ok(directions):
        return None  # one direction (one view, or views a half-turn apart): no outline to fit
    with phase("the limb's outline in the views"):
        try:
            level, variance = L.tissue_level(atlas, template)
        except InputError:  # an atlas of the bone alone
            return None
        warp = L.LimbWarp(L.scan_outline(scan), L.atlas_outline(atlas, level, directions), template, variance)
    if warp.measured < 0.5:
        print(f"the limb's outline was measured on {100 * warp.measured:.0f} % of the slices (the limb cut by the "
              "detector's side?): the atlas's own limb is used", file=sys.stderr)
        return None
    placed = warp.placed(size_centre(template))
    taken = placed["weight"] > 0.999
    if not taken.any():
        print(f"the limb's outline was measured on {100 * warp.measured:.0f} % of the slices but differs from the "
              "atlas's by more than the factors taken (clgs.shape.limb.MAX_RATIO): the atlas's own limb is used",
              file=sys.stderr)
        return None
    across = 1.0 / np.median(placed["ratio"][taken], axis=0)
    print(f"the limb's outline measured on {100 * warp.measured:.0f} % of the slices; against the atlas's, "
          f"x {across[0]:.3f} across x, x {across[1]:.3f} across y (medians)", file=sys.stderr)
    return warp


def carried_tissue(warp, tissue: ShapeInit, blend: np.ndarray, centre_mm, size, length) -> ShapeInit:
    """The free Gaussians' start (``tissue``, centres of the subject's frame) carried from the
    atlas's limb onto the scan's outline by ``warp``, ``blend`` (from :meth:`LimbWarp.blend` at the
    template's centres) near the bone; their extents across the leg scaled with it (they start
    isotropic, unrotated). ``size`` and ``length`` place the atlas's outline as the start's
    stretch (:func:`clgs.shape.size.stretched_surroundings`) did."""
    along = max(float(size), 1.0) * max(float(length or 1.0), 1.0) if size is not None else 1.0
    centres, factor = warp.from_atlas(warp.placed(centre_mm, 1.0, along), tissue.centres, blend)
    scales = np.array(tissue.scales, np.float64, copy=True)
    scales[:, [a for a in range(3) if a != LEG_AXIS]] *= factor
    return dataclasses.replace(tissue, centres=centres, scales=scales)


def atlas_factors(cfg: ShapeGuidedConfig) -> tuple[float, float]:
    """(bone, rest) factors the atlas is scaled by (1 where none was fitted or given)."""
    return (1.0 if cfg.atlas_bone_factor is None else float(cfg.atlas_bone_factor),
            1.0 if cfg.atlas_rest_factor is None else float(cfg.atlas_rest_factor))


def calibrate_atlas(scan, cfg: ShapeGuidedConfig, reader: DensityPrior, shape_set, tissue) -> None:
    """A new run's atlas scaled to the scan (:mod:`clgs.shape.calibration`): with
    ``atlas_calibration="fit"`` and no factor given, the factors fitted to every training view from
    the atlas as ``reader`` (a :class:`DensityPrior`) reads it for the registered ``shape_set``,
    stored in ``cfg``; then the start's densities scaled by them (the bone's Gaussians by the
    bone's factor, ``tissue``, the free set when it starts on the atlas's tissue, by the rest's)."""
    from clgs.ops.ct_projector import CTProjector
    from clgs.shape import calibration as C

    if cfg.atlas_calibration == "fit" and cfg.atlas_bone_factor is None and cfg.atlas_rest_factor is None:
        geo = scan.geometry
        with phase("scaling the density atlas to the scan"):
            bone, rest = reader.atlas_parts(shape_set, geo.volume_grid(scene=True))
            pb, pt = C.atlas_projections(CTProjector(geo), bone, rest)
            b, t = C.fit_factors(pb, pt, np.asarray(scan.projections, np.float32))
        cfg.atlas_bone_factor, cfg.atlas_rest_factor = b, (b if t is None else t)
        if any(f in C.FACTOR_RANGE for f in (cfg.atlas_bone_factor, cfg.atlas_rest_factor)):
            warnings.warn(f"the scan's densities are more than {C.FACTOR_RANGE[1]:g} times apart from the density "
                          f"atlas's (the factors were clipped to {C.FACTOR_RANGE}): are the projections line "
                          "integrals of attenuation per mm, and is the bone in the views? --set "
                          "atlas_calibration=off runs on the atlas as it is", stacklevel=2)
        print(f"density atlas scaled to the scan: bone x{b:.3f}, the tissue around it x{cfg.atlas_rest_factor:.3f}"
              + ("" if t is not None else " (the atlas holds no tissue apart from the bone: one factor)"),
              file=sys.stderr)
    b, t = atlas_factors(cfg)
    C.scale_densities(shape_set, b)
    if tissue is not None:
        C.scale_densities(tissue, t)
    reader.factors = (b, t)


def choose_size(scan, cfg: ShapeGuidedConfig, init, tissue, centre_mm) -> float | None:
    """The size the shape set starts from (:func:`clgs.shape.size.search_size`), or None when none
    is fitted (``fit_size="off"``, or ``"auto"`` and the bone within ``AUTO_TOLERANCE`` of the
    model's size: then the run is the same as without the search). Without the atlas's tissue
    around the bone (``tissue`` None) the search would let the bone grow into the tissue it cannot
    see: ``"auto"`` then fits no size and ``"on"`` starts from the model's size. With ``fit_size="on"``
    and ``fit_length`` "auto" or "on" the search is :func:`search_size_and_length`, and the length
    it takes goes to ``cfg.length_factor`` (a length given there is held and only the size
    searched)."""
    if cfg.fit_size == "off" or (tissue is None and cfg.fit_size == "auto"):
        return None
    if tissue is None:
        return 1.0
    assert cfg.value_scale is not None  # set by build_trainer before the search
    if cfg.fit_length != "off" and cfg.fit_size == "on" and cfg.length_factor is None:
        with phase("searching the bone's size and length"):
            best, length, alone, share = search_size_and_length(
                scan, Backend(cfg.backend, cfg.projector_mode), cfg.value_scale, init, tissue, centre_mm,
                gain=LENGTH_GAIN if cfg.fit_length == "auto" else 0.0)
        if length != 1.0:
            print(f"bone length: {length:.2f} x its size along the leg, size {best:.2f} (the size alone: {alone:.2f}; "
                  f"the length lowers the projections' L1 by {100 * share:.1f} %; --fit-length off: one size)",
                  file=sys.stderr)
        cfg.length_factor = None if length == 1.0 else length
        return best
    with phase("searching the bone's size"):
        best, _ = search_size(scan, Backend(cfg.backend, cfg.projector_mode), cfg.value_scale, init, tissue,
                              centre_mm, length=cfg.length_factor or 1.0)
    if cfg.fit_size == "auto" and abs(best - 1.0) <= AUTO_TOLERANCE:
        return None
    return best


def write_uncertainty(trainer, shape_set, template, moved, out_dir, volume_surface=None) -> dict:
    """shape_uncertainty.ply and .vtk beside shape_surface.stl (``moved``: its (vertices, faces)),
    from :func:`clgs.shape.uncertainty.shape_uncertainty` (``volume_surface``: the surface.stl
    written, read back; None where there is none); their summary for the report."""
    from clgs.shape import uncertainty as U

    field = U.shape_uncertainty(trainer, shape_set, template.vertices, template.faces, surface=moved[0],
                                volume_surface=volume_surface)
    U.write_uncertainty_files(out_dir, moved[0], moved[1], field["values"],
                              parts={"posterior_mm": field["posterior"], "beyond_model_mm": field["beyond"],
                                     "volume_mm": field["volume"]})
    model = ("max(sqrt(posterior^2 + beyond^2), volume): Laplace posterior of alpha (prior N(0, I), independent "
             "pixel noise) with the leave-one-out field beyond the modes, or the distance to the volume's bone "
             "surface " + ("(surface.stl)" if volume_surface is not None else "(none written: 0)") + ", the larger")
    return U.summary(field, {"model": model})


def deformed_template_surface(template, shape_set) -> tuple | None:
    """The template surface carried onto the subject by the fitted alpha (and size, and length):
    (vertices mm, faces)."""
    if not isinstance(shape_set, ShapeGuidedSet):
        return None
    parts = surface_displacement_parts(template, shape_set)
    return parts["vertices"], np.asarray(template.faces)


def surface_displacement_parts(template, shape_set) -> dict:
    """The template surface carried onto the subject, and its displacement split into the shape
    model's part (alpha, the size and a length: ``model_mm``, (V, 3)) and the residual's
    (``residual_mm``: r at the vertex carried by the size and length), each from the template's
    vertex; ``vertices`` = the template's + both."""
    with torch.no_grad():
        m = shape_set.shape_model
        u = m.displacement(shape_set.alpha.detach())
        v = torch.as_tensor(template.vertices, dtype=torch.float32)
        model = shape_set.scaled(v + m.sample(u, v))
        moved = shape_set.scaled(v + m.sample(u + shape_set.residual_field(), v))
    v64 = np.asarray(template.vertices, np.float64)
    model, moved = model.numpy().astype(np.float64), moved.numpy().astype(np.float64)
    return {"vertices": moved, "model_mm": model - v64, "residual_mm": moved - model}


def displacement_report(template, shape_set) -> dict | None:
    """How much of the surface's displacement from the template is the shape model's and how much
    the residual's: mean and largest length (mm) of each over the template's vertices, and the
    residual's share of the mean lengths; None for a set not bound to a shape model."""
    if not isinstance(shape_set, ShapeGuidedSet):
        return None
    import trimesh

    parts = surface_displacement_parts(template, shape_set)
    model = np.linalg.norm(parts["model_mm"], axis=1)
    res = np.linalg.norm(parts["residual_mm"], axis=1)
    # the residual's part along the surface's normal (where the model left it) changes the surface;
    # the rest slides along it
    model_surface = parts["vertices"] - parts["residual_mm"]
    normals = trimesh.Trimesh(model_surface, np.asarray(template.faces), process=False).vertex_normals
    res_n = np.abs((parts["residual_mm"] * normals).sum(1))
    total = float(model.mean() + res.mean())
    r4 = lambda x: round(float(x), 4)  # noqa: E731
    return {"residual": "on" if shape_set.has_residual else "off",
            "model_mean_mm": r4(model.mean()), "model_max_mm": r4(model.max()),
            "residual_mean_mm": r4(res.mean()), "residual_max_mm": r4(res.max()),
            "residual_normal_mean_mm": r4(res_n.mean()), "residual_normal_max_mm": r4(res_n.max()),
            "residual_share": r4(res.mean() / total) if total > 0 else 0.0}


def reconstruct_shape_guided(scan, anatomy, out_dir=None, iterations: int | None = None, *, resume: bool = False,
                             overwrite: bool = False, progress: bool = True, fdk=None,
                             surface_level: float | None = None, surface_closing: int | None = None,
                             **settings) -> ShapeGuidedResult:
    """See :func:`_reconstruct_shape_guided`. ``out_dir``: one that holds anything is refused
    unless ``resume=True`` or ``overwrite=True`` (its clgs files go first), and it is locked while
    the run writes it (:func:`clgs.fit.config.run_folder`)."""
    with run_folder(out_dir, resume, overwrite), enabled(progress), run_clock():
        return _reconstruct_shape_guided(scan, anatomy, out_dir, iterations, resume=resume, progress=progress,
                                         fdk=fdk, surface_level=surface_level, surface_closing=surface_closing,
                                         **settings)


def _reconstruct_shape_guided(scan, anatomy, out_dir=None, iterations: int | None = None, *, resume: bool = False,
                              progress: bool = True, fdk=None, surface_level: float | None = None,
                              surface_closing: int | None = None, **settings) -> ShapeGuidedResult:
    """Reconstruct ``scan`` with the shape-guided method and the parts of ``anatomy``.

    ``anatomy``: a :class:`clgs.anatomy.AnatomyParts`, or a :class:`clgs.anatomy.Anatomy` (its
    template, shape model and atlas are loaded); anything else is a TypeError. ``settings``:
    :class:`ShapeGuidedConfig` fields.
    ``out_dir`` receives volume.nii.gz, gaussians.npz, alpha.json, log.csv/png, summary.txt,
    surface.stl with surface.json (the reconstruction's outer bone surface and the level it was
    taken at: ``surface_level`` (1/mm) when given, else :func:`clgs.anatomy.bone_level.choose_level`'s
    for this anatomy and scan; gaps in its wall sealed by a closing of up to ``surface_closing``
    voxels when given, else the anatomy's) and shape_surface.stl (the template deformed by the fitted alpha);
    checkpoints allow ``resume``. ``result.surface`` records the bone surface written.
    """

    if not isinstance(scan, Scan):
        scan = Scan.load(scan)
    parts = AnatomyParts.of(anatomy)
    cfg, state = run_config(ShapeGuidedConfig, iterations, settings, resume, out_dir)
    warn_if_the_scan_cannot_hold(scan, parts.template)
    level = with_closing(choose_level(user=surface_level, anatomy=parts.anatomy, truth=scan.truth, scan_meta=scan.meta,
                                      atlas=parts.atlas, template=parts.template), surface_closing)
    if level is not None:  # what the scan shows, before the shape model shapes it: its FDK
        fdk = fdk_volume(scan) if fdk is None else fdk
        warn_if_it_fills_the_grid(fdk, level.value, parts.template, seen=scan.geometry.field_of_view())
    t0 = time.perf_counter()
    trainer = build_trainer(scan, parts, cfg, out_dir, progress=progress, fdk=fdk, state=state)
    restore(trainer, state, cfg)
    trainer.fit()
    with phase("the volume" + (", its bone surface and the run's files" if out_dir is not None else "")):
        volume = voxelize_volume(trainer) / np.float32(cfg.value_scale)
        shape_set = trainer.sets[0]
        alpha = shape_set.alpha.detach().numpy().copy() if isinstance(shape_set, ShapeGuidedSet) else np.zeros(0)
        seconds = time.perf_counter() - t0
        warn_if_implausible(alpha, trainer.log.last("proj_psnr"))
        surface = uncertainty = None
        if out_dir is not None:
            written = write_outputs(trainer, out_dir, cfg.value_scale, volume, parts.template, alpha, level,
                                    uncertainty=cfg.uncertainty == "on")
            surface, uncertainty = written.pop("bone_surface"), written.pop("uncertainty", None)
        displacement = displacement_report(parts.template, shape_set)
    return ShapeGuidedResult(volume=volume, gaussians=gaussians_in_scan_units(trainer, cfg.value_scale),
                             alpha=alpha, log=trainer.log, trainer=trainer, value_scale=cfg.value_scale,
                             interrupted=trainer.interrupted, out_dir=None if out_dir is None else Path(out_dir),
                             summary=trainer.log.summary(), seconds=seconds, surface=surface,
                             displacement=displacement, uncertainty=uncertainty)


def load_anatomy_parts(anatomy) -> AnatomyParts:
    """The :class:`clgs.anatomy.AnatomyParts` (template, shape model or None, atlas or None) from an
    Anatomy's lazy loaders."""
    return AnatomyParts.load(anatomy)


def write_outputs(trainer, out_dir, value_scale, volume, template, alpha, level, uncertainty: bool = False) -> dict:
    """The r2gs outputs plus alpha and the two surfaces (the bone surface at ``level``, a
    :class:`clgs.anatomy.bone_level.BoneLevel` or None for none); each file atomically. The
    returned ``bone_surface`` is :func:`clgs.anatomy.evaluation.write_bone_surface`'s record.
    ``uncertainty``: also the shape surface's uncertainty files (:func:`write_uncertainty`), their
    summary returned as ``uncertainty``."""

    out_dir = Path(out_dir)
    paths = write_common(trainer, out_dir, value_scale, volume, method="shape-guided")
    shape_set = trainer.sets[0]
    size = shape_set.size if isinstance(shape_set, ShapeGuidedSet) and shape_set.fits_size else None
    split = displacement_report(template, shape_set)  # the surface's displacement: model and residual
    moved = deformed_template_surface(template, trainer.sets[0])
    surface = write_bone_surface(out_dir, volume, trainer.geometry, level)
    if surface["path"] is not None:
        paths["surface"] = Path(surface["path"])
        paths["surface_record"] = out_dir / "surface.json"
    if moved is not None:
        paths["shape_surface"] = save_mesh(out_dir / "shape_surface.stl", *moved)
        if uncertainty and len(alpha):
            volume_surface = None
            if surface["path"] is not None:  # the surface measured is the surface written
                written = load_mesh(surface["path"])
                volume_surface = (written.vertices, written.faces)
            paths["uncertainty"] = write_uncertainty(trainer, shape_set, template, moved, out_dir, volume_surface)
    record = {"alpha": [float(a) for a in alpha], "size": size, **({"displacement": split} if split else {})}
    if isinstance(shape_set, ShapeGuidedSet) and shape_set.fits_length:
        record["length"] = shape_set.length  # along the leg, times the size
    if paths.get("uncertainty"):
        record["uncertainty"] = paths["uncertainty"]
    paths["alpha"] = atomic.write_json(out_dir / "alpha.json", record)
    paths["bone_surface"] = surface
    return paths


# ---------------------------------------------------------------------- `--method shape`
def _anatomy_for(scan, anatomy):
    if anatomy is not None and not isinstance(anatomy, str):
        return anatomy

    name = anatomy or (scan.meta or {}).get("anatomy")
    if not name:
        raise InputError("the shape-guided method needs an anatomy: pass --anatomy NAME (see `clgs anatomies`) "
                         "or reconstruct with `clgs <anatomy> reconstruct`")
    return plugins.get_anatomy(name)


def run_method(scan, out_dir=None, iterations: int | None = None, anatomy=None, resume: bool = False,
               progress: bool = True, surface_level: float | None = None, surface_closing: int | None = None,
               **settings) -> dict:
    """The ``shape`` entry of :mod:`clgs.methods`; its ``info`` names the bone surface written
    (``surface_file``, ``surface_level``, ``surface_level_source``)."""
    anatomy = _anatomy_for(scan, anatomy)
    result = reconstruct_shape_guided(scan, anatomy, out_dir, iterations, resume=resume, progress=progress,
                                      surface_level=surface_level, surface_closing=surface_closing, **settings)
    files = {p.name: str(p) for p in sorted(Path(out_dir).iterdir())} if out_dir is not None else {}
    shape_set = result.trainer.sets[0]
    size = shape_set.size if isinstance(shape_set, ShapeGuidedSet) and shape_set.fits_size else None
    if size is not None:
        print(f"bone size: {size:.3f} x the shape model's (fitted with its shape; --fit-size off keeps the model's)"
              + (f", {shape_set.length:.3f} x that along the leg" if shape_set.fits_length else ""), file=sys.stderr)
    surface = {}
    if result.surface is not None:
        surface = {k: result.surface[k] for k in LEVEL_KEYS if k in result.surface}
        surface["surface_file"] = result.surface["path"]
        if result.surface["path"] is None:
            surface["surface_note"] = result.surface["reason"]
    split = result.displacement
    if split is not None and split["residual"] == "on":
        print(f"surface displacement from the template: model {split['model_mean_mm']:.2f} mm mean "
              f"({split['model_max_mm']:.2f} max), residual {split['residual_mean_mm']:.2f} mm mean "
              f"({split['residual_max_mm']:.2f} max; along the normal {split['residual_normal_mean_mm']:.2f} mean, "
              f"{split['residual_normal_max_mm']:.2f} max): {100 * split['residual_share']:.0f} % residual",
              file=sys.stderr)
    if result.uncertainty is not None:
        u = result.uncertainty
        print(f"shape surface uncertainty: {u['mean_mm']:.3f} mm mean, {u['max_mm']:.3f} mm max along the normal, "
              f"{100 * u['share_above_2mm']:.0f} % of the surface above 2 mm (the views' posterior "
              f"{u['posterior_mean_mm']:.3f} mm mean, beyond the model's modes {u['beyond_model_mean_mm']:.3f}, "
              f"to the volume's bone surface {u['volume_mean_mm']:.3f}; {u['file']}, {u['vtk_file']})",
              file=sys.stderr)
    extra: dict = {"uncertainty": result.uncertainty} if result.uncertainty is not None else {}
    if isinstance(shape_set, ShapeGuidedSet) and shape_set.fits_length:  # along the leg, times the size
        extra["length"] = shape_set.length
    config = result.trainer.config
    if config.get("atlas_bone_factor") is not None:  # the atlas scaled to the scan (calibrate_atlas)
        extra["atlas_factors"] = {"bone": config["atlas_bone_factor"], "rest": config["atlas_rest_factor"]}
    return method_output(result, out_dir, files, seconds=result.seconds, alpha=[float(a) for a in result.alpha],
                         size=size, history=result.log.rows, displacement=split, **surface, **extra)


METHOD = Method("shape", run_method, config=ShapeGuidedConfig, atomic_dir=False,
                options=[Option("--anatomy", "anatomy", "str",
                                "anatomy plugin giving template, shape model and atlas", default="the scan's"),
                         *RUN_OPTIONS],
                help="shape-guided Gaussian splatting with an anatomy's shape model and density atlas")

__all__ = ["ShapeGuidedConfig", "ShapeGuidedSet", "ShapeGuidedResult", "reconstruct_shape_guided",
           "build_trainer", "bone_surface", "DensityPrior", "random_subgrid"]


#: beyond these the fit says the scan does not show this anatomy (or its geometry is wrong)
ALPHA_LIMIT_SD = 3.0
PROJECTION_PSNR_FLOOR_DB = 10.0


def warn_if_the_scan_cannot_hold(scan, template) -> None:
    """Warn before a run when the scan's volume is much smaller than the anatomy's template: the
    template cannot fit in it (a scan of something else, or a field of view that misses the bone)."""
    lo, hi = template.bounds()
    bone = float(np.max(np.asarray(hi, float) - np.asarray(lo, float)))
    fov = float(np.max(scan.geometry.sVoxel))
    if bone > 1.5 * fov:
        warnings.warn(f"the scan's volume is {fov:.0f} mm across, the anatomy's template {bone:.0f} mm: the shape "
                      "cannot fit in it; is this scan of that anatomy, and is its geometry in mm?", stacklevel=3)


#: a bone whose end slices hold at least this share of its usual cross-section reaches the grid's end
#: (a reconstruction blurs a rod's end slices to about a sixth of its cross-section; a bone that ends
#: inside the grid, even two slices from its end, leaves none there)
FILLS_END_FRACTION = 0.1


def warn_if_it_fills_the_grid(volume, level, template, seen=None) -> None:
    """Warn before a run whose bone (``volume``, the scan's FDK, above ``level``, 1/mm) reaches both
    ends of the grid along the template's long axis, where the template's bone ends inside its
    grid: a rod, cylinder or slab that fills the grid fits the shape model within its range and
    the projections well, yet is not the anatomy (or the scan cuts the bone, so the shape fitted
    beyond the cut is a guess). ``seen``: the voxels every view saw
    (:meth:`clgs.geometry.Geometry.field_of_view`); the grid's ends are then the first and last
    slices holding any of them."""
    label = getattr(template, "label", None)
    if level is None or label is None:
        return
    seen = np.ones(np.shape(volume), bool) if seen is None else np.asarray(seen, bool)
    bone = (np.asarray(volume) > level) & seen
    label = np.asarray(label, bool)
    spacing = np.asarray(getattr(template, "spacing", (1.0, 1.0, 1.0)), float)
    axis = int(np.argmax(np.asarray(label.shape) * spacing))  # the bone's length: across it, FDK's
    name = "zyx"[axis]  # truncation rims and a cut field of view would say the same of any bone
    if label.shape[axis] >= 3 and bone.shape[axis] >= 3 and not np.take(label, [0, -1], axis=axis).any():
        area = np.moveaxis(bone, axis, 0).reshape(bone.shape[axis], -1).sum(1)  # bone voxels per slice
        seen_area = np.moveaxis(seen, axis, 0).reshape(seen.shape[axis], -1).sum(1)
        where = np.nonzero(seen_area)[0]
        if not area.any() or where.size < 3:
            return
        share = area / np.maximum(seen_area, 1)  # the bone's share of each slice's seen voxels
        usual = float(np.median(share[area > 0]))
        first, last = share[where[0]], share[where[-1]]
        if first >= FILLS_END_FRACTION * usual and last >= FILLS_END_FRACTION * usual:
            warnings.warn(f"the bone (above {level:.3g}/mm) fills the grid along {name}: it reaches both ends (its end "
                          f"slices hold {first / usual:.0%} and {last / usual:.0%} of its usual cross-section), "
                          "where the anatomy's template ends inside its grid: is this a rod, cylinder or "
                          "slab rather than the anatomy, or does the scan cut the bone? check the result before "
                          "using its surface", stacklevel=3)


def warn_if_implausible(alpha, proj_psnr) -> None:
    """Warn after a run whose fit says the prior does not describe the scan: shape coefficients
    beyond ``ALPHA_LIMIT_SD`` standard deviations, or projections fitted to below
    ``PROJECTION_PSNR_FLOOR_DB``."""
    worst = float(np.max(np.abs(alpha))) if np.size(alpha) else 0.0
    reasons = []
    if worst > ALPHA_LIMIT_SD:
        reasons.append(f"the fitted shape lies {worst:.1f} standard deviations from the population's mean")
    if proj_psnr is not None and np.isfinite(proj_psnr) and proj_psnr < PROJECTION_PSNR_FLOOR_DB:
        reasons.append(f"the projections are matched to only {proj_psnr:.1f} dB")
    if reasons:
        warnings.warn("; ".join(reasons) + ": the scan may not show this anatomy, or its geometry may be wrong; "
                      "check the result before using its surface", stacklevel=3)
