"""Write a C-arm-like per-view geometry file (clgs's ``vectors`` format, docs/formats.md).

A C-arm is no ideal circle: its source distance sags and its height wobbles from view to view,
and the detector sits off the centre ray and a little turned. This script makes such a scan's
vectors (ASTRA's ``cone_vec`` order, mm, world x y z) about the isocentre at the origin:

    python3 examples/c_arm_geometry.py --views 5 --arc 120 --offset 30 -10 --yaw 4 --out carm.json
    clgs femur simulate --geometry carm.json --out femur_carm
    clgs femur reconstruct femur_carm --out rec_carm --set iterations=500

The views span ``--arc`` degrees centred on the x axis; view ``i`` has its source at
``DSO + sag * i`` mm from the isocentre and ``wobble * (i - n/2)`` mm above it; the detector
centre is ``DSD - DSO`` mm beyond the isocentre, moved by ``--offset`` (u, v mm), turned by
``--yaw`` degrees about its column (v) axis and rolled by ``--roll`` degrees in its own plane. The
detector is ``--rows`` x ``--cols`` pixels of ``--pixel`` mm.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import tempfile


def c_arm_vectors(views=5, arc=120.0, dso=700.0, dsd=1100.0, sag=20.0, wobble=15.0, offset=(30.0, -10.0),
                  yaw=4.0, pixel=3.0, roll=0.0) -> list:
    """(views, 12) lists: source, detector centre, one pixel along u, one pixel along v (mm)."""
    rows = []
    for i in range(views):
        t = math.radians(-arc / 2 + (arc * i / (views - 1) if views > 1 else arc / 2))
        c, s = math.cos(t), math.sin(t)
        e_s, e_u = (c, s, 0.0), (-s, c, 0.0)
        y, r = math.radians(yaw), math.radians(roll)
        u0 = [math.cos(y) * e_u[k] - math.sin(y) * e_s[k] for k in range(3)]  # turned about z
        v0 = [0.0, 0.0, 1.0]
        u = [pixel * (math.cos(r) * u0[k] + math.sin(r) * v0[k]) for k in range(3)]  # rolled in its plane
        v = [pixel * (-math.sin(r) * u0[k] + math.cos(r) * v0[k]) for k in range(3)]
        d_src = dso + sag * i
        src = [d_src * e_s[0], d_src * e_s[1], wobble * (i - views // 2)]
        det = [-(dsd - dso) * e_s[0] + offset[0] * e_u[0], -(dsd - dso) * e_s[1] + offset[0] * e_u[1], offset[1]]
        rows.append(src + det + u + v)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=5)
    ap.add_argument("--arc", type=float, default=120.0, help="degrees")
    ap.add_argument("--dso", type=float, default=700.0, help="source to isocentre of the first view, mm")
    ap.add_argument("--dsd", type=float, default=1100.0, help="source to detector along the centre ray, mm")
    ap.add_argument("--sag", type=float, default=20.0, help="mm the source distance grows per view")
    ap.add_argument("--wobble", type=float, default=15.0, help="mm the source height changes per view")
    ap.add_argument("--offset", type=float, nargs=2, default=(30.0, -10.0), metavar=("U", "V"),
                    help="detector centre off the centre ray, mm")
    ap.add_argument("--yaw", type=float, default=4.0, help="detector turn about its v axis, degrees")
    ap.add_argument("--roll", type=float, default=0.0, help="detector roll in its own plane, degrees")
    ap.add_argument("--pixel", type=float, default=3.0, help="detector pixel, mm")
    ap.add_argument("--rows", type=int, default=200)
    ap.add_argument("--cols", type=int, default=160)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    if a.views < 1:
        ap.error("--views must be at least 1")
    doc = {"mode": "cone", "nDetector": [a.rows, a.cols],
           "vectors": c_arm_vectors(a.views, a.arc, a.dso, a.dsd, a.sag, a.wobble, a.offset, a.yaw, a.pixel,
                                    a.roll)}
    folder = os.path.dirname(os.path.abspath(a.out))
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")  # written whole, then renamed
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, indent=1)
    os.replace(tmp, a.out)
    print(f"wrote {a.out}: {a.views} cone-beam views over {a.arc:g} degrees")


if __name__ == "__main__":
    main()
