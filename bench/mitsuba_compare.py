#!/usr/bin/env python3
"""Render a Nimbus benchmark cloud with Mitsuba 3 and compare speed and image.

Usage:
    python3 bench/mitsuba_compare.py DIR [--spp N] [--variant llvm_ad_mono]
                                         [--threads 2] [--seed 0] [--png]

DIR is written by `nimbus bench render --mitsuba-dir DIR` and holds
    cloud.vol        Mitsuba binary grid volume (float32, 1 channel, padded,
                     cell-centred; bbox = world box spanned by the voxels)
    scene.json       camera / sun / medium parameters and Nimbus's timing
    nimbus_full.npy  Nimbus's image, float32 (h, w, 3), row 0 = top

The script writes DIR/mitsuba_full.npy and DIR/mitsuba.exr (and, with --png,
DIR/compare.png: Mitsuba | Nimbus | |difference| side by side) and prints one
JSON line with timings and image-comparison metrics as its last line.

Conventions handled here (see bench/README.md for the details):
  * gridvolume ignores the bbox stored in the .vol file unless
    `use_grid_bbox` is set; we pass an explicit `to_world` that maps the unit
    cube [0,1]^3 onto the bbox. Lookups are cell-centred (texel i has its
    centre at (i + 0.5) / res in [0,1]^3), which is exactly how Nimbus writes
    the bbox, so no half-voxel shift is needed. A self-check below evaluates
    the Mitsuba volume at voxel centres and compares with the file contents.
  * Mitsuba's `directional` emitter's `direction` is the propagation
    direction, like our `sun.direction`.
  * `perspective` with `fov_axis = 'y'` and `look_at(origin, target, up)`
    gives image +x = cross(forward, up) and row 0 = top, like Nimbus.
"""

import argparse
import json
import os
import struct
import sys
import time

import numpy as np


# --------------------------------------------------------------------------
# Input files
# --------------------------------------------------------------------------

def read_vol(path):
    """Read a Mitsuba .vol grid (float32, 1 channel).

    Returns (data, bbox_min, bbox_max) with data indexed [z, y, x].
    """
    with open(path, "rb") as f:
        header = f.read(48)
        if header[:3] != b"VOL" or header[3] != 3:
            raise ValueError(f"{path}: not a version-3 Mitsuba .vol file")
        encoding, xres, yres, zres, channels = struct.unpack("<5i", header[4:24])
        if encoding != 1 or channels != 1:
            raise ValueError(f"{path}: expected float32 with 1 channel, got "
                             f"encoding {encoding}, {channels} channels")
        bbox = struct.unpack("<6f", header[24:48])
        data = np.fromfile(f, dtype="<f4", count=xres * yres * zres)
    if data.size != xres * yres * zres:
        raise ValueError(f"{path}: truncated voxel data")
    return (data.reshape(zres, yres, xres),
            np.array(bbox[:3], dtype=np.float64),
            np.array(bbox[3:], dtype=np.float64))


def load_scene_dir(d):
    with open(os.path.join(d, "scene.json")) as f:
        scene = json.load(f)
    grid, bmin, bmax = read_vol(os.path.join(d, "cloud.vol"))
    return scene, grid, bmin, bmax


# --------------------------------------------------------------------------
# Mitsuba scene
# --------------------------------------------------------------------------

def init_mitsuba(variant, threads, log_level="Warn"):
    """Import Mitsuba / Dr.Jit, pick the variant and limit the thread pool."""
    import drjit as dr
    import mitsuba as mi
    dr.set_thread_count(threads)  # Dr.Jit's LLVM backend thread pool
    mi.set_variant(variant)
    mi.set_log_level(getattr(mi.LogLevel, log_level))
    return mi, dr


def is_mono(mi):
    return "mono" in mi.variant()


