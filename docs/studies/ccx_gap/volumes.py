"""Volume change (mL) and mean |u| (mm) of displacement fields of the dumped scene.
  python3 volumes.py DIR FIELD...
"""
import os
import sys

import numpy as np

from ccx import load_scene

d = sys.argv[1]
rest, groups, el, faces, cons = load_scene(d)


def vol(x):
    v = 0.0
    for tri in ([0, 1, 2], [0, 2, 3]):
        a, b, c = (x[faces[:, t]] for t in tri)
        v += np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    return v


v0 = vol(rest)
for n in sys.argv[2:]:
    u = np.loadtxt(os.path.join(d, n))[: len(rest)]
    print(f"{n}: ΔV {(vol(rest + u) - v0) * 1e6:.2f} mL, mean |u| {np.linalg.norm(u, axis=1).mean() * 1e3:.3f} mm")
