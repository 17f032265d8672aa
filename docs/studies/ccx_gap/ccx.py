"""CalculiX helpers for the issue-16 gap study: run a deck, read the last displacement block,
make element-type variants and a once-subdivided mesh of the dumped CIP scene.

Usage (study dir = where `ccx_gap_study_dump` wrote its files):
  python3 ccx.py run DIR DECK.inp            -> DECK.u.txt (displacements of every node, m)
  python3 ccx.py variant DIR c3d8_nh.inp C3D8I -> c3d8i_nh.inp (same nodes, other element)
  python3 ccx.py subdivide DIR c3d8_nh.inp   -> sub_nh.inp + sub_map.txt (refined mesh)
"""
import os
import re
import subprocess
import sys
import time

import numpy as np


def run(dirpath, deck, threads=2):
    name = deck[:-4]
    t0 = time.time()
    with open(os.path.join(dirpath, name + ".log"), "w") as log:
        subprocess.run(["nice", "-n", "19", "ccx", "-i", name], cwd=dirpath, stdout=log,
                       stderr=subprocess.STDOUT, env=dict(os.environ, OMP_NUM_THREADS=str(threads)),
                       check=True)
    wall = time.time() - t0
    dat = open(os.path.join(dirpath, name + ".dat")).read()
    start = dat.rfind("displacements (vx,vy,vz) for set")
    if start < 0:
        raise SystemExit(f"{name}: no displacement block")
    header = dat[start:].split("\n", 1)[0]
    rows = {}
    for line in dat[start:].split("\n")[1:]:
        parts = line.split()
        if len(parts) != 4:
            if rows:
                break
            continue
        rows[int(parts[0])] = [float(x) for x in parts[1:]]
    n = max(rows)
    u = np.array([rows[i + 1] for i in range(n)])
    np.savetxt(os.path.join(dirpath, name + ".u.txt"), u)
    print(f"{name}: {header.strip()} wall {wall:.1f} s, {n} nodes")
    return u


def variant(dirpath, deck, etype):
    text = open(os.path.join(dirpath, deck)).read()
    text = re.sub(r"TYPE=C3D8,", f"TYPE={etype},", text)
    out = deck.replace("c3d8", etype.lower())
    open(os.path.join(dirpath, out), "w").write(text)
    print(out)


def parse_deck(text):
    """Splits a deck written by `write_deck` into its parts (nodes, elements, the rest)."""
    lines = text.split("\n")
    i = 0
    nodes, elements, head, tail = [], [], [], []
    section = None
    for line in lines:
        if line.startswith("*NODE,") or line.startswith("*NODE\n"):
            section = "node"
            continue
        if line.startswith("*ELEMENT"):
            section = "element"
            continue
        if line.startswith("*"):
            section = "other"
        if section == "node":
            p = line.split(",")
            nodes.append([float(x) for x in p[1:]])
        elif section == "element":
            elements.append([int(x) - 1 for x in line.split(",")[1:]])
        else:
            tail.append(line)
    return np.array(nodes), np.array(elements), tail


if __name__ == "__main__":
    cmd = sys.argv[1]
    if cmd == "run":
        run(sys.argv[2], sys.argv[3], int(os.environ.get("THREADS", "2")))
    elif cmd == "variant":
        variant(sys.argv[2], sys.argv[3], sys.argv[4])


# C3D8 corner signs (ξ, η, ζ), node order 1…8, which is also our corner order.
SIGNS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                  [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]])
# C3D8 face number of each (axis, side): the face whose corners have that sign on that axis.
FACE_OF = {(2, -1): 1, (2, 1): 2, (1, -1): 3, (0, 1): 4, (1, 1): 5, (0, -1): 6}
RESTRICT = {"fixed": 3, "line": 2, "plane": 1}


