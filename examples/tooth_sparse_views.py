"""The real tooth scan, sparse: FDK, SART and R2-Gaussian mode from 10, 15 and 20 of its 181 views,
against the FDK reconstruction from all 181, with their run times, on one plot; with ASTRA's and
RTK's FBP/FDK and SART on the same views where they are installed.

    python examples/tooth_sparse_views.py --out tooth_cmp

The data: ``shared/data/real/tooth/tooth.h5`` (or ``--raw``), real synchrotron counts with flat
and dark fields, 2 detector rows x 640 columns, parallel beam over 180 degrees. It is imported as
``clgs import`` does with its defaults (flat/dark correction, -log, each view's beam normalised
from the air around the tooth, the rotation axis from the import's three estimators on all 181
views: the 180-degree pair, the FBP sharpness and the centre of mass, see docs/calibration.md), the
reference is FDK (ramp filter) from every view, and each sparse set
takes evenly spaced views (clgs's FDK with the Hann window, and with ram-lak as the peers run
theirs). 2D PSNR over both reconstructed slices (normalised by the reference's
range, as the 3D PSNR of ``clgs.metrics``) and 2D SSIM (scikit-image, mean over the two slices).
Writes ``OUT/curves.png``, ``OUT/summary.json`` and ``OUT/slices.png``.

When ASTRA is installed (``pip install astra-toolbox``: a benchmark-only extra, never needed to
reconstruct), its CPU FBP and SART run on the same views in the same run, slice by slice, with
the same rotation axis (each projection shifted by a Fourier phase ramp, an exact sub-pixel shift,
so that the axis falls on the detector's middle, which ASTRA's CPU FBP assumes; FBP with the
``strip`` projector, SART with ``linear``).
ASTRA's image axes and rotation sense differ from clgs's: its results are turned (one of the
eight flips and transposes, the one that best matches its own 181-view FBP to the reference) before
they are compared.

When RTK is installed (``pip install itk-rtk``, also in the ``compare`` extra), its CPU FDK and
SART run too, in RTK's own parallel geometry (source-detector distance 0) with the same angles,
the axis given by the projections' origin (no resampling). RTK's FDK leaves out the slices of
the detector's first and last rows, so the 2 rows are padded to 6 by repeating them (parallel
beam: rows are independent) and the middle two slices kept. RTK's frame (rotation about y) maps
to clgs's by a fixed transpose. RTK's SART: the same iterations and 5 subsets as clgs's, values
kept non-negative.

The axis the run used, how it was chosen and every estimator's column and figure of merit are
printed and recorded in ``summary.json`` (``axis``), with the air normalisation (``air``), the
machine and its load before and after the run (``machine``). ``--centre COLUMN`` sets the axis
instead of the import's estimate; every method, clgs's and the peers', and the reference use the
same axis.
"""
import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

DEFAULT_RAW = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "tooth" / "tooth.h5"


def _ssim2d(vol, ref):
    from skimage.metrics import structural_similarity

    lo, hi = float(ref.min()), float(ref.max())
    a, b = (vol - lo) / (hi - lo), (ref - lo) / (hi - lo)
    return float(np.mean([structural_similarity(x, y, data_range=1.0) for x, y in zip(a, b)]))


def _astra_runs(proj, theta, column, ref, sart_iterations):
    """ASTRA's CPU FBP and SART of each detector row; [(name, volume (rows, N, N), seconds)] turned
    into the reference's orientation (see the module doc), or [] without ASTRA."""
    try:
        import astra
    except ImportError:
        return None
    rows, n = proj.shape[1], proj.shape[2]
    # ASTRA's CPU FBP takes the plain parallel geometry only (axis at the detector's middle): move
    # the axis there by shifting every projection
    proj = centre_axis(proj, column)
    pg = astra.create_proj_geom("parallel", 1.0, n, np.asarray(theta, np.float64))
    vg = astra.create_vol_geom(n, n)
    projectors = {"FBP": astra.create_projector("strip", pg, vg), "SART": astra.create_projector("linear", pg, vg)}

    def run(alg, r, iterations=1):
        sid = astra.data2d.create("-sino", pg, np.ascontiguousarray(proj[:, r, :], np.float32))
        rid = astra.data2d.create("-vol", vg, 0.0)
        cfg = astra.astra_dict(alg)
        cfg.update(ReconstructionDataId=rid, ProjectionDataId=sid, ProjectorId=projectors[alg])
        if alg == "SART":
            cfg["option"] = {"MinConstraint": 0.0}
        aid = astra.algorithm.create(cfg)
        astra.algorithm.run(aid, iterations)
        out = astra.data2d.get(rid)
        astra.algorithm.delete(aid)
        astra.data2d.delete([sid, rid])
        return out

    import time

    results = []
    for alg, its in (("FBP", 1), ("SART", sart_iterations * len(theta))):  # SART: one view per iteration
        t0 = time.perf_counter()
        vol = np.stack([run(alg, r, its) for r in range(rows)])
        results.append((f"ASTRA {alg}", vol, time.perf_counter() - t0))
    for pid in projectors.values():
        astra.projector.delete(pid)
    return results


