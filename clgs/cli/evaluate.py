"""``clgs evaluate``: a volume against a truth (3D PSNR / SSIM, surface distance). Heavy modules
load when it runs."""
from __future__ import annotations

from pathlib import Path

import click

from clgs.cli.common import (
    check_not_input,
    check_output,
    check_writable,
    click_error,
    fmt_number,
    load_scan,
    load_volume_file,
    parse_spacing,
)
from clgs.cli.options import FiniteFloat, force_option, mesh_space_option, out_option


def _truth_from(path: Path, spacing, axes: str = "zyx"):
    """A truth volume from a volume file or from a scan folder's truth; last, the array order of
    the scan's files (a ``.npy`` beside it is read in that order), or None for a volume file."""
    if path.is_dir():
        from clgs.io.volume import grid_spacing_origin

        sc = load_scan(path)
        if sc.truth is None:
            raise click.BadParameter(f"{path}: this scan has no ground truth", param_hint="--truth")
        sp, org = grid_spacing_origin(sc.geometry)
        return sc.truth, sp, org, (sc.surface, sc.meta.get("truth_surface_level")), sc.geometry.orientation
    vol, sp, org = load_volume_file(path, spacing, "truth", axes=axes)
    return vol, sp, org, (None, None), None


def _in_scan_order(path: Path, vol, orientation, axes: str):
    """A ``.npy`` written by clgs for a scan holds the scan's file order (``orientation``, e.g.
    LAS): bring it to the working order the scan's truth is in. Files that carry their own
    orientation (NIfTI, ...) are in the working order already."""
    if orientation is None or orientation == "RAS" or axes != "zyx" or not str(path).lower().endswith(".npy"):
        return vol
    from clgs.io.orientation import to_working

    return to_working(vol, orientation)


@click.command()
@click.argument("volume", type=click.Path(path_type=Path))
@click.argument("truth_arg", metavar="TRUTH", type=click.Path(path_type=Path), required=False)
@click.option("--truth", "-t", type=click.Path(path_type=Path), default=None,
              help="the true volume (.npy/.nii/.nii.gz) or a scan folder holding it (the same as TRUTH)")