def load_scene(d):
    nodes = np.loadtxt(os.path.join(d, "nodes.txt"))
    rest, groups = nodes[:, :3], nodes[:, 3].astype(int)
    elements = np.loadtxt(os.path.join(d, "elements.txt"), dtype=int)
    faces = np.loadtxt(os.path.join(d, "faces.txt"), dtype=int)
    cons = {}
    for line in open(os.path.join(d, "constraints.txt")):
        p = line.split()
        vals = np.array([float(x) for x in p[2:]])
        cons[int(p[0])] = (p[1], vals)
    return rest, groups, elements, faces, cons


def locate_faces(elements, faces):
    """(element, C3D8 face number, axis, side) of every external face."""
    owner = {}
    for e, corners in enumerate(elements):
        for (axis, side), num in FACE_OF.items():
            local = [c for c in range(8) if SIGNS[c][axis] == side]
            owner[frozenset(corners[local])] = (e, num, axis, side)
    return [owner[frozenset(f)] for f in faces]


def frame_with_x(x):
    a = x / np.linalg.norm(x)
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    b = helper - a * helper.dot(a)
    b /= np.linalg.norm(b)
    return a, b


def material_block(deck_text):
    """The *MATERIAL … *SOLID SECTION lines of a deck (copied as they are)."""
    lines = deck_text.split("\n")
    out, on = [], False
    for line in lines:
        if line.startswith("*MATERIAL"):
            on = True
        if on:
            out.append(line)
            if line.startswith("*SOLID SECTION"):
                break
    return "\n".join(out)


def write_deck(path, rest, elements, cons, face_loads, material, pressure, etype="C3D8",
               solver=None):
    d = ["** gap study deck", "*NODE, NSET=NALL"]
    d += [f"{i + 1}, {p[0]:.12e}, {p[1]:.12e}, {p[2]:.12e}" for i, p in enumerate(rest)]
    d.append(f"*ELEMENT, TYPE={etype}, ELSET=E1")
    for e, corners in enumerate(elements):
        ids = [str(c + 1) for c in corners]
        if len(ids) > 15:  # CalculiX reads at most 16 entries a line: continue after 15
            d.append(f"{e + 1}, " + ", ".join(ids[:15]) + ",")
            d.append(", ".join(ids[15:]))
        else:
            d.append(f"{e + 1}, " + ", ".join(ids))
    d.append(material)
    frames, boundary = {}, []
    for n, (kind, v) in sorted(cons.items()):
        if kind == "fixed":
            boundary += [(n, i + 1) for i in range(3)]
        elif kind in ("plane", "line"):
            direction = v[3:6]
            ax = [i for i in range(3) if abs(direction[i]) > 1 - 1e-12]
            if ax:
                if kind == "plane":
                    boundary.append((n, ax[0] + 1))
                else:
                    boundary += [(n, j + 1) for j in range(3) if j != ax[0]]
            else:
                a, b = frame_with_x(direction)
                key = tuple(np.round(a, 12))
                frames.setdefault(key, (a, b, []))[2].append(n)
                boundary += [(n, 1)] if kind == "plane" else [(n, 2), (n, 3)]
    for t, (a, b, members) in enumerate(frames.values()):
        d.append(f"*NSET, NSET=TR{t + 1}")
        for k in range(0, len(members), 8):
            d.append(", ".join(str(m + 1) for m in members[k:k + 8]) + ",")
        d.append(f"*TRANSFORM, NSET=TR{t + 1}, TYPE=R")
        d.append(", ".join(f"{x:.12e}" for x in list(a) + list(b)))
    d.append("*STEP, NLGEOM, INC=1000")
    d.append("*STATIC" + (f", SOLVER={solver}" if solver else ""))
    d.append("1.000000e-1, 1.0, 1.000000e-5, 1.000000e0")
    d.append("*BOUNDARY")
    d += [f"{n + 1}, {dof}, {dof}, 0.0" for n, dof in boundary]
    d.append("*DLOAD")
    d += [f"{e + 1}, P{num}, {pressure:.12e}" for e, num in face_loads]
    d.append("*NODE PRINT, NSET=NALL, GLOBAL=YES\nU\n*END STEP\n")
    open(path, "w").write("\n".join(d))