def centre_axis(proj, column):
    """Projections (n, V, U) shifted along u so that the axis at ``column`` falls on the middle
    ``(U - 1) / 2``: a Fourier phase ramp (an exact shift of band-limited rows) on rows padded by
    half their length with their edge values, so nothing wraps around."""
    p = np.asarray(proj, np.float64)
    n = p.shape[-1]
    pad = n // 2
    ext = np.pad(p, ((0, 0), (0, 0), (pad, pad)), mode="edge")
    f = np.fft.fftfreq(ext.shape[-1])
    shifted = np.fft.ifft(np.fft.fft(ext, axis=-1) * np.exp(-2j * np.pi * f * ((n - 1) / 2.0 - column)), axis=-1)
    return shifted.real[..., pad:pad + n]


def _rtk_runs(proj, theta, column, sart_iterations, subsets=5):
    """RTK's CPU FDK and SART (see the module doc): [(name, volume (rows, N, N), seconds)] in clgs's
    orientation, or None without RTK. ``sart_iterations`` 0: FDK only."""
    try:
        import itk
        from itk import RTK as rtk
    except ImportError:
        return None
    nviews, rows, n = proj.shape
    pad = 2
    padded = np.concatenate([np.repeat(proj[:, :1], pad, 1), proj, np.repeat(proj[:, -1:], pad, 1)], 1)
    nv = rows + 2 * pad
    image = itk.Image[itk.F, 3]
    geometry = rtk.ThreeDCircularProjectionGeometry.New()
    for a in theta:
        geometry.AddProjection(1000.0, 0.0, float(np.rad2deg(a)), 0.0, 0.0)  # SDD 0: parallel beam
    stack = itk.image_from_array(np.ascontiguousarray(padded, np.float32))  # x = u, y = v, z = view
    stack.SetSpacing([1.0, 1.0, 1.0])
    stack.SetOrigin([-float(column), -(nv - 1) / 2.0, 0.0])  # the axis (u = 0) at ``column``
    volume = rtk.ConstantImageSource[image].New()
    volume.SetOrigin([-(n - 1) / 2.0, -(nv - 1) / 2.0, -(n - 1) / 2.0])
    volume.SetSpacing([1.0, 1.0, 1.0])
    volume.SetSize([n, nv, n])
    volume.SetConstant(0.0)

    def fdk_filter():
        f = rtk.FDKConeBeamReconstructionFilter[image].New()
        return f

    def sart_filter():
        f = rtk.SARTConeBeamReconstructionFilter[image, image].New()
        f.SetNumberOfIterations(int(sart_iterations))
        f.SetNumberOfProjectionsPerSubset(max(1, int(np.ceil(nviews / subsets))))
        f.SetEnforcePositivity(True)
        f.SetLambda(1.0)
        return f

    results = []
    for name, make in (("RTK FDK", fdk_filter), ("RTK SART", sart_filter)):
        if name == "RTK SART" and not sart_iterations:
            continue
        t0 = time.perf_counter()
        f = make()
        f.SetInput(0, volume.GetOutput())
        f.SetInput(1, stack)
        f.SetGeometry(geometry)
        f.Update()
        vol = itk.array_from_image(f.GetOutput())  # (z, y, x) of RTK: y is the rotation axis
        results.append((name, np.ascontiguousarray(vol.transpose(1, 2, 0)[pad:pad + rows]),
                        time.perf_counter() - t0))
    return results


def _axis_record(centre: dict) -> dict:
    """The axis the run used, from the import's report: its column, how it was chosen and, when the
    import found it, each estimator's column and figure of merit."""
    figures = {"pair": "mismatch_percent", "sinogram": "contrast_percent", "com": "rms_residual_pixels"}
    record = {"column": float(centre["column"]), "method": centre["method"]}
    for key in ("why", "spread_pixels", "agree", "warning"):
        if key in centre:
            record[key] = centre[key]
    estimates = {}
    for key, e in centre.get("estimates", {}).items():
        if e.get("available"):
            estimates[key] = {"name": e["name"], "column": float(e["column"]), "counted": bool(e.get("counted", True)),
                              figures[key]: float(e[figures[key]])}
        else:
            estimates[key] = {"name": e.get("name", key), "available": False, "why": e.get("why")}
    if estimates:
        record["estimates"] = estimates
    return record