@click.option("--mask", "mask_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="a label volume; metrics are also computed over its non-zero voxels")
@click.option("--mask-level", type=FiniteFloat(), default=None,
              help="mask = truth above this value (e.g. a bone threshold, 1/mm)")
@click.option("--dilate", type=click.IntRange(min=0), default=0, show_default=True,
              help="grow the mask by this many voxels")
@click.option("--level", type=FiniteFloat(), default=None,
              help="iso-level for the surface distance (mm) between VOLUME's and the truth's surfaces")
@click.option("--surface", "surface_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="true surface mesh (STL/PLY/OBJ/npz) to compare with instead of the truth's iso-surface")
@mesh_space_option("the --surface")
@click.option("--spacing", default=None, help="voxel size in mm for .npy inputs, 'd' or 'dZ,dY,dX'")
@click.option("--axes", type=click.Choice(["zyx", "xyz"]), default="zyx", show_default=True,
              help="axis order of .npy inputs: zyx (clgs) or xyz (R2-Gaussian's vol_gt.npy)")
@out_option("write the figures to this JSON file (an infinite PSNR is written as null)", name="json_out",
            aliases=("--json",), type=click.Path(dir_okay=False, path_type=Path))
@click.option("--figure", "figure_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="slice panel PNG (central slices of VOLUME, the truth and the error) [default: next to VOLUME, "
                   "VOLUME_vs_truth.png, or evaluation.png in a run folder]")
@click.option("--no-figure", is_flag=True, help="draw no slice panel")
@force_option("replace an existing --out or --figure")
def evaluate(volume, truth_arg, truth, mask_path, mask_level, dilate, level, surface_path, mesh_space, spacing, axes,
             json_out, figure_out, no_figure, force):
    """Compare VOLUME with TRUTH (a volume, or a scan folder holding it): 3D PSNR / SSIM (as
    R2-Gaussian), masked variants, and the surface distance in mm when --level is given. VOLUME may
    also be a reconstruct output folder. The result comes first, then the truth, as in every evaluate.

    \f
    (One function: the truth, the mask, the metrics and the optional surface distance use the
    same loaded arrays.)
    """

    from clgs import metrics
    from clgs.cli.common import check_evaluate_order
    from clgs.io import atomic

    if truth_arg is not None and truth is not None:
        raise click.UsageError("give the truth once: as TRUTH or as --truth")
    truth = truth if truth is not None else truth_arg
    if truth is None:
        raise click.UsageError("missing argument TRUTH (the true volume or its scan folder): "
                               "clgs evaluate VOLUME TRUTH")
    check_evaluate_order(volume, truth, "clgs evaluate VOLUME TRUTH")

    if mesh_space and surface_path is None:
        raise click.UsageError("--mesh-space is the frame of a --surface file")
    if json_out is not None:
        check_not_input(json_out, [("volume", volume, False), ("truth", truth, truth.is_dir()),
                                    ("mask", mask_path, False), ("surface", surface_path, False)], "--out")
        check_output(json_out, force, "--out")
        check_writable(json_out, "--out")
    if mask_path is not None and mask_level is not None:
        raise click.UsageError("give either --mask or --mask-level, not both")
    if figure_out is not None:
        if no_figure:
            raise click.UsageError("give --figure or --no-figure, not both")
        _check_figure_path(figure_out, force, [("volume", volume, False), ("truth", truth, truth.is_dir()),
                                                ("mask", mask_path, False), ("surface", surface_path, False),
                                                ("json", json_out, False)])
    if volume.is_dir():
        if not (volume / "volume.nii.gz").is_file():
            raise click.BadParameter(f"{volume}: a folder without volume.nii.gz", param_hint="VOLUME")
        volume = volume / "volume.nii.gz"
    sp = parse_spacing(spacing)
    pred, psp, porg = load_volume_file(volume, sp, axes=axes)
    tvol, tsp, torg, tsurf, order = _truth_from(truth, sp, axes)
    pred = _in_scan_order(volume, pred, order, axes)
    if pred.shape != tvol.shape:
        raise click.UsageError(f"VOLUME {pred.shape} and --truth {tvol.shape} have different shapes (Z, Y, X)")
    _check_same_grid(volume, psp, porg, tsp, torg)
    mask = None
    if mask_path is not None:
        mvol, _, _ = load_volume_file(mask_path, sp, "mask", axes=axes)
        mvol = _in_scan_order(mask_path, mvol, order, axes)
        if mvol.shape != tvol.shape:
            raise click.UsageError(f"--mask {mvol.shape} does not match the volumes' shape {tvol.shape}")
        mask = mvol != 0
    elif mask_level is not None:
        mask = tvol > mask_level
    if mask is not None:
        if dilate:
            from scipy.ndimage import binary_dilation

            mask = binary_dilation(mask, iterations=dilate)
        if not mask.any():
            raise click.UsageError("the mask is empty (no voxel inside); check --mask / --mask-level")
    try:
        res = metrics.evaluate_volume(pred, tvol, mask)
    except metrics.MetricError as exc:
        raise click_error(exc) from None
    res.update(volume=str(volume), truth=str(truth))
    if mask is not None:
        res["mask_voxels"] = int(mask.sum())
    if level is not None or surface_path is not None:
        from clgs.io.mesh import MeshError, load_mesh
        from clgs.mesh.surface import SurfaceError, surface_distance, surface_from_volume

        if level is None:
            raise click.UsageError("--surface needs --level (the iso-level of VOLUME's surface)")
        sp_mm = tsp if tsp is not None else (psp if psp is not None else None)
        if sp_mm is None:
            raise click.UsageError("surface distances need voxel sizes: give --spacing for .npy volumes")
        org = torg if torg is not None else porg
        try:
            ours = surface_from_volume(pred, level, spacing=sp_mm, origin=org)
            if surface_path is not None:
                ref = load_mesh(surface_path, space=mesh_space)
            elif tsurf[0] is not None and tsurf[1] == level:
                ref = tsurf[0]  # the scan's stored true surface, made at this level
            else:
                ref = surface_from_volume(tvol, level, spacing=sp_mm, origin=org)
            res["surface"] = surface_distance(ours, ref)
        except (SurfaceError, MeshError) as exc:
            raise click_error(exc, "surface distance") from None
        res["surface"]["level"] = level
    click.echo(f"PSNR {fmt_number(res['psnr3d'])} dB   SSIM {res['ssim3d']:.4f}   "
               f"(SSIM z/y/x {' '.join(f'{a:.4f}' for a in res['ssim3d_axes'])})")
    if mask is not None:
        click.echo(f"masked ({res['mask_voxels']} voxels): PSNR {fmt_number(res['psnr3d_masked'])} dB   "
                   f"SSIM {res['ssim3d_masked']:.4f}")
    if "surface" in res:
        s = res["surface"]
        click.echo(f"surface distance (mm): mean {s['mean']:.3f}   p95 {s['p95']:.3f}   Hausdorff {s['hausdorff']:.3f}")
    if not no_figure:
        figure = _draw_figure(figure_out, volume, pred, tvol, psp if psp is not None else tsp,
                              porg if porg is not None else torg, res, truth)
        if figure is not None:
            res["figure"] = figure
    if json_out is not None:
        atomic.write_json(json_out, res, overwrite=True)
        click.echo(f"wrote {json_out}")


def _check_figure_path(path: Path, force: bool, inputs) -> None:
    """A --figure path: a .png file that is no input and may be written (an existing one with --force)."""
    if path.suffix.lower() != ".png":
        raise click.BadParameter(f"{path}: the figure is a PNG; name it ....png", param_hint="--figure")
    check_not_input(path, inputs, "--figure")
    if path.is_dir():
        raise click.BadParameter(f"{path} is a folder", param_hint="--figure")
    if path.exists() and not force:
        raise click.ClickException(f"{path} already exists; pass --force to overwrite it (or choose another --figure)")
    check_writable(path, "--figure")


def _default_figure(volume: Path) -> Path:
    """Next to the volume: ``evaluation.png`` in a run folder, else ``<name>_vs_truth.png``."""
    if volume.name == "volume.nii.gz":
        return volume.parent / "evaluation.png"
    name = volume.name
    for suffix in (".nii.gz", ".nii", ".npy", ".mha", ".mhd", ".nrrd", ".nhdr"):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    return volume.parent / f"{name}_vs_truth.png"


def _draw_figure(path, volume: Path, pred, truth, spacing, origin, res, truth_arg) -> str | None:
    """The slice panel (:func:`clgs.figures.slice_panel`); at the default place, a folder that
    will not take it is said and skipped (the figures printed are the command's result)."""
    from clgs.figures import slice_panel

    given = path is not None
    path = path if given else _default_figure(volume)
    figures = {"3D PSNR (dB)": res.get("psnr3d"), "3D SSIM": res.get("ssim3d")}
    units = "mm" if spacing is not None else "voxels"
    try:
        if not given:
            check_not_input(path, [("truth", truth_arg, truth_arg.is_dir())], "--figure")
        out = slice_panel(path, pred, spacing if spacing is not None else (1.0, 1.0, 1.0),
                          origin if origin is not None else (0.0, 0.0, 0.0), truth=truth,
                          title=f"{volume.name} against the truth", figures=figures, label="volume", units=units)
    except (OSError, click.ClickException) as exc:
        if given:
            raise click.ClickException(f"cannot write --figure {path}: {exc}") from None
        msg = exc.format_message() if isinstance(exc, click.ClickException) else str(exc)
        click.echo(f"no figure written next to the volume ({msg}); give --figure PATH", err=True)
        return None
    click.echo(f"figure: {out}")
    return out


def _check_same_grid(volume, psp, porg, tsp, torg) -> None:
    """Voxels are compared by index, so both volumes must lie on one world grid: where both files
    say where they lie (NIfTI, MetaImage, NRRD, DICOM), a different voxel size or origin is refused
    with both grids (a .npy carries no position and is taken as on the truth's grid)."""
    import numpy as np

    if psp is None or tsp is None:
        return
    if not np.allclose(psp, tsp, rtol=1e-4):
        raise click.UsageError(f"{volume} has voxels of {tuple(psp)} mm, the truth {tuple(tsp)} mm (dZ, dY, dX): "
                               "the two are on different grids; resample one onto the other first")
    if porg is not None and torg is not None:
        off = np.abs(np.asarray(porg, float) - np.asarray(torg, float))
        if np.any(off > 0.01 * np.asarray(tsp, float)[::-1]):
            raise click.UsageError(f"{volume} starts at {tuple(round(float(v), 3) for v in porg)} mm, the truth at "
                                   f"{tuple(round(float(v), 3) for v in torg)} mm (x, y, z of the first voxel): the "
                                   "same voxel index would compare different places; resample one onto the other, "
                                   "or evaluate against the scan's own truth (its folder)")
