"""A volume at a glance: three orthogonal central slices (axial, coronal, sagittal) in mm, and,
when a truth is known, the truth's slices and the error's (reconstruction minus truth) under
them. Written next to every reconstruction (``slices.png``) and by ``clgs evaluate``, so a run
that draws no training curve (FDK, SART) still leaves a picture of what it made.

Matplotlib with the Agg backend (no display needed); the PNG is written atomically."""
from __future__ import annotations

import numpy as np

from clgs.progress import phased

__all__ = ["slice_panel", "volume_slices", "SLICES_FILE"]

#: the slice panel of a run folder
SLICES_FILE = "slices.png"


def _central(volume: np.ndarray) -> list:
    """(name, 2-D slice, horizontal axis, vertical axis) of the three central slices of (Z, Y, X)."""
    z, y, x = (s // 2 for s in volume.shape)
    return [("axial (z = centre)", volume[z], "x", "y"),
            ("coronal (y = centre)", volume[:, y, :], "x", "z"),
            ("sagittal (x = centre)", volume[:, :, x], "y", "z")]


def slice_panel(path, volume, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), truth=None, title: str = "",
                figures: dict | None = None, label: str = "reconstruction", units: str = "mm") -> str:
    """Write ``path`` (PNG): ``volume``'s three central slices and, with ``truth`` (same shape),
    the truth's and the error's; returns the path as a string.

    ``spacing`` (dZ, dY, dX) mm and ``origin`` (x, y, z) mm of voxel [0, 0, 0]'s centre place the
    slices in world mm. Volume and truth share one grey scale (0 to the 99.9th percentile of the
    truth, else of the volume); the error a symmetric red-blue one. ``figures`` (e.g. PSNR, SSIM)
    go into the title as ``name value`` pairs; ``label`` names the volume's row; ``units`` the
    axes' (``"voxels"`` for a volume of unknown voxel size, with unit spacing)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from clgs.io import atomic

    vol = np.asarray(volume, np.float32)
    if vol.ndim != 3:
        raise ValueError(f"a slice panel needs a (Z, Y, X) volume, got shape {vol.shape}")
    rows = [(label, vol)]
    if truth is not None:
        t = np.asarray(truth, np.float32)
        if t.shape != vol.shape:
            raise ValueError(f"volume {vol.shape} and truth {t.shape} differ in shape")
        rows += [("truth", t), (f"error ({label} - truth)", vol - t)]
    ref = rows[1][1] if truth is not None else vol
    finite = ref[np.isfinite(ref)]
    top = float(np.percentile(finite, 99.9)) if finite.size else 1.0
    lo = min(0.0, float(np.percentile(finite, 0.1))) if finite.size else 0.0
    top = top if top > lo else lo + 1.0
    if truth is not None:
        err = rows[2][1]
        e = float(np.percentile(np.abs(err[np.isfinite(err)]), 99.5)) if np.isfinite(err).any() else 1.0
        e = e if e > 0 else 1.0
    dz, dy, dx = (float(s) for s in spacing)
    ox, oy, oz = (float(o) for o in origin)
    nz, ny, nx = vol.shape
    # extents (left, right, bottom, top) of each slice: voxel edges, not centres
    span = {"x": (ox - dx / 2, ox + (nx - 0.5) * dx), "y": (oy - dy / 2, oy + (ny - 0.5) * dy),
            "z": (oz - dz / 2, oz + (nz - 0.5) * dz)}
    widths = [span[h][1] - span[h][0] for h in ("x", "x", "y")]
    height = max(span["y"][1] - span["y"][0], span["z"][1] - span["z"][0])
    fig_w = 9.0
    row_h = fig_w * height / sum(widths) * 0.9 + 0.9
    fig = Figure(figsize=(fig_w + 1.2, row_h * len(rows) + (0.7 if title or figures else 0.2)), dpi=90)
    grid = fig.add_gridspec(len(rows), 4, width_ratios=widths + [0.04 * sum(widths)])
    for r, (row_label, data) in enumerate(rows):
        is_err = row_label.startswith("error")
        kw = dict(cmap="RdBu_r", vmin=-e, vmax=e) if is_err else dict(cmap="gray", vmin=lo, vmax=top)
        image = None
        for c, (name, sl, h, v) in enumerate(_central(data)):
            ax = fig.add_subplot(grid[r, c])
            image = ax.imshow(sl, origin="lower", extent=(*span[h], *span[v]), interpolation="nearest", **kw)
            ax.set_xlabel(f"{h} ({units})", fontsize=7)
            ax.set_ylabel(f"{v} ({units})", fontsize=7)
            ax.tick_params(labelsize=6)
            ax.set_title(f"{row_label}\n{name}" if c == 0 else name, fontsize=8, loc="left" if c == 0 else "center")
        cb = fig.colorbar(image, cax=fig.add_subplot(grid[r, 3]))
        cb.set_label("difference (1/mm)" if is_err else "attenuation (1/mm)", fontsize=7)
        cb.ax.tick_params(labelsize=6)
    words = [title] if title else []
    for k, val in (figures or {}).items():
        if isinstance(val, (int, float)) and np.isfinite(val):
            words.append(f"{k} {val:.4g}")
    if words:
        fig.suptitle(",  ".join(words), fontsize=9)
    fig.tight_layout()
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return str(path)


@phased("drawing the slices")
def volume_slices(path, volume, geometry, truth=None, title: str = "", label: str = "reconstruction") -> str:
    """:func:`slice_panel` of a volume on ``geometry``'s grid (a :class:`clgs.geometry.Geometry`
    or grid), with 3D PSNR / SSIM in the title when ``truth`` defines them."""
    from clgs import metrics
    from clgs.io.volume import grid_spacing_origin

    spacing, origin = grid_spacing_origin(geometry)
    figures = None
    if truth is not None:
        f = metrics.volume_figures(np.asarray(volume, np.float32), np.asarray(truth, np.float32))
        if f.get("psnr3d") is not None:
            figures = {"3D PSNR (dB)": f["psnr3d"], "3D SSIM": f["ssim3d"]}
    return slice_panel(path, volume, spacing, origin, truth=truth, title=title, figures=figures, label=label)
