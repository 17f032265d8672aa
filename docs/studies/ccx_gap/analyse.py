"""Compares displacement fields of the dumped CIP scene (issue-16 gap study).

  python3 analyse.py DIR A.txt B.txt [--label NAME]
A and B: one displacement per node (m), A the candidate, B the reference. Prints |A − B| overall,
per group, surface against interior, per direction, a calibration check (best scale of B), the
smooth/local split (difference averaged over the nodes within 2 elements against the rest) and
the elements' homogeneous strain and hourglass content in both fields.
"""
import os
import sys

import numpy as np

from ccx import SIGNS, load_scene

GROUPS = {0: "interior", 1: "hilum", 2: "mediastinal", 3: "costal", 4: "diaphragmatic", 5: "apex"}


def stats(d):
    n = np.linalg.norm(d, axis=1) * 1e3
    return n.mean(), np.percentile(n, 95), n.max(), n


def report(dirpath, a_name, b_name, label=None, brief=False):
    rest, groups, elements, faces, cons = load_scene(dirpath)
    a = np.loadtxt(os.path.join(dirpath, a_name))[: len(rest)]
    b = np.loadtxt(os.path.join(dirpath, b_name))[: len(rest)]
    d = a - b
    mean, p95, mx, n = stats(d)
    ub = np.linalg.norm(b, axis=1) * 1e3
    print(f"== {label or a_name} vs {b_name}: mean {mean:.3f} mm ({100 * mean / ub.mean():.1f} % of "
          f"mean |u_ref| {ub.mean():.2f}), median {np.median(n):.3f}, p95 {p95:.3f}, max {mx:.3f} mm "
          f"at node {n.argmax()} ({GROUPS[groups[n.argmax()]]}, rest {np.round(rest[n.argmax()] * 1e3, 1)} mm, "
          f"u {np.round(a[n.argmax()] * 1e3, 2)} vs {np.round(b[n.argmax()] * 1e3, 2)})")
    if brief:
        return n
    surface = np.zeros(len(rest), bool)
    surface[np.unique(faces)] = True
    for g in sorted(set(groups)):
        m = groups == g
        print(f"   {GROUPS[g]:>13}: {m.sum():5d} nodes, mean {n[m].mean():.3f}, p95 "
              f"{np.percentile(n[m], 95):.3f}, max {n[m].max():.3f} mm; mean |u_ref| {ub[m].mean():.2f}")
    for name, m in [("surface", surface), ("interior", ~surface)]:
        print(f"   {name:>13}: {m.sum():5d} nodes, mean {n[m].mean():.3f}, max {n[m].max():.3f} mm")
    print(f"   signed mean Δu (x, y, z LPS) {np.round(d.mean(axis=0) * 1e3, 3)} mm; mean |Δu_i| "
          f"{np.round(np.abs(d).mean(axis=0) * 1e3, 3)} mm; mean |u_ref,i| {np.round(np.abs(b).mean(axis=0) * 1e3, 2)}")
    # Calibration: A against s·B for the best s.
    s = (a * b).sum() / (b * b).sum()
    ms, _, mxs, _ = stats(a - s * b)
    print(f"   best scale of the reference s = {s:.4f}: mean |A − sB| {ms:.3f}, max {mxs:.3f} mm")
    # Component of Δu along the reference field's direction versus across it.
    ubn = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    along = (d * ubn).sum(axis=1)
    across = d - along[:, None] * ubn
    print(f"   along u_ref: mean {along.mean() * 1e3:+.3f} (mean |.| {np.abs(along).mean() * 1e3:.3f}); across: "
          f"mean |.| {np.linalg.norm(across, axis=1).mean() * 1e3:.3f} mm")
    # Smooth part: mean of Δu over the nodes within 2 element edges (16 mm, a 5³ box).
    h = np.median(np.abs(rest[elements[:, 1]] - rest[elements[:, 0]]).sum(axis=1))
    key = np.round((rest - rest.min(axis=0)) / h).astype(int)
    index = {tuple(k): i for i, k in enumerate(key)}
    smooth = np.zeros_like(d)
    r = 2
    offs = [(i, j, k) for i in range(-r, r + 1) for j in range(-r, r + 1) for k in range(-r, r + 1)]
    for i, k in enumerate(key):
        nb = [index.get((k[0] + o[0], k[1] + o[1], k[2] + o[2])) for o in offs]
        nb = [x for x in nb if x is not None]
        smooth[i] = d[nb].mean(axis=0)
    m1, _, x1, _ = stats(smooth)
    m2, _, x2, n2 = stats(d - smooth)
    print(f"   smooth part (mean over ±{r} nodes): mean {m1:.3f}, max {x1:.3f}; rest: mean {m2:.3f}, "
          f"max {x2:.3f} mm; energy share of the smooth part {np.sum(smooth ** 2) / np.sum(d ** 2):.2f}")
    order = np.sort(n)[::-1]
    for q in (0.01, 0.05, 0.2):
        k = int(q * len(n))
        print(f"   top {100 * q:.0f} % of nodes carry {100 * order[:k].sum() / order.sum():.1f} % of the "
              f"sum of |Δu| (mean without them {order[k:].mean():.3f} mm)")
    # Elements: centre deformation gradient and hourglass content of each field.
    X = rest[elements]                      # (E, 8, 3)
    L = np.abs(X[:, 6] - X[:, 0])           # edges (axis-aligned cubes)
    grads = SIGNS[None, :, :] / (4.0 * L[:, None, :])   # ∇N_a at the centre, (E, 8, 3)
    out = {}
    for name, u in [("A", a), ("B", b)]:
        ue = u[elements]
        Fm = np.einsum("eai,eaj->eij", ue, grads) + np.eye(3)
        Xc = X - X.mean(axis=1, keepdims=True)
        lin = ue.mean(axis=1, keepdims=True) + np.einsum("eij,eaj->eai", Fm - np.eye(3), Xc)
        hg = np.linalg.norm(ue - lin, axis=2).mean(axis=1)
        J = np.linalg.det(Fm)
        out[name] = (Fm, hg, J)
    dF = np.linalg.norm(out["A"][0] - out["B"][0], axis=(1, 2))
    print(f"   elements: |F̄_A − F̄_B| mean {dF.mean():.4f}, max {dF.max():.4f}; |F̄_B − I| mean "
          f"{np.linalg.norm(out['B'][0] - np.eye(3), axis=(1, 2)).mean():.4f}; J mean A {out['A'][2].mean():.4f} "
          f"B {out['B'][2].mean():.4f}, min A {out['A'][2].min():.3f} B {out['B'][2].min():.3f}")
    print(f"   hourglass content (mean |u_a − homogeneous fit| per element): A {out['A'][1].mean() * 1e3:.4f} "
          f"B {out['B'][1].mean() * 1e3:.4f} mm (max A {out['A'][1].max() * 1e3:.3f}, B {out['B'][1].max() * 1e3:.3f})")
    return n