def build_scene(mi, d, scene, bmin, bmax, spp, samples_per_pass, rr_depth=5):
    """Build the Mitsuba scene dict and load it.

    Returns the loaded scene. In mono variants the sun is rendered with unit
    irradiance; `render` scales the result per channel afterwards (exact,
    because the medium is grey: scalar albedo and extinction).
    """
    T = mi.ScalarTransform4f
    w, h = scene["resolution"]
    cam = scene["camera"]
    sun = scene["sun"]
    med = scene["medium"]

    bmin_l, bmax_l = bmin.tolist(), bmax.tolist()
    extent = (bmax - bmin).tolist()
    centre = (0.5 * (bmin + bmax)).tolist()
    half = (0.5 * (bmax - bmin)).tolist()

    # Clip planes sized to the scene so that kilometre-scale clouds work too.
    origin = np.array(cam["origin"], dtype=np.float64)
    far = 4.0 * (np.linalg.norm(origin - 0.5 * (bmin + bmax))
                 + np.linalg.norm(bmax - bmin))
    near = far * 1e-6

    if is_mono(mi):
        irradiance = 1.0
    else:
        irradiance = {"type": "rgb", "value": list(sun["irradiance"])}

    medium = {
        "type": "heterogeneous",
        # gridvolume maps [0,1]^3 -> world through to_world; the bbox in the
        # file is ignored unless use_grid_bbox=True, so we set it explicitly.
        "sigma_t": {
            "type": "gridvolume",
            "filename": os.path.join(d, "cloud.vol"),
            "filter_type": "trilinear",
            "wrap_mode": "clamp",
            "to_world": T().translate(bmin_l).scale(extent),
        },
        "scale": float(med["rho"]),          # sigma_t = rho * density
        "albedo": float(med["albedo"]),
        "phase": {"type": "hg", "g": float(med["g"])},
    }

    sensor = {
        "type": "perspective",
        "fov": float(cam["fov_y_deg"]),
        "fov_axis": "y",
        "near_clip": near,
        "far_clip": far,
        "to_world": T().look_at(origin=cam["origin"], target=cam["target"],
                                up=cam["up"]),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {
            "type": "hdrfilm",
            "width": int(w),
            "height": int(h),
            "rfilter": {"type": "box"},
            "pixel_format": "luminance" if is_mono(mi) else "rgb",
            "sample_border": False,
        },
    }
    inside = bool(np.all(origin > bmin) and np.all(origin < bmax))
    if inside:
        # A camera inside the box must know which medium it starts in.
        sensor["medium"] = {"type": "ref", "id": "cloud"}

    # rr_depth: Mitsuba's Russian roulette starts at this depth (its default 5);
    # a huge value turns it off, as Nimbus renders (no roulette on path depth).
    integrator = {"type": "volpath", "max_depth": -1, "rr_depth": int(rr_depth)}
    if samples_per_pass:
        integrator["samples_per_pass"] = int(samples_per_pass)

    scene_dict = {
        "type": "scene",
        "integrator": integrator,
        "cloud": medium,
        "sensor": sensor,
        "sun": {
            "type": "directional",
            "direction": list(sun["direction"]),   # direction of travel
            "irradiance": irradiance,
        },
        # The default cube spans [-1,1]^3: scale by half extent, move to centre.
        "bounds": {
            "type": "cube",
            "to_world": T().translate(centre).scale(half),
            "bsdf": {"type": "null"},
            "interior": {"type": "ref", "id": "cloud"},
        },
    }
    return mi.load_dict(scene_dict)


