#!/usr/bin/env python3
"""How much of a learned preview's error a blurred image-space correction removes.

    python3 bench/blurred_correction.py REF PREVIEW1 PREVIEW2 CORR [CORR2]

REF is a `nimbus render --reference` EXR (its `variance` layer is its own noise),
PREVIEW1 and PREVIEW2 two renders of the preview with different seeds, CORR (and
CORR2) renders of a less biased estimator of the same image: a second reference of
another seed (the bound: what a correction from converged path tracing would leave),
or prediction at bounce 2 (`--predict 2`), two seeds. With one CORR its `variance`
layer is its noise, with two their difference is.

For each blur width sigma (pixels) it forms P + blur(C - P), P the mean of the
previews, C the mean of the CORR images, the blur a Gaussian normalized over the
cloud's pixels, and prints the per-pixel relative RMSE floor against REF (both
images' noise subtracted, as `bench/error_by_brightness.py` and `nimbus eval
--preview` measure it) and the RMSE with the correction's noise left in. A floor that
falls with small sigma and rises with large sigma says at which scale the preview's
error lies. Reads EXR through Mitsuba 3's Bitmap (see bench/README.md).
"""
import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from exr_layers import load


def main():
    if len(sys.argv) not in (5, 6):
        sys.exit(__doc__)
    ref, p1, p2 = (load(p) for p in sys.argv[1:4])
    corr = [load(p) for p in sys.argv[4:]]
    if "variance" not in ref or "direct" not in ref:
        sys.exit(f"{sys.argv[1]}: not a reference render (needs the 'variance' and 'direct' layers)")
    for img, path in zip([p1, p2] + corr, sys.argv[2:]):
        if img["full"].shape != ref["full"].shape:
            sys.exit(f"{path}: not the reference's size")
    if len(corr) == 1 and "variance" not in corr[0]:
        sys.exit(f"{sys.argv[4]}: no 'variance' layer; give two renders of other seeds instead")
    cloud = (ref["full"] - ref["direct"]) > 0
    if not cloud.any():
        sys.exit("the reference shows no cloud")
    mask = cloud.astype(float)
    scale = ref["full"][cloud].mean()
    preview = (p1["full"] + p2["full"]) / 2
    preview_var = (p1["full"] - p2["full"]) ** 2 / 4
    if len(corr) == 2:
        c = (corr[0]["full"] + corr[1]["full"]) / 2
        c_var = (corr[0]["full"] - corr[1]["full"]) ** 2 / 4
    else:
        c, c_var = corr[0]["full"], corr[0]["variance"]

    def floor(img, noise_var=0.0):
        """Relative RMSE against REF with REF's noise and `noise_var` (the image's own
        noise) subtracted; without `noise_var`, the image's noise stays in."""
        e2 = (img - ref["full"]) ** 2 - ref["variance"] - noise_var
        return 100 * np.sqrt(max(e2[cloud].mean(), 0.0)) / scale

    def blur(x, s):
        den = np.maximum(gaussian_filter(mask, s), 1e-12)
        return gaussian_filter(x * mask, s) / den * mask

    def blur_var(v, s):
        # The variance of a normalized Gaussian blur of independent pixels: the sum of
        # the squared weights times each variance; the squared kernel is a Gaussian of
        # width s / sqrt 2 scaled by 1 / (4 pi s^2).
        den = np.maximum(gaussian_filter(mask, s), 1e-12)
        return gaussian_filter(v * mask, s / np.sqrt(2)) / (4 * np.pi * s * s) / den**2 * mask

    print(f"preview: RMSE floor {floor(preview, preview_var):.2f} %")
    print(f"correction source alone: RMSE floor {floor(c, c_var):.2f} %, its noise "
          f"{100 * np.sqrt(c_var[cloud].mean()) / scale:.2f} % per pixel")
    for s in (1, 2, 3, 4, 6, 8):
        out = preview + blur(c - preview, s)
        v = blur_var(c_var, s)
        print(f"blur sigma {s} px: RMSE floor {floor(out, preview_var + v):.2f} %, with the correction's noise "
              f"{floor(out):.2f} % (its noise {100 * np.sqrt(v[cloud].mean()) / scale:.2f} %)")


if __name__ == "__main__":
    main()
