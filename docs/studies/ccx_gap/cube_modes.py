"""One 8 mm cube, E = 390 Pa, ν = 0.3: small-strain stiffness on the 12 hourglass (bending and
twist) modes, Baudet's element (dumped by `ccx_gap_study_dump`) against C3D8 (full 2×2×2
integration) and C3D8I (incompatible modes, statically condensed).

  python3 cube_modes.py DIR
"""
import os
import sys

import numpy as np

from ccx import SIGNS

E, NU, L = 390.0, 0.3, 8e-3


def d_matrix():
    lam = E * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E / (2 * (1 + NU))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[:3, :3] += 2 * mu * np.eye(3)
    D[3:, 3:] = mu * np.eye(3)
    return D


def b_rows(dN):
    """Strain-displacement rows (6 × 3n) for shape gradients dN (n × 3), engineering shear."""
    n = len(dN)
    B = np.zeros((6, 3 * n))
    for a in range(n):
        gx, gy, gz = dN[a]
        B[0, 3 * a] = gx
        B[1, 3 * a + 1] = gy
        B[2, 3 * a + 2] = gz
        B[3, 3 * a], B[3, 3 * a + 1] = gy, gx
        B[4, 3 * a + 1], B[4, 3 * a + 2] = gz, gy
        B[5, 3 * a], B[5, 3 * a + 2] = gz, gx
    return B


def fe_stiffness(incompatible):
    D = d_matrix()
    g = 1 / np.sqrt(3)
    K = np.zeros((24, 24))
    Kca = np.zeros((9, 24))
    Kaa = np.zeros((9, 9))
    jac = L / 2
    for p in SIGNS * g:
        xi = p
        dN = SIGNS * np.array([
            (1 + SIGNS[:, 1] * xi[1]) * (1 + SIGNS[:, 2] * xi[2]),
            (1 + SIGNS[:, 0] * xi[0]) * (1 + SIGNS[:, 2] * xi[2]),
            (1 + SIGNS[:, 0] * xi[0]) * (1 + SIGNS[:, 1] * xi[1])]).T / 8 / jac
        B = b_rows(dN)
        w = jac ** 3
        K += B.T @ D @ B * w
        if incompatible:
            dM = np.diag(-2 * xi) / jac  # gradients of 1 − ξ_i², i = 0..2 (3 × 3)
            Ba = b_rows(dM)
            Kca += Ba.T @ D @ B * w
            Kaa += Ba.T @ D @ Ba * w
    if incompatible:
        K -= Kca.T @ np.linalg.solve(Kaa, Kca)
    return K


def load_k(path):
    rows = [[float(v) for v in l.split()] for l in open(path) if l.strip()]
    return np.array(rows[:8]), np.array(rows[8:])


def modes(offsets):
    s = np.sign(offsets)
    h = [s[:, 0] * s[:, 1], s[:, 1] * s[:, 2], s[:, 2] * s[:, 0], s[:, 0] * s[:, 1] * s[:, 2]]
    names, H = [], []
    for k, hk in enumerate(h):
        for i in range(3):
            v = np.zeros((8, 3))
            v[:, i] = hk * L / 2  # corner displacement ± L/2
            H.append(v.ravel())
            names.append(f"u_{'xyz'[i]} = {['ξη', 'ηζ', 'ζξ', 'ξηζ'][k]}")
    return names, np.array(H).T


if __name__ == "__main__":
    d = sys.argv[1]
    offsets, K_b = load_k(os.path.join(d, "cube_k_linear.txt"))
    K_bc = load_k(os.path.join(d, "cube_k_corrected.txt"))[1]
    # Our corner order is C3D8's? (checked: the offsets' signs)
    assert np.allclose(np.sign(offsets), SIGNS), offsets
    K8, K8i = fe_stiffness(False), fe_stiffness(True)
    names, H = modes(offsets)
    print("mode energy ½hᵀKh (nJ) for corner amplitude L/2, Baudet | Baudet+correction | C3D8 | C3D8I; ratio Baudet/C3D8, Baudet/C3D8I")
    for j, nm in enumerate(names):
        h = H[:, j]
        e = [0.5 * h @ K @ h * 1e9 for K in (K_b, K_bc, K8, K8i)]
        print(f"  {nm:10s} {e[0]:9.4f} {e[1]:9.4f} {e[2]:9.4f} {e[3]:9.4f}   {e[0] / e[2]:.3f} {e[0] / max(e[3], 1e-30):.3f}")
    # Homogeneous modes agree? (uniaxial x and shear xy)
    X = offsets
    for nm, F in [("uniaxial ε_xx", np.diag([1e-2, 0, 0])), ("shear γ_xy", np.array([[0, 1e-2, 0], [0, 0, 0], [0, 0, 0]]))]:
        u = (X @ F.T).ravel()
        e = [0.5 * u @ K @ u * 1e9 for K in (K_b, K_bc, K8, K8i)]
        print(f"  {nm:10s} {e[0]:9.4f} {e[1]:9.4f} {e[2]:9.4f} {e[3]:9.4f}")
    # Coupling between hourglass and homogeneous modes in Baudet's K.
    Q, _ = np.linalg.qr(H)
    Kh = {n: Q.T @ K @ Q for n, K in [("Baudet", K_b), ("C3D8", K8), ("C3D8I", K8i)]}
    for n, k in Kh.items():
        w = np.linalg.eigvalsh(0.5 * (k + k.T))
        print(f"  {n:7s} hourglass-block eigenvalues (N/m): {np.round(np.sort(w), 4)}")