def check_grid_placement(mi, dr, d, grid, bmin, bmax, n=200_000):
    """Evaluate Mitsuba's gridvolume at the world-space centres of (up to n
    random) voxels and return the max abs difference to the file values.
    A wrong to_world or a half-voxel (node- vs cell-centred) shift shows up
    as an error of the order of the voxel-to-voxel variation."""
    T = mi.ScalarTransform4f
    vol = mi.load_dict({
        "type": "gridvolume",
        "filename": os.path.join(d, "cloud.vol"),
        "to_world": T().translate(bmin.tolist()).scale((bmax - bmin).tolist()),
    })
    res = np.array(grid.shape[::-1], dtype=np.float64)   # (x, y, z)
    rng = np.random.default_rng(0)
    flat = rng.choice(grid.size, size=min(n, grid.size), replace=False)
    z, y, x = np.unravel_index(flat, grid.shape)
    idx = np.stack([x, y, z], axis=1).astype(np.float64)
    p = bmin + (idx + 0.5) * (bmax - bmin) / res
    it = dr.zeros(mi.Interaction3f, len(flat))
    it.p = mi.Point3f(p[:, 0], p[:, 1], p[:, 2])
    got = np.array(vol.eval_1(it))
    return float(np.max(np.abs(got - grid[z, y, x])))


