"""The surface error as a picture: a reconstructed bone surface coloured by its distance (mm) to
the true one, seen from the side and from the front, with the mean, 95th percentile and
Hausdorff distance in the title; one row per surface (the volume's, the fitted model's). Written
with every reconstruction of a scan that has a true surface (matplotlib, Agg, atomically)."""
from __future__ import annotations

import numpy as np

from clgs.progress import phased

__all__ = ["surface_distance_figure", "reconstruction_figure", "vertex_distances"]

#: colour scale of the picture: 0 to this many mm (beyond: the top colour)
DEFAULT_MAX_MM = 5.0


def vertex_distances(mesh, truth) -> np.ndarray:
    """Exact distance (mm) from each vertex of ``mesh`` to the surface ``truth``."""
    from clgs.mesh.surface import point_to_mesh_distance

    v = np.asarray(mesh[0] if isinstance(mesh, tuple) else mesh.vertices, float)
    return point_to_mesh_distance(v, truth)


def surface_distance_figure(path, surfaces: dict, truth, max_mm: float = DEFAULT_MAX_MM, title: str = "") -> str:
    """Write a PNG of each surface in ``surfaces`` ({label: (vertices, faces) or Mesh}, None
    entries skipped) coloured by distance to ``truth``; returns the path. Distances come from
    :func:`vertex_distances` (per face: the mean of its three vertices); the figures printed in each
    row are those of :func:`clgs.metrics.surface_distance` (symmetric, area-sampled)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from clgs.io import atomic
    from clgs.metrics import surface_distance

    rows = [(k, m) for k, m in surfaces.items() if m is not None]
    if not rows:
        raise ValueError("no surface to draw")
    cmap = plt.get_cmap("viridis")
    norm = matplotlib.colors.Normalize(0.0, float(max_mm))
    fig, axes = plt.subplots(len(rows), 2, figsize=(6.0, 7.0 * len(rows)), squeeze=False)
    # orthographic views, triangles drawn far to near (painter's order): from the side (+x looking
    # along -x: screen (-y, z), depth x) and from the front (-y, anterior: screen (x, z), depth -y)
    views = (("lateral", (lambda p: np.stack([-p[..., 1], p[..., 2]], -1)), lambda c: c[:, 0]),
             ("antero-posterior", (lambda p: np.stack([p[..., 0], p[..., 2]], -1)), lambda c: -c[:, 1]))
    for r, (label, mesh) in enumerate(rows):
        v = np.asarray(mesh[0] if isinstance(mesh, tuple) else mesh.vertices, float)
        f = np.asarray(mesh[1] if isinstance(mesh, tuple) else mesh.faces, np.int64)
        d = vertex_distances((v, f), truth)
        sd = surface_distance((v, f), truth)
        colours = cmap(norm(d[f].mean(axis=1)))
        tri = v[f]
        for c, (name, screen, depth) in enumerate(views):
            ax = axes[r, c]
            order = np.argsort(depth(tri.mean(axis=1)))
            ax.add_collection(PolyCollection(screen(tri[order]), facecolors=colours[order], edgecolors="none"))
            ax.autoscale_view()
            ax.set_aspect("equal")
            ax.set_axis_off()
            ax.set_title((f"{label}: mean {sd['mean']:.2f}, p95 {sd['p95']:.2f}, Hausdorff {sd['hausdorff']:.2f} mm"
                          "\n" if c == 0 else "\n") + name, fontsize=8, loc="left" if c == 0 else "center")
    sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=axes.ravel().tolist(), shrink=0.5,
                 label=f"distance to the true surface (mm; {max_mm:g} and beyond: top)")
    if title:
        fig.suptitle(title, fontsize=10)
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png", bbox_inches="tight")
    plt.close(fig)
    return str(path)


@phased("drawing the surface-distance picture")
def reconstruction_figure(path, anatomy, scan, volume, model_surface=None, mesh=None, title: str = "", level=None):
    """:func:`surface_distance_figure` of a reconstruction of ``scan``: its outer bone surface
    (``mesh``, the surface a run wrote, taken at ``level``; or extracted from ``volume`` at
    :func:`clgs.anatomy.bone_level.choose_level`'s level) and, for a shape-guided run, the fitted
    model's surface, against the scan's true surface; the row names the level and its source. None
    (nothing written) when the scan has no true surface or the reconstruction no bone surface."""
    if scan.surface is None or scan.truth is None:
        return None
    from clgs.anatomy.bone_level import choose_level
    from clgs.anatomy.evaluation import bone_surface
    from clgs.mesh.surface import SurfaceError

    if mesh is None:
        level = choose_level(anatomy=anatomy, truth=scan.truth, scan_meta=scan.meta)
        try:
            mesh = None if level is None else bone_surface(volume, scan.geometry, level)
        except (SurfaceError, ValueError):
            mesh = None
    label = "volume surface" if level is None else f"volume surface (level {level.value:.4g}, {level.source})"
    surfaces = {label: mesh, "model surface": model_surface}
    if all(m is None for m in surfaces.values()):
        return None
    return surface_distance_figure(path, surfaces, scan.surface, title=title)
