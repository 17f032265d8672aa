"""Small-strain (linear) solves of the dumped CIP scene with any 24 × 24 cube stiffness, by
Jacobi-preconditioned projected conjugate gradients (numpy only): which element's hourglass
stiffness makes the linear difference between our element and CalculiX's C3D8.

  python3 linear_lung.py DIR
Writes lin_<name>.u.txt for each element (at 1 % of the frame's pressure, as the dump's
`c3d8_small.inp`) and compares them with `u_ours_small.txt` and `c3d8_small.u.txt`.
"""
import os
import sys

import numpy as np

from ccx import load_scene
from cube_modes import fe_stiffness, load_k

HG = None


def hourglass_projector():
    from ccx import SIGNS
    h = np.stack([SIGNS[:, 0] * SIGNS[:, 1], SIGNS[:, 1] * SIGNS[:, 2], SIGNS[:, 2] * SIGNS[:, 0],
                  SIGNS[:, 0] * SIGNS[:, 1] * SIGNS[:, 2]])
    H = np.zeros((24, 12))
    for a in range(4):
        for c in range(8):
            for i in range(3):
                H[3 * c + i, 3 * a + i] = h[a, c]
    return H


def with_hourglass_of(k_base, k_target):
    """k_base with its hourglass block replaced by k_target's (the Rust correction at rest)."""
    H = hourglass_projector()
    P = H @ H.T / 8.0
    return k_base - P @ k_base @ P + P @ k_target @ P


def solve(d, K, pressure, tol=1e-10, maxit=20000):
    rest, groups, elements, faces, cons = load_scene(d)
    return solve_arrays(rest, elements, faces, cons, K, pressure, tol, maxit)


def solve_arrays(rest, elements, faces, cons, K, pressure, tol=1e-10, maxit=20000):
    """`faces`: quads (node ids) of the loaded surface; the area vector is oriented away from
    the owning element's centre when `faces` is given as (quads, element of each)."""
    n = len(rest)
    # Projector per node: fixed → 0, line → ddᵀ, plane → I − nnᵀ.
    proj = np.tile(np.eye(3), (n, 1, 1))
    for node, (kind, v) in cons.items():
        if kind == "fixed":
            proj[node] = 0
        elif kind == "line":
            proj[node] = np.outer(v[3:6], v[3:6])
        elif kind == "plane":
            proj[node] = np.eye(3) - np.outer(v[3:6], v[3:6])
    # Pressure: positive pushes inward, −p·A_out/4 per corner of each face.
    f = np.zeros((n, 3))
    owners = None
    if isinstance(faces, tuple):
        faces, owners = faces
    x = rest[faces]
    area = 0.5 * np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
    if owners is not None:
        out = x.mean(axis=1) - rest[elements[owners]].mean(axis=1)
        area *= np.sign((area * out).sum(axis=1))[:, None]
    for k in range(4):
        np.add.at(f, faces[:, k], -pressure * area / 4)
    b = np.einsum("nij,nj->ni", proj, f).ravel()

    def matvec(u):
        ue = u.reshape(n, 3)[elements].reshape(len(elements), 24)
        fe = ue @ K.T
        out = np.zeros((n, 3))
        np.add.at(out, elements.ravel(), fe.reshape(-1, 3))
        return np.einsum("nij,nj->ni", proj, out).ravel()

    diag = np.zeros((n, 3))
    kd = np.diag(K).reshape(8, 3)
    for c in range(8):
        np.add.at(diag, elements[:, c], kd[c])
    dinv = 1.0 / np.maximum(diag.ravel(), 1e-30)
    u = np.zeros(3 * n)
    r = b - matvec(u)
    z = dinv * r
    p = z.copy()
    rz = r @ z
    b_norm = np.linalg.norm(b)
    for it in range(maxit):
        Ap = matvec(p)
        alpha = rz / (p @ Ap)
        u += alpha * p
        r -= alpha * Ap
        if np.linalg.norm(r) < tol * b_norm:
            break
        z = dinv * r
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        rz = rz_new
    return u.reshape(n, 3), it


if __name__ == "__main__":
    from analyse import report
    d = sys.argv[1]
    text = open(os.path.join(d, "c3d8_small.inp")).read()
    import re
    pressure = float(re.search(r"\n\d+, P\d, (\S+)", text).group(1))
    _, k_baudet = load_k(os.path.join(d, "cube_k_linear.txt"))
    k8, k8i = fe_stiffness(False), fe_stiffness(True)
    cases = {
        "baudet": k_baudet,
        "c3d8": k8,
        "c3d8i": k8i,
        "baudet_hg_c3d8": with_hourglass_of(k_baudet, k8),
        "baudet_hg_c3d8i": with_hourglass_of(k_baudet, k8i),
    }
    for name, K in cases.items():
        u, it = solve(d, K, pressure)
        np.savetxt(os.path.join(d, f"lin_{name}.u.txt"), u)
        print(f"{name}: {it} CG iterations")
    for name in cases:
        report(d, f"lin_{name}.u.txt", "c3d8_small.u.txt", brief=True)
    report(d, "lin_baudet.u.txt", "u_ours_small.txt", brief=True)
    report(d, "lin_c3d8i.u.txt", "lin_c3d8.u.txt", brief=True)
    report(d, "lin_baudet_hg_c3d8i.u.txt", "lin_c3d8i.u.txt", brief=True)
