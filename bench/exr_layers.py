"""Reading Nimbus's multi-layer EXR files for the bench scripts (through Mitsuba 3's
Bitmap; see bench/README.md for the install)."""
import numpy as np
import mitsuba as mi

mi.set_variant("scalar_rgb")


def load(path):
    """The layers of an EXR file by name (full, direct, low, high, variance), each
    averaged over its colour channels."""
    out = {}
    for name, bitmap in mi.Bitmap(path).split():
        a = np.array(bitmap)
        out[name] = a.mean(-1) if a.ndim == 3 else a
    return out