G_NH, K_NH = E / (2 * (1 + NU)), E / (3 * (1 - 2 * NU))


def piola_nh(F):
    J = np.linalg.det(F)
    Fit = np.linalg.inv(F).T
    I1 = (F * F).sum()
    return G_NH * J ** (-2 / 3) * (F - I1 / 3 * Fit) + K_NH * (J - 1) * J * Fit


def gauss_grads():
    g = 1 / np.sqrt(3)
    jac = L / 2
    out = []
    for xi in SIGNS * g:
        dN = SIGNS * np.array([
            (1 + SIGNS[:, 1] * xi[1]) * (1 + SIGNS[:, 2] * xi[2]),
            (1 + SIGNS[:, 0] * xi[0]) * (1 + SIGNS[:, 2] * xi[2]),
            (1 + SIGNS[:, 0] * xi[0]) * (1 + SIGNS[:, 1] * xi[1])]).T / 8 / jac
        dM = np.diag(-2 * xi) / jac
        out.append((dN, dM, jac ** 3))
    return out


GP = gauss_grads()


def c3d8_forces(x, incompatible):
    """Internal nodal forces (8 × 3, the force the element exerts is minus this) of a C3D8 /
    C3D8I cube with corners at x, neo-Hookean; incompatible modes solved for equilibrium."""
    def forces(alpha):
        f = np.zeros((8, 3))
        r = np.zeros((3, 3))
        for dN, dM, w in GP:
            F = x.T @ dN + (alpha.T @ dM if incompatible else 0)
            P = piola_nh(F)
            f += dN @ P.T * w
            r += dM @ P.T * w
        return f, r
    alpha = np.zeros((3, 3))
    if incompatible:
        for _ in range(20):
            _, r = forces(alpha)
            if np.abs(r).max() < 1e-16:
                break
            h = 1e-9
            Jm = np.zeros((9, 9))
            for k in range(9):
                a = alpha.copy().ravel()
                a[k] += h
                Jm[:, k] = ((forces(a.reshape(3, 3))[1] - r) / h).ravel()
            alpha = alpha - np.linalg.solve(Jm, r.ravel()).reshape(3, 3)
    return forces(alpha)[0]


def fe_tangent(F, incompatible, offsets):
    x0 = offsets @ F.T
    h = 1e-9
    K = np.zeros((24, 24))
    for c in range(24):
        xp, xm = x0.copy(), x0.copy()
        xp[c // 3, c % 3] += h
        xm[c // 3, c % 3] -= h
        K[:, c] = ((c3d8_forces(xp, incompatible) - c3d8_forces(xm, incompatible)) / (2 * h)).ravel()
    return K


def tangents(d):
    offsets = load_k(os.path.join(d, "cube_k_linear.txt"))[0]
    names, H = modes(offsets)
    blocks = open(os.path.join(d, "cube_tangents_corrected.txt")).read().split("F ")[1:]
    for b in blocks:
        lines = b.strip().split("\n")
        F = np.array([float(v) for v in lines[0].split()]).reshape(3, 3)
        Ko = np.array([[float(v) for v in l.split()] for l in lines[1:25]])
        K8, K8i = fe_tangent(F, False, offsets), fe_tangent(F, True, offsets)
        print(f"F = {np.round(F, 4).tolist()}: hourglass mode energies ½hᵀK_t h (nJ, modes mapped "
              f"by F), ours | C3D8 | C3D8I, ratio ours/C3D8, ours/C3D8I")
        # Modes in the deformed configuration: the same corner patterns (small rotation ignored).
        for j, nm in enumerate(names):
            h = H[:, j]
            e = [0.5 * h @ K @ h * 1e9 for K in (Ko, K8, K8i)]
            print(f"  {nm:10s} {e[0]:9.4f} {e[1]:9.4f} {e[2]:9.4f}   {e[0] / e[1]:.3f} {e[0] / e[2]:.3f}")
        # Homogeneous block (should agree with C3D8 exactly at the centre... C3D8 at 8 points).
        X = offsets
        for nm, G in [("ε_xx", np.diag([1, 0, 0.0])), ("γ_xy", np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0.0]]))]:
            u = (X @ (G * 1e-2).T).ravel()
            e = [0.5 * u @ K @ u * 1e9 for K in (Ko, K8, K8i)]
            print(f"  {nm:10s} {e[0]:9.4f} {e[1]:9.4f} {e[2]:9.4f}")


if __name__ == "__main__" and len(sys.argv) > 2 and sys.argv[2] == "tangents":
    tangents(sys.argv[1])
