"""Linear small-strain refinement check at 1 % of the frame's pressure: C3D8 and C3D8I on the
8 mm mesh and on the once-subdivided 4 mm mesh (same surface, same constraints), and ours.

  python3 refine_linear.py DIR
"""
import os
import re
import sys

import numpy as np

from analyse import report
from ccx import subdivide
from cube_modes import fe_stiffness
from linear_lung import solve_arrays

d = sys.argv[1]
text = open(os.path.join(d, "c3d8_small.inp")).read()
pressure = float(re.search(r"\n\d+, P\d, (\S+)", text).group(1))
pts, elements, cons, faces = subdivide(d, "c3d8_small.inp", "ARRAYS")
for name, inc in [("c3d8", False), ("c3d8i", True)]:
    K = fe_stiffness(inc) * 0.5  # 4 mm cubes: K ∝ E·L
    u, it = solve_arrays(pts, elements, faces, cons, K, pressure)
    np.savetxt(os.path.join(d, f"lin_sub_{name}.u.txt"), u)
    print(f"sub {name}: {it} CG iterations, {len(pts)} nodes")
for a in ["lin_c3d8.u.txt", "lin_c3d8i.u.txt", "lin_baudet.u.txt", "lin_sub_c3d8.u.txt"]:
    report(d, a, "lin_sub_c3d8i.u.txt", brief=True)
report(d, "lin_baudet.u.txt", "lin_sub_c3d8.u.txt", brief=True)
report(d, "lin_c3d8.u.txt", "lin_sub_c3d8.u.txt", brief=True)
