#!/usr/bin/env python3
"""Where a learned image's error lies: the higher orders of two runs of a preview (or
prediction) against a path-traced reference, per fifth of the cloud's pixels ranked by
the reference's brightness, and per band of rows and of columns.

    python3 bench/error_by_brightness.py REF.exr RUN1.exr RUN2.exr

REF is a `nimbus render --reference` EXR, RUN1 and RUN2 two renders of the same scene
with different seeds (their mean is compared, their difference gives their own noise).
Prints, per group, the higher orders' relative bias (sum of the runs' `high` layer over
the reference's, minus 1), the higher orders' share of the reference there, and the
per-pixel relative RMSE of the full image with both images' noise subtracted
(docs/conventions.md, RMSE floor). Reads EXR through Mitsuba 3's Bitmap (see
bench/README.md for the install).
"""
import sys

import numpy as np

from exr_layers import load


def main():
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    ref, a, b = (load(p) for p in sys.argv[1:4])
    for img, path in ((ref, sys.argv[1]), (a, sys.argv[2]), (b, sys.argv[3])):
        for layer in ("full", "high"):
            if layer not in img:
                sys.exit(f"{path}: no layer '{layer}'")
    if "variance" not in ref or "direct" not in ref:
        sys.exit(f"{sys.argv[1]}: not a reference render (needs the 'variance' and 'direct' layers)")
    if a["full"].shape != ref["full"].shape or b["full"].shape != ref["full"].shape:
        sys.exit("the three images differ in size")
    mean = {k: (a[k] + b[k]) / 2 for k in ("full", "high")}
    own = (a["full"] - b["full"]) ** 2 / 4
    err2 = (mean["full"] - ref["full"]) ** 2 - ref["variance"] - own
    cloud = (ref["full"] - ref["direct"]) > 0
    if not cloud.any():
        sys.exit("the reference shows no cloud")
    scale = ref["full"][cloud].mean()

    def row(mask):
        high = ref["high"][mask].sum()
        bias = mean["high"][mask].sum() / high - 1 if high > 0 else float("nan")
        share = high / ref["full"][mask].sum()
        rmse = np.sqrt(max(err2[mask].mean(), 0.0)) / scale
        return f"higher orders {100 * bias:+.1f} % (their share {share:.2f}), RMSE floor {100 * rmse:.1f} %"

    print(f"all cloud pixels: {row(cloud)}")
    values = ref["full"][cloud]
    edges = np.quantile(values, np.linspace(0, 1, 6))
    for i in range(5):
        mask = cloud & (ref["full"] >= edges[i]) & (ref["full"] <= edges[i + 1])
        print(f"brightness fifth {i + 1} (darkest first): {row(mask)}")
    ys, xs = np.nonzero(cloud)
    for axis, coords in (("rows", ys), ("columns", xs)):
        cuts = np.linspace(coords.min(), coords.max() + 1, 6).astype(int)
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            band = np.zeros_like(cloud)
            if axis == "rows":
                band[lo:hi, :] = True
            else:
                band[:, lo:hi] = True
            print(f"{axis} {lo} - {hi - 1}: {row(cloud & band)}")


if __name__ == "__main__":
    main()