if __name__ == "__main__" and "--modes" not in sys.argv:
    report(sys.argv[1], sys.argv[2], sys.argv[3], brief="--brief" in sys.argv)


def hourglass_modes(dirpath, names):
    """Mean amplitude (mm, corner displacement d = q/8) of each element's hourglass modes by
    kind, for each field."""
    rest, groups, elements, faces, cons = load_scene(dirpath)
    h = np.stack([SIGNS[:, 0] * SIGNS[:, 1], SIGNS[:, 1] * SIGNS[:, 2], SIGNS[:, 2] * SIGNS[:, 0],
                  SIGNS[:, 0] * SIGNS[:, 1] * SIGNS[:, 2]])  # (4, 8)
    kinds = {"bending": [(0, 0), (0, 1), (1, 1), (1, 2), (2, 0), (2, 2)],
             "twist": [(0, 2), (1, 0), (2, 1)], "xyz": [(3, 0), (3, 1), (3, 2)]}
    qs = {}
    for name in names:
        u = np.loadtxt(os.path.join(dirpath, name))[: len(rest)]
        q = np.einsum("ka,eai->eki", h, u[elements]) / 8.0 * 1e3  # (E, 4, 3) mm
        qs[name] = q
        print(f"   {name:22s} " + ", ".join(
            f"{k} {np.mean([np.abs(q[:, a, i]).mean() for a, i in v]):.4f}" for k, v in kinds.items()))
    ref = qs[names[-1]]
    for name in names[:-1]:
        dq = qs[name] - ref
        print(f"   |Δq| {name} vs {names[-1]}: " + ", ".join(
            f"{k} {np.mean([np.abs(dq[:, a, i]).mean() for a, i in v]):.4f}" for k, v in kinds.items()))


if __name__ == "__main__" and "--modes" in sys.argv:
    hourglass_modes(sys.argv[1], [a for a in sys.argv[2:] if not a.startswith("--")])