def render(mi, dr, scene_obj, spp, seed, sun_irradiance, stats=None):
    """Render; return (image float32 (h, w, 3), wall seconds).

    If `stats` is a dict, stats["cpu_seconds"] receives the process CPU time
    (all threads) spent in the render, to detect competing load."""
    dr.sync_thread()
    c0, t0 = time.process_time(), time.perf_counter()
    img = mi.render(scene_obj, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    if stats is not None:
        stats["cpu_seconds"] = time.process_time() - c0
    a = np.array(img, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    a = a[:, :, :3]
    if is_mono(mi):
        a = a * np.asarray(sun_irradiance, dtype=np.float32)[None, None, :]
    return np.ascontiguousarray(a, dtype=np.float32), seconds


# --------------------------------------------------------------------------
# Image comparison
# --------------------------------------------------------------------------

def downscale(img, f):
    """Box-filter an (h, w, c) image by f in each axis (cropping to f-multiples)."""
    h, w = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    if h == 0 or w == 0:
        raise ValueError(f"image {img.shape} too small for {f}x downscale")
    c = img[:h, :w].astype(np.float64)
    return c.reshape(h // f, f, w // f, f, -1).mean(axis=(1, 3))


def rel_bias(ref, test, f):
    """Mean over pixels with ref > 0 of channel-averaged |ref - test|, divided
    by the mean ref value over the same pixels, after f x f box filtering."""
    r, t = downscale(ref, f), downscale(test, f)
    r_px = r.mean(axis=2)
    mask = r_px > 0
    if not mask.any():
        return float("nan")
    err = np.abs(r - t).mean(axis=2)
    return float(err[mask].mean() / r_px[mask].mean())


def mean_rel_diff(ref, test):
    """(mean(test) - mean(ref)) / mean(ref) over pixels where either > 0."""
    mask = (ref > 0).any(axis=2) | (test > 0).any(axis=2)
    if not mask.any():
        return float("nan")
    mr = ref[mask].astype(np.float64).mean()
    mt = test[mask].astype(np.float64).mean()
    return float((mt - mr) / mr)


def corr(a, b):
    a = a.astype(np.float64).ravel()
    b = b.astype(np.float64).ravel()
    a, b = a - a.mean(), b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else float("nan")


def write_png(mi, path, images):
    """Write images side by side as an 8-bit sRGB PNG, with one shared exposure
    (99.5th percentile of the first image mapped to 1)."""
    scale = np.percentile(images[0], 99.5)
    scale = 1.0 / scale if scale > 0 else 1.0
    gap = np.ones((images[0].shape[0], 2, 3), dtype=np.float32)
    row = []
    for im in images:
        row += [np.clip(im * scale, 0, 1).astype(np.float32), gap]
    strip = np.concatenate(row[:-1], axis=1)
    bmp = mi.Bitmap(strip, pixel_format=mi.Bitmap.PixelFormat.RGB)
    bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8,
                srgb_gamma=True).write(path)


# --------------------------------------------------------------------------

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="directory written by `nimbus bench render --mitsuba-dir`")
    ap.add_argument("--spp", type=int, default=None,
                    help="samples per pixel (default: scene.json spp)")
    ap.add_argument("--variant", default="llvm_ad_mono")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--warmup-spp", type=int, default=4,
                    help="spp of the JIT warm-up render")
    ap.add_argument("--samples-per-pass", type=int, default=0,
                    help="volpath samples_per_pass (deprecated in Mitsuba 3.6+; "
                         "0 = let Mitsuba choose the passes)")
    ap.add_argument("--png", action="store_true",
                    help="also write DIR/compare.png (Mitsuba | Nimbus | |diff|)")
    ap.add_argument("--no-compare", action="store_true",
                    help="only render (no nimbus_full.npy needed)")
    ap.add_argument("--rr-depth", default="5",
                    help="volpath rr_depth (Mitsuba's default 5), or 'off' for no roulette")
    ap.add_argument("--repeats", type=int, default=8,
                    help="render this many independent images of spp / repeats each: "
                         "their spread gives the variance for the efficiency "
                         "1 / (relative variance x seconds)")
    args = ap.parse_args(argv)
    rr_depth = (1 << 30) if str(args.rr_depth).lower() == "off" else int(args.rr_depth)

    d = args.dir
    scene, grid, bmin, bmax = load_scene_dir(d)
    w, h = scene["resolution"]
    spp = args.spp or int(scene["spp"])
    irr = np.asarray(scene["sun"]["irradiance"], dtype=np.float64)

    mi, dr = init_mitsuba(args.variant, args.threads)
    if not is_mono(mi) and "rgb" not in mi.variant():
        print("warning: spectral variant; RGB irradiance is upsampled and the "
              "result is not exactly comparable", file=sys.stderr)

    # samples_per_pass must divide spp; fall back to a single pass otherwise.
    spp_pass = args.samples_per_pass
    if spp_pass <= 0 or spp_pass >= spp or spp % spp_pass != 0:
        spp_pass = 0
    warmup_spp = min(args.warmup_spp, spp)

    err = check_grid_placement(mi, dr, d, grid, bmin, bmax)
    print(f"grid placement self-check: max |mitsuba - file| at voxel centres "
          f"= {err:.3g}", file=sys.stderr)
    if err > 1e-4 * max(1.0, float(grid.max())):
        print("WARNING: gridvolume does not reproduce the voxel values at the "
              "voxel centres: to_world / cell-centring mismatch!", file=sys.stderr)

    t0 = time.perf_counter()
    scene_obj = build_scene(mi, d, scene, bmin, bmax, spp, spp_pass, rr_depth)
    load_s = time.perf_counter() - t0

    # Warm-up: compiles (or fetches from Dr.Jit's kernel cache) the kernels;
    # the sample count is not baked into them, so the timed render reuses them.
    _, warm_s = render(mi, dr, scene_obj, warmup_spp, args.seed + 1000003, irr)
    # Independent images (seeds seed .. seed + R - 1) of spp / R each: the mean is
    # the image, the spread of the R images the variance of its pixels.
    repeats = max(1, min(args.repeats, spp))
    per = spp // repeats
    spp = per * repeats
    images, seconds, cpu = [], 0.0, 0.0
    for r in range(repeats):
        stats = {}
        im, secs = render(mi, dr, scene_obj, per, args.seed + r, irr, stats)
        images.append(im.astype(np.float64))
        seconds += secs
        cpu += stats["cpu_seconds"]
    stack = np.stack(images)
    img = stack.mean(axis=0).astype(np.float32)
    rel_noise = None
    if repeats > 1:
        var_mean = stack.var(axis=0, ddof=1) / repeats
        lum = stack.mean(axis=0).mean(axis=2)
        lit = lum > 0
        if lit.any():
            # As Nimbus's Film::relative_noise: sqrt(sum of the pixels' variances of
            # the mean / sum of their squared means), channel-averaged, lit pixels.
            rel_noise = float(np.sqrt(var_mean.mean(axis=2)[lit].sum() / (lum[lit] ** 2).sum()))
    cpu_util = cpu / seconds / args.threads
    print(f"scene load {load_s:.2f} s, warm-up ({warmup_spp} spp) {warm_s:.2f} s, "
          f"render ({spp} spp) {seconds:.2f} s, CPU utilisation "
          f"{100 * cpu_util:.0f}% of {args.threads} threads", file=sys.stderr)
    if cpu_util < 0.85:
        print("WARNING: the render threads got well under their share of CPU; "
              "is something else running? The timing is not trustworthy.",
              file=sys.stderr)

    np.save(os.path.join(d, "mitsuba_full.npy"), img)
    # Gotcha (mitsuba 3.9.1): writing an EXR deadlocks in OpenEXR's thread
    # pool when Dr.Jit has a single worker thread; use two while writing.
    if dr.thread_count() < 2:
        dr.set_thread_count(2)
    mi.Bitmap(img, pixel_format=mi.Bitmap.PixelFormat.RGB).write(
        os.path.join(d, "mitsuba.exr"))
    dr.set_thread_count(args.threads)

    sps = spp * w * h / seconds
    nim = scene.get("nimbus", {})
    nimbus_sps = nim.get("samples_per_second")
    result = {
        "mitsuba_variant": mi.variant(),
        "mitsuba_version": mi.__version__,
        "spp": spp,
        "resolution": [w, h],
        "threads": args.threads,
        "mitsuba_warmup_seconds": warm_s,
        "mitsuba_seconds": seconds,
        "mitsuba_samples_per_second": sps,
        "mitsuba_cpu_utilisation": cpu_util,
        "nimbus_samples_per_second": nimbus_sps,
        "speed_ratio": (nimbus_sps / sps) if nimbus_sps else None,
        "mitsuba_rr_depth": rr_depth,
        "mitsuba_repeats": repeats,
        "mitsuba_relative_noise": rel_noise,
    }
    m_eff = 1.0 / (rel_noise ** 2 * seconds) if rel_noise else None
    n_eff = nim.get("efficiency")
    result["mitsuba_efficiency"] = m_eff
    result["nimbus_efficiency"] = n_eff
    result["nimbus_relative_noise"] = nim.get("relative_noise")
    result["efficiency_ratio"] = (n_eff / m_eff) if (n_eff and m_eff) else None

    result.update({k: None for k in ("mean_rel_diff", "rel_bias_16x", "rel_bias_4x",
                                     "corr", "corr_flip_x", "corr_flip_y")})
    if not args.no_compare:
        nimbus = np.load(os.path.join(d, nim.get("image", "nimbus_full.npy")))
        nimbus = nimbus.astype(np.float32)
        if nimbus.shape != img.shape:
            raise ValueError(f"nimbus image shape {nimbus.shape} != mitsuba {img.shape}")
        c = corr(img, nimbus)
        cx = corr(img, nimbus[:, ::-1])
        cy = corr(img, nimbus[::-1, :])
        result.update({
            "mean_rel_diff": mean_rel_diff(img, nimbus),
            "rel_bias_16x": rel_bias(img, nimbus, 16),
            "rel_bias_4x": rel_bias(img, nimbus, 4),
            "corr": c,
            "corr_flip_x": cx,
            "corr_flip_y": cy,
        })
        if max(cx, cy) > c:
            axis = "horizontally" if cx >= cy else "vertically"
            print("\n" + "!" * 72 + "\n!!! WARNING: the Nimbus image correlates "
                  f"better with Mitsuba when flipped {axis}\n!!! "
                  f"(corr {c:.4f}, flip_x {cx:.4f}, flip_y {cy:.4f}): "
                  "camera / image orientation conventions disagree.\n"
                  + "!" * 72 + "\n", file=sys.stderr)
        if args.png:
            diff = np.abs(img - nimbus)
            write_png(mi, os.path.join(d, "compare.png"), [img, nimbus, diff])
    elif args.png:
        write_png(mi, os.path.join(d, "compare.png"), [img])

    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
