#!/usr/bin/env python3
"""Write a synthetic `--mitsuba-dir` directory to test bench/mitsuba_compare.py
without a Nimbus build.

    python3 bench/make_synthetic_dir.py OUT [--grid 64] [--res 64] [--spp 256]
                                            [--rho 20] [--fake-nimbus]

The cloud is a large soft lobe at the origin plus a smaller lobe towards
+x (image right) and +y (image top), so a mirrored or upside-down image is
easy to spot. Camera at (0, 0, 3) looking at the origin, sun straight down.
The .vol follows Nimbus's convention: one voxel of zero padding on every side,
bbox = world box spanned by the voxels, values at voxel centres.

With --fake-nimbus, nimbus_full.npy is a Mitsuba render with a different seed
(and the "nimbus" timing fields come from that render), so the comparison
should report noise-level differences only.
"""

import argparse
import json
import os
import struct
import sys

import numpy as np


def write_vol(path, data_zyx, bmin, bmax):
    zres, yres, xres = data_zyx.shape
    with open(path, "wb") as f:
        f.write(b"VOL" + bytes([3]))
        f.write(struct.pack("<5i", 1, xres, yres, zres, 1))
        f.write(struct.pack("<6f", *bmin, *bmax))
        f.write(np.ascontiguousarray(data_zyx, dtype="<f4").tobytes())


def soft_lobe(p, centre, radius):
    """Density 1 in the core falling smoothly to 0 at `radius`."""
    r = np.linalg.norm(p - np.asarray(centre), axis=-1) / radius
    t = np.clip(1.0 - r, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)          # smoothstep


def make_grid(n, half_extent=0.6):
    """n^3 grid (including one zero voxel of padding per side) spanning
    [-half_extent, half_extent]^3 with voxel centres at cell midpoints."""
    bmin = np.full(3, -half_extent)
    bmax = np.full(3, half_extent)
    c = bmin[0] + (np.arange(n) + 0.5) * (2 * half_extent) / n
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    p = np.stack([x, y, z], axis=-1)
    dens = np.maximum(soft_lobe(p, [-0.08, -0.05, 0.0], 0.42),
                      soft_lobe(p, [0.30, 0.28, 0.0], 0.22))
    dens[0, :, :] = dens[-1, :, :] = 0.0
    dens[:, 0, :] = dens[:, -1, :] = 0.0
    dens[:, :, 0] = dens[:, :, -1] = 0.0
    return dens.astype(np.float32), bmin, bmax


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--rho", type=float, default=20.0)
    ap.add_argument("--g", type=float, default=0.85)
    ap.add_argument("--sun", type=float, nargs=3, default=[0.0, -1.0, 0.0])
    ap.add_argument("--fake-nimbus", action="store_true")
    ap.add_argument("--variant", default="llvm_ad_mono")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    os.makedirs(args.out, exist_ok=True)
    dens, bmin, bmax = make_grid(args.grid)
    write_vol(os.path.join(args.out, "cloud.vol"), dens, bmin, bmax)

    scene = {
        "resolution": [args.res, args.res],
        "spp": args.spp,
        "camera": {"origin": [0.0, 0.0, 3.0], "target": [0.0, 0.0, 0.0],
                   "up": [0.0, 1.0, 0.0], "fov_y_deg": 30.0},
        "sun": {"direction": list(args.sun), "irradiance": [1.0, 1.0, 1.0]},
        "medium": {"rho": args.rho, "albedo": 1.0, "g": args.g},
        "nimbus": {"spp": args.spp, "seconds": None, "samples_per_second": None,
                   "threads": args.threads, "image": "nimbus_full.npy"},
    }

    if args.fake_nimbus:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        import mitsuba_compare as mc
        mi, dr = mc.init_mitsuba(args.variant, args.threads)
        s = mc.build_scene(mi, args.out, scene, bmin, bmax, args.spp, 0)
        irr = scene["sun"]["irradiance"]
        mc.render(mi, dr, s, 4, 777, irr)                        # JIT warm-up
        img, secs = mc.render(mi, dr, s, args.spp, 12345, irr)
        np.save(os.path.join(args.out, "nimbus_full.npy"), img)
        scene["nimbus"]["seconds"] = secs
        scene["nimbus"]["samples_per_second"] = args.spp * args.res ** 2 / secs

    with open(os.path.join(args.out, "scene.json"), "w") as f:
        json.dump(scene, f, indent=2)
    print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
