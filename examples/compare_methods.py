"""FDK, SART and R2-Gaussian on one simulated scan: 3D PSNR against run time, on one plot.

    python examples/compare_methods.py --views 25 --iterations 30000 --out cmp25
    python examples/compare_methods.py --scan femur20 --views 25 --out cmp_femur25

The scan: the 64^3 head phantom of ``examples/reconstruct_r2gs.py`` (the voxel volume's line
integrals, noise I0 1e5, sigma 10), cone beam over a full circle as R2-Gaussian's synthetic
scans (``--arc 180`` for a half circle); or ``--scan DIR``, any scan folder with its truth (e.g.
``clgs femur simulate --views 50 --arc 360 --out femur20``), of which ``--views`` evenly spread
views are used. R2-Gaussian runs the paper's schedule over ``--iterations`` (``--set
schedule=fast`` for clgs's default). SART logs every iteration, R2-Gaussian every ``--log-every``
iterations; FDK is one point. Writes ``OUT/curves.png`` and
``OUT/summary.json`` (final PSNR of each method, and R2-Gaussian's PSNR at 10k and at the end).
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np
from reconstruct_r2gs import phantom_scan


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=25)
    ap.add_argument("--iterations", type=int, default=30_000)
    ap.add_argument("--sart-iterations", type=int, default=30)
    ap.add_argument("--arc", type=float, default=360.0, help="degrees")
    ap.add_argument("--log-every", type=int, default=1000)
    ap.add_argument("--out", default="compare")
    ap.add_argument("--scan", default=None, help="a scan folder with its truth instead of the phantom")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                    help="an R2-Gaussian option (R2GSConfig field), e.g. grad_threshold=3e-5; repeatable")
    args = ap.parse_args()

    from clgs import Scan, fdk, metrics, reconstruct_r2gs, sart
    from clgs.io import atomic

    settings = {}
    for pair in args.settings:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"--set expects KEY=VALUE, got {pair!r}")
        try:
            settings[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            settings[key.replace("-", "_")] = value
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.scan:
        scan = Scan.load(args.scan)
        if scan.truth is None:
            raise SystemExit(f"{args.scan} has no truth volume: 3D PSNR needs one")
        scan = scan.subset(np.unique(np.linspace(0, scan.n_views, args.views, endpoint=False).astype(int)))
        name = f"{Path(args.scan).name}, {scan.n_views} views"
    else:
        scan = phantom_scan(args.views, arc=np.deg2rad(args.arc))
        name = f"head phantom, {args.views} views over {args.arc:g} degrees"
    truth = scan.truth

    t0 = time.perf_counter()
    vol = fdk(scan.projections, scan.geometry, filter="hann")
    fdk_point = (time.perf_counter() - t0, float(metrics.psnr3d(vol, truth)))

    sart_curve = []
    t0 = time.perf_counter()

    def log_sart(it, volume):
        sart_curve.append((time.perf_counter() - t0, float(metrics.psnr3d(volume, truth))))

    sart(scan.projections, scan.geometry, n_iter=args.sart_iterations, subsets=5, callback=log_sart)

    # the published schedule over --iterations, one view a step (the fast schedule changes both on
    # 20 views or more); --set schedule=fast runs clgs's default instead
    res = reconstruct_r2gs(scan, out_dir=out / "r2gs", iterations=args.iterations, log_every=args.log_every,
                           progress=False, checkpoint_every=5000, **{"schedule": "paper", **settings})
    rows = [r for r in res.log.rows if r.get("psnr3d") is not None]
    r2_curve = [(r["seconds"], r["psnr3d"], r["iteration"]) for r in rows]
    at = {r["iteration"]: r["psnr3d"] for r in rows}

    summary = {"scan": name, "views": scan.n_views, "fdk_psnr": fdk_point[1], "fdk_seconds": fdk_point[0],
               "sart_psnr": sart_curve[-1][1], "sart_seconds": sart_curve[-1][0],
               "r2gs_psnr": r2_curve[-1][1], "r2gs_seconds": r2_curve[-1][0],
               "r2gs_psnr_at_10k": at.get(10_000), "iterations": res.trainer.iteration,
               "r2gs_gaussians": len(res.gaussians["means"]), "settings": settings}
    atomic.write_json(out / "summary.json", summary)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(*np.array(sart_curve).T, "o-", ms=3, label="SART (OS, 5 subsets)")
    ax.plot(np.array(r2_curve)[:, 0], np.array(r2_curve)[:, 1], "-", label="R2-Gaussian (clgs)")
    ax.plot([fdk_point[0]], [fdk_point[1]], "s", label="FDK")
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlabel("run time (s)")
    ax.set_ylabel("3D PSNR (dB)")
    ax.set_title(name)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic.atomic_path(out / "curves.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