def merged_constraint(parents, cons):
    """The constraint of a new boundary node from its parents' (majority, ties to the more
    restrictive); planes and lines take the mean direction."""
    kinds = [cons[p][0] for p in parents if p in cons]
    if not kinds:
        return None
    best = max(set(kinds), key=lambda k: (kinds.count(k), RESTRICT[k]))
    if best == "fixed":
        return ("fixed", np.zeros(3))
    dirs = [cons[p][1][3:6] for p in parents if p in cons and cons[p][0] == best]
    ref = dirs[0]
    m = sum(x if x.dot(ref) >= 0 else -x for x in dirs)
    m /= np.linalg.norm(m)
    return (best, np.concatenate([np.zeros(3), m]))


def subdivide(d, deck, solver=None):
    rest, groups, elements, faces, cons = load_scene(d)
    pressure = float(re.search(r"\n\d+, P\d, (\S+)", open(os.path.join(d, deck)).read()).group(1))
    material = material_block(open(os.path.join(d, deck)).read())
    for n, (kind, v) in cons.items():
        if kind in ("plane", "line") and np.linalg.norm(v[:3] - rest[n]) > 1e-9 and kind == "line":
            off = v[:3] - rest[n]
            if np.linalg.norm(off - v[3:6] * off.dot(v[3:6])) > 1e-9:
                raise SystemExit(f"line of node {n} is not through its rest position")
        if kind == "plane" and abs((v[:3] - rest[n]).dot(v[3:6])) > 1e-9:
            raise SystemExit(f"plane of node {n} is not through its rest position")
    located = locate_faces(elements, faces)
    surface_edges, surface_faces = set(), set()
    for f in faces:
        surface_faces.add(frozenset(f))
        for k in range(4):
            surface_edges.add(frozenset((f[k], f[(k + 1) % 4])))
    new_id = {}
    pts = [p for p in rest]
    new_cons = dict(cons)

    def point(key, parents):
        if key in new_id:
            return new_id[key]
        i = len(pts)
        new_id[key] = i
        pts.append(rest[list(parents)].mean(axis=0))
        on_surface = (len(parents) == 2 and key in surface_edges) or (
            len(parents) == 4 and key in surface_faces)
        if on_surface:
            c = merged_constraint(parents, cons)
            if c is not None:
                new_cons[i] = c
        return i

    children, child_faces = [], []
    for e, corners in enumerate(elements):
        grid = {}
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    # Parent corners whose signs match on the axes where (i,j,k) is not 1.
                    sel = [c for c in range(8) if all(
                        ([i, j, k][a] == 1) or (SIGNS[c][a] == [i, j, k][a] - 1)
                        for a in range(3))]
                    parents = frozenset(corners[sel])
                    if len(sel) == 1:
                        grid[i, j, k] = corners[sel[0]]
                    elif len(sel) == 8:
                        grid[i, j, k] = point(("body", e), parents)
                    else:
                        grid[i, j, k] = point(parents, parents)
        base = len(children)
        for a in range(2):
            for b in range(2):
                for c in range(2):
                    children.append([grid[a + (s[0] + 1) // 2, b + (s[1] + 1) // 2,
                                          c + (s[2] + 1) // 2] for s in SIGNS])
    by_elem = {}
    for (fe, num, axis, side) in located:
        by_elem.setdefault(fe, []).append((num, axis, side))
    for e, lst in by_elem.items():
        for num, axis, side in lst:
            for a in range(2):
                for b in range(2):
                    for c in range(2):
                        idx = [a, b, c]
                        if idx[axis] == (0 if side < 0 else 1):
                            child_faces.append((8 * e + 4 * a + 2 * b + c, num))
    pts = np.array(pts)
    if solver == "ARRAYS":
        quads, owners = [], []
        for ce, num in child_faces:
            axis, side = [k for k, v in FACE_OF.items() if v == num][0]
            corners = np.array(children[ce])
            local = [c for c in range(8) if SIGNS[c][axis] == side]
            quad = corners[local]
            # Order the four corners around the face (by angle about its centre).
            p = pts[quad]
            c = p.mean(axis=0)
            ax = [i for i in range(3) if i != axis]
            ang = np.arctan2(p[:, ax[1]] - c[ax[1]], p[:, ax[0]] - c[ax[0]])
            quads.append(quad[np.argsort(ang)])
            owners.append(ce)
        return pts, np.array(children), new_cons, (np.array(quads), np.array(owners))
    name = deck.replace("c3d8", "sub") if solver is None else deck.replace("c3d8", "subit")
    write_deck(os.path.join(d, name), pts, np.array(children), new_cons, child_faces, material,
               pressure, solver=solver)
    np.savetxt(os.path.join(d, "sub_nodes.txt"), pts)
    print(f"{name}: {len(pts)} nodes, {len(children)} elements, {len(new_cons)} constrained, "
          f"{len(child_faces)} loaded faces (coarse: {len(rest)} nodes, {len(cons)} constrained, "
          f"{len(faces)} faces), pressure {pressure}")


if __name__ == "__main__" and sys.argv[1] == "subdivide":
    subdivide(sys.argv[2], sys.argv[3], sys.argv[4] if len(sys.argv) > 4 else None)


# C3D20(R) midside nodes 9…20: the corner pairs of their edges (0-based C3D8 corners).
MIDSIDE = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
           (0, 4), (1, 5), (2, 6), (3, 7)]


def quadratic(d, deck, etype="C3D20R", solver=None):
    """The same mesh with midside nodes (C3D20 or C3D20R); surface midside nodes take their
    corners' constraint (majority, ties to the more restrictive; mean direction)."""
    rest, groups, elements, faces, cons = load_scene(d)
    text = open(os.path.join(d, deck)).read()
    pressure = float(re.search(r"\n\d+, P\d, (\S+)", text).group(1))
    material = material_block(text)
    located = locate_faces(elements, faces)
    surface_edges = set()
    for f in faces:
        for k in range(4):
            surface_edges.add(frozenset((f[k], f[(k + 1) % 4])))
    pts = list(rest)
    new_cons = dict(cons)
    mid = {}
    out = []
    for corners in elements:
        row = list(corners)
        for a, b in MIDSIDE:
            key = frozenset((corners[a], corners[b]))
            if key not in mid:
                mid[key] = len(pts)
                pts.append(0.5 * (rest[corners[a]] + rest[corners[b]]))
                if key in surface_edges:
                    c = merged_constraint(key, cons)
                    if c is not None:
                        new_cons[mid[key]] = c
            row.append(mid[key])
        out.append(row)
    name = deck.replace("c3d8", etype.lower())
    write_deck(os.path.join(d, name), np.array(pts), np.array(out), new_cons,
               [(e, num) for e, num, _, _ in located], material, pressure, etype=etype,
               solver=solver)
    print(f"{name}: {len(pts)} nodes, {len(out)} elements, {len(new_cons)} constrained")


if __name__ == "__main__" and sys.argv[1] == "quadratic":
    quadratic(sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5] if len(sys.argv) > 5 else None)


def rewrite(d, deck, etype="C3D8", solver=None):
    """The dumped scene through this script's own deck writer (checks it against `write_deck`'s
    deck: both must give the same solution)."""
    rest, groups, elements, faces, cons = load_scene(d)
    text = open(os.path.join(d, deck)).read()
    pressure = float(re.search(r"\n\d+, P\d, (\S+)", text).group(1))
    located = locate_faces(elements, faces)
    name = deck.replace("c3d8", "py" + etype.lower() + ("it" if solver else ""))
    write_deck(os.path.join(d, name), rest, elements, cons, [(e, n) for e, n, _, _ in located],
               material_block(text), pressure, etype=etype, solver=solver)
    print(name)


if __name__ == "__main__" and sys.argv[1] == "rewrite":
    rewrite(sys.argv[2], sys.argv[3], *(sys.argv[4:]))