def _axis_text(axis: dict) -> str:
    lines = [f"rotation axis at column {axis['column']:.2f} ({axis['method']})"]
    for e in axis.get("estimates", {}).values():
        if "column" in e:
            figure = ", ".join(f"{k} {v:.3g}" for k, v in e.items() if k not in ("name", "column", "counted"))
            lines.append(f"  {e['name']:16s} {e['column']:7.2f}  {figure}{'' if e['counted'] else ' (not counted)'}")
        else:
            lines.append(f"  {e['name']:16s} not available: {e['why']}")
    if "spread_pixels" in axis:
        lines.append(f"  spread {axis['spread_pixels']:.2f} px")
    if "warning" in axis:
        lines.append(f"  warning: {axis['warning']}")
    return "\n".join(lines)


def _machine(load_before) -> dict:
    """The processor, its cores and the load: run times on a shared machine mean little without them."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "load_before": [round(x, 2) for x in load_before]}


def _orient(vol, turn):
    flip_y, flip_x, transpose = turn
    v = vol[:, ::-1] if flip_y else vol
    v = v[:, :, ::-1] if flip_x else v
    return np.ascontiguousarray(v.transpose(0, 2, 1) if transpose else v)


def _best_turn(vol, ref):
    import itertools

    turns = list(itertools.product((False, True), repeat=3))
    return max(turns, key=lambda t: float(np.corrcoef(_orient(vol, t).ravel(), ref.ravel())[0, 1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--raw", default=str(DEFAULT_RAW))
    ap.add_argument("--views", type=int, nargs="+", default=[10, 15, 20])
    ap.add_argument("--iterations", type=int, default=3000, help="R2-Gaussian iterations")
    ap.add_argument("--sart-iterations", type=int, default=30)
    ap.add_argument("--log-every", type=int, default=250)
    ap.add_argument("--centre", default="auto",
                    help="rotation axis column (after import), or 'auto' (default) for the import's own "
                         "(the three estimators of clgs import)")
    ap.add_argument("--out", default="tooth_cmp")
    args = ap.parse_args()
    if args.centre != "auto":
        try:
            args.centre = float(args.centre)
        except ValueError:
            ap.error(f"--centre takes a column number or 'auto', got {args.centre!r}")

    import warnings

    from clgs import metrics
    from clgs.ct.fdk import fdk
    from clgs.ct.sart import sart
    from clgs.io import atomic
    from clgs.io.raw import read_raw, scan_from_raw
    from clgs.io.scan import Scan
    from clgs.methods.r2gs import reconstruct_r2gs

    out = Path(args.out)
    held = [str(out / f"r2gs_{nv}") for nv in args.views if (out / f"r2gs_{nv}" / "checkpoint.pt").is_file()]
    if held:  # R2-Gaussian refuses to start over a run; say so before the other methods run
        ap.error(f"{', '.join(held)} hold(s) an R2-Gaussian run already: choose another --out or delete them")
    out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    full, report = scan_from_raw(read_raw(args.raw), centre=args.centre)
    column = report["centre"]["column"]
    axis = _axis_record(report["centre"])
    print(_axis_text(axis))
    t0 = time.perf_counter()
    ref = fdk(full.projections, full.geometry, filter="ram-lak")
    ref_seconds = time.perf_counter() - t0
    summary = {"raw": args.raw, "centre_column": column, "centre_method": report["centre"]["method"],
               "axis": axis, "air": {k: v for k, v in report.get("air", {}).items() if k != "background_per_view"},
               "machine": _machine(load_before),
               "reference": "FDK, 181 views, ram-lak", "reference_seconds": ref_seconds,
               "r2gs_iterations": args.iterations, "sart_iterations": args.sart_iterations, "runs": []}
    curves = {}
    astra_turn = None
    full_astra = _astra_runs(full.projections, full.geometry.angles, column, ref, 0)
    if full_astra is not None:
        astra_turn = _best_turn(full_astra[0][1], ref)
        turned = _orient(full_astra[0][1], astra_turn)
        summary["astra"] = {"orientation (flip y, flip x, transpose)": list(astra_turn),
                            "fbp_181_psnr_vs_reference": float(metrics.psnr3d(turned, ref))}
    full_rtk = _rtk_runs(full.projections, full.geometry.angles, column, 0)
    if full_rtk is not None:
        summary["rtk"] = {"fdk_181_psnr_vs_reference": float(metrics.psnr3d(full_rtk[0][1], ref))}
    for nv in args.views:
        keep = np.linspace(0, full.n_views, nv, endpoint=False).astype(int)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scan = Scan(full.geometry.with_angles(full.geometry.angles[keep]), full.projections[keep], ref,
                        {"views": keep.tolist()})
        t0 = time.perf_counter()
        vol = fdk(scan.projections, scan.geometry, filter="hann")
        sec = time.perf_counter() - t0
        runs = [("FDK", vol, sec, [(sec, float(metrics.psnr3d(vol, ref)))])]
        t0 = time.perf_counter()
        vol = fdk(scan.projections, scan.geometry, filter="ram-lak")  # the peers' filter
        sec = time.perf_counter() - t0
        runs.append(("FDK ram-lak", vol, sec, [(sec, float(metrics.psnr3d(vol, ref)))]))
        sart_curve = []
        t0 = time.perf_counter()
        vol = sart(scan.projections, scan.geometry, n_iter=args.sart_iterations, subsets=5,
                   callback=lambda it, v, curve=sart_curve, t0=t0: curve.append((time.perf_counter() - t0,
                                                                               float(metrics.psnr3d(v, ref)))))
        runs.append(("SART", vol, time.perf_counter() - t0, sart_curve))
        t0 = time.perf_counter()
        # one view a step at the paper's rates at every view count, as tooth.md's tables were made
        # (the fast schedule takes four views a step from 20 views on)
        res = reconstruct_r2gs(scan, out_dir=out / f"r2gs_{nv}", iterations=args.iterations,
                               log_every=args.log_every, progress=False, checkpoint_every=0,
                               views_per_step=1, lr_factor=1.0)
        sec = time.perf_counter() - t0
        curve = [(r["wall"], r["psnr3d"]) for r in res.log.rows if r.get("psnr3d") is not None]
        runs.append(("R2-Gaussian", res.volume, sec, curve))
        if astra_turn is not None:
            for name, raw, s in _astra_runs(scan.projections, scan.geometry.angles, column, ref,
                                            args.sart_iterations):
                v = _orient(raw, astra_turn)
                runs.append((name, v, s, [(s, float(metrics.psnr3d(v, ref)))]))
        if full_rtk is not None:
            for name, v, s in _rtk_runs(scan.projections, scan.geometry.angles, column, args.sart_iterations):
                runs.append((name, v, s, [(s, float(metrics.psnr3d(v, ref)))]))
        for name, v, s, c in runs:
            row = {"views": nv, "method": name, "psnr2d": float(metrics.psnr3d(v, ref)), "ssim2d": _ssim2d(v, ref),
                   "seconds": s}
            summary["runs"].append(row)
            curves[(name, nv)] = c
            print(f"{nv:3d} views  {name:12s} PSNR {row['psnr2d']:6.2f} dB  SSIM {row['ssim2d']:.3f}  {s:7.1f} s")
            if nv == max(args.views) or nv == min(args.views):
                np.save(out / f"{name.replace('-', '').lower()}_{nv}.npy", v[0])
    summary["machine"]["load_after"] = [round(x, 2) for x in os.getloadavg()]
    summary["curves"] = [{"method": name, "views": nv, "seconds_psnr2d": [list(map(float, p)) for p in c]}
                         for (name, nv), c in curves.items()]
    atomic.write_json(out / "summary.json", summary)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(name for name, _ in curves))
    colours = {name: f"C{i}" for i, name in enumerate(names)}
    fig, axs = plt.subplots(1, len(args.views), figsize=(4.2 * len(args.views), 4), sharey=True, squeeze=False)
    for ax, nv in zip(axs[0], args.views):
        for name in names:
            c = np.asarray(curves.get((name, nv), []))
            if c.size:
                ax.plot(c[:, 0], c[:, 1], "-o" if len(c) > 1 else "o", ms=3, color=colours[name], label=name)
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlabel("run time (s)")
        ax.set_title(f"{nv} views")
        ax.grid(alpha=0.3)
    axs[0, 0].set_ylabel("2D PSNR against the 181-view FDK (dB)")
    axs[0, -1].legend(fontsize=8)
    fig.suptitle("real tooth scan (synchrotron, parallel beam)")
    fig.tight_layout()
    with atomic.atomic_path(out / "curves.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    nv = max(args.views)
    shown = [name for name in ("FDK", "SART", "R2-Gaussian", "ASTRA SART")
             if (out / f"{name.replace('-', '').lower()}_{nv}.npy").is_file() and (name, nv) in curves]
    fig, axs = plt.subplots(1, 1 + len(shown), figsize=(3.5 * (1 + len(shown)), 3.8))
    lo, hi = float(ref[0].min()), float(ref[0].max())
    axs[0].imshow(ref[0], cmap="gray", vmin=lo, vmax=hi)
    axs[0].set_title("FDK, 181 views (reference)")
    for ax, name in zip(axs[1:], shown):
        ax.imshow(np.load(out / f"{name.replace('-', '').lower()}_{nv}.npy"), cmap="gray", vmin=lo, vmax=hi)
        ax.set_title(f"{name}, {nv} views")
    for ax in axs:
        ax.axis("off")
    fig.tight_layout()
    with atomic.atomic_path(out / "slices.png") as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    print(json.dumps({k: v for k, v in summary.items() if k not in ("runs", "curves")}, indent=1))


if __name__ == "__main__":
    main()
