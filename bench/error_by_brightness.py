#!/usr/bin/env python3
"""Where a learned image's error lies: the higher orders of two runs of a preview (or
prediction) against a path-traced reference, per fifth of the cloud's pixels ranked by
brightness, and per band of rows and of columns.

    python3 bench/error_by_brightness.py REF.exr RUN1.exr RUN2.exr RANK.exr

REF is a `nimbus render --reference` EXR, RUN1 and RUN2 two renders of the same scene
with different seeds (their mean is compared, their difference gives their own noise),
RANK a second reference of another seed, whose brightness ranks the pixels. Ranking by
REF itself would select its noise: its dimmest pixels are those its noise made dim,
so every image would read too bright there and too dark in its brightest pixels, an
unbiased one included.
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
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    ref, a, b, rank = (load(p) for p in sys.argv[1:5])
    for img, path in zip((ref, a, b, rank), sys.argv[1:5]):
        for layer in ("full", "high"):
            if layer not in img:
                sys.exit(f"{path}: no layer '{layer}'")
    if "variance" not in ref or "direct" not in ref:
        sys.exit(f"{sys.argv[1]}: not a reference render (needs the 'variance' and 'direct' layers)")
    if any(img["full"].shape != ref["full"].shape for img in (a, b, rank)):
        sys.exit("the four images differ in size")
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
    values = rank["full"][cloud]
    edges = np.quantile(values, np.linspace(0, 1, 6))
    for i in range(5):
        mask = cloud & (rank["full"] >= edges[i]) & (rank["full"] <= edges[i + 1])
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
