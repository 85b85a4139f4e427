"""Block z-scores of cached `nimbus eval p2p` renders against their BDPT references.

For an unbiased render E and an independent reference R, each lit block's
z = (mean_E - mean_R) / sqrt(var_E + var_R) is about N(0, 1) when the block
variances are right. The block variance is the pixels' variances of the mean
summed / n^2, which assumes independent pixels: if the samples of a pass are
correlated (light subpath pools), |z| comes out wider. The median |z| is the
robust figure (N(0, 1): 0.674); the RMS is dominated by heavy-tailed blocks.

    python bench/block_z.py OUT/cache '*estimated*pool256*.npy' 8
"""
import glob
import os
import sys

import numpy as np


def blocks(a, f):
    h, w, _ = a.shape
    m = a[:, :, :3].astype(np.float64)
    v = a[:, :, 3:6].astype(np.float64)
    m = m[: h // f * f, : w // f * f].reshape(h // f, f, w // f, f, 3).mean(axis=(1, 3))
    v = v[: h // f * f, : w // f * f].reshape(h // f, f, w // f, f, 3).sum(axis=(1, 3)) / (f * f) ** 2
    return m, v


def main():
    cache, pattern, f = sys.argv[1], sys.argv[2], int(sys.argv[3])
    every = []
    for path in sorted(glob.glob(os.path.join(cache, pattern))):
        name = os.path.basename(path)
        parts = name.split("_")
        cloud, config, size, res = parts[0], parts[1], parts[2], parts[3]
        k = next(p for p in parts if p.startswith("k") and p[1:].isdigit())
        refs = glob.glob(os.path.join(cache, f"{cloud}_{config}_{size}_{res}_bdpt_{k}_spp*.npy"))
        if not refs:
            print(f"{name}: no reference, skipped")
            continue
        me, ve = blocks(np.load(path), f)
        mr, vr = blocks(np.load(refs[0]), f)
        # Lit blocks, channels with some variance.
        keep = (mr.mean(axis=2, keepdims=True) > 0) & (ve + vr > 0)
        z = (me - mr)[keep] / np.sqrt((ve + vr)[keep])
        every.append(z)
        print(f"{name}: {z.size} values, median |z| {np.median(np.abs(z)):.2f}, rms {np.sqrt((z ** 2).mean()):.2f}")
    if not every:
        sys.exit("no render matched")
    z = np.concatenate(every)
    print(f"all: {z.size} values, median |z| {np.median(np.abs(z)):.2f} (N(0, 1): 0.67), rms {np.sqrt((z ** 2).mean()):.2f}")


if __name__ == "__main__":
    main()
