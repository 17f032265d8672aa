//! Planar contours of a mask slice and back: marching squares (outer boundaries and holes
//! as separate closed polygons) and the even-odd fill that rasterises polygons on a slice.
//!
//! Coordinates are continuous voxel indices (i, j) of the slice: voxel (i, j)'s centre is at
//! (i, j). The contours pass through the midpoints between an inside and an outside voxel
//! centre, so filling them by the even-odd rule at the voxel centres gives back exactly the
//! mask: an RTSTRUCT written from a mask and read back recovers it voxel for voxel.

/// One closed polygon of a slice, in voxel indices (the last point joins the first).
#[derive(Debug, Clone, PartialEq)]
pub struct SliceContour {
    /// Vertices (i, j), without the closing repeat of the first.
    pub points_ij: Vec<[f64; 2]>,
    /// Whether it bounds a hole (its inside lies outside the mask): drawn clockwise in (i, j)
    /// where outer boundaries run counter-clockwise.
    pub hole: bool,
}

/// Corner offsets of a marching-squares cell in counter-clockwise order: a (0,0), b (1,0),
/// c (1,1), d (0,1). Edge e goes from corner e to corner e+1.
const CORNERS: [(usize, usize); 4] = [(0, 0), (1, 0), (1, 1), (0, 1)];

/// The closed contours of the voxels of `slice` (ni × nj, i fastest) for which `inside`
/// holds, outer boundaries counter-clockwise and holes clockwise in (i, j). Straight runs
/// are merged into one edge. Diagonal neighbours are separate regions (4-connectivity):
/// each such voxel gets its own polygon.
pub fn slice_contours<T: Copy>(
    slice: &[T],
    ni: usize,
    nj: usize,
    inside: impl Fn(T) -> bool,
) -> Vec<SliceContour> {
    let Some([i0, j0, i1, j1]) = bounding_box(slice, ni, nj, &inside) else {
        return Vec::new();
    };
    // The box padded by one outside voxel each side, so that every contour closes inside it.
    let (w, h) = (i1 - i0 + 3, j1 - j0 + 3);
    let at = |x: usize, y: usize| -> bool {
        // Padded (x, y) is voxel (i0 + x − 1, j0 + y − 1).
        x >= 1
            && y >= 1
            && x <= w - 2
            && y <= h - 2
            && inside(slice[(i0 + x - 1) + ni * (j0 + y - 1)])
    };
    // Edge ids: horizontal edge (x,y)–(x+1,y) is y·w + x; vertical (x,y)–(x,y+1) is
    // w·h + y·w + x. `next[e]` is the edge the contour goes to from edge e.
    let mut next = vec![u32::MAX; 2 * w * h];
    let edge_id = |x: usize, y: usize, e: usize| -> usize {
        match e {
            0 => y * w + x,             // bottom: (x,y)–(x+1,y)
            1 => w * h + y * w + x + 1, // right: (x+1,y)–(x+1,y+1)
            2 => (y + 1) * w + x,       // top: (x,y+1)–(x+1,y+1)
            _ => w * h + y * w + x,     // left: (x,y)–(x,y+1)
        }
    };
    for y in 0..h - 1 {
        for x in 0..w - 1 {
            let corner_in = CORNERS.map(|(dx, dy)| at(x + dx, y + dy));
            // Each run of inside corners s..=t (counter-clockwise) gives one segment from the
            // edge leaving t to the edge entering s: the inside lies on its left.
            for t in 0..4 {
                if corner_in[t] && !corner_in[(t + 1) % 4] {
                    let mut s = t;
                    while corner_in[(s + 3) % 4] {
                        s = (s + 3) % 4;
                    }
                    let from = edge_id(x, y, t);
                    let to = edge_id(x, y, (s + 3) % 4);
                    next[from] = to as u32;
                }
            }
        }
    }
    let midpoint = |e: usize| -> [f64; 2] {
        // Padded coordinates back to slice indices.
        let (ox, oy) = (i0 as f64 - 1.0, j0 as f64 - 1.0);
        if e < w * h {
            let (x, y) = (e % w, e / w);
            [ox + x as f64 + 0.5, oy + y as f64]
        } else {
            let e = e - w * h;
            let (x, y) = (e % w, e / w);
            [ox + x as f64, oy + y as f64 + 0.5]
        }
    };
    let mut contours = Vec::new();
    for start in 0..next.len() {
        if next[start] == u32::MAX {
            continue;
        }
        let mut points = Vec::new();
        let mut e = start;
        while next[e] != u32::MAX {
            points.push(midpoint(e));
            let n = next[e] as usize;
            next[e] = u32::MAX;
            e = n;
        }
        let points = merge_straight_runs(points);
        let hole = signed_area(&points) < 0.0;
        contours.push(SliceContour {
            points_ij: points,
            hole,
        });
    }
    contours
}

/// The box [i0, j0, i1, j1] (inclusive) of the voxels for which `inside` holds, if any.
fn bounding_box<T: Copy>(
    slice: &[T],
    ni: usize,
    nj: usize,
    inside: &impl Fn(T) -> bool,
) -> Option<[usize; 4]> {
    let mut found: Option<[usize; 4]> = None;
    for j in 0..nj {
        for (i, &v) in slice[j * ni..(j + 1) * ni].iter().enumerate() {
            if inside(v) {
                let b = found.get_or_insert([i, j, i, j]);
                *b = [b[0].min(i), b[1].min(j), b[2].max(i), b[3].max(j)];
            }
        }
    }
    found
}

/// Drops the vertices that lie on the straight line through their neighbours.
fn merge_straight_runs(points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    let n = points.len();
    if n < 4 {
        return points;
    }
    (0..n)
        .filter(|&k| {
            let (p, q, r) = (points[(k + n - 1) % n], points[k], points[(k + 1) % n]);
            let cross = (q[0] - p[0]) * (r[1] - q[1]) - (q[1] - p[1]) * (r[0] - q[0]);
            cross.abs() > 1e-9
        })
        .map(|k| points[k])
        .collect()
}

/// The signed area of a closed polygon (positive counter-clockwise).
pub fn signed_area(points: &[[f64; 2]]) -> f64 {
    let n = points.len();
    (0..n)
        .map(|k| {
            let (p, q) = (points[k], points[(k + 1) % n]);
            p[0] * q[1] - q[0] * p[1]
        })
        .sum::<f64>()
        / 2.0
}

/// Marks in `out` (ni × nj, i fastest) the voxels whose centre lies inside an odd number of
/// `polygons` (the even-odd rule: a polygon inside another is a hole), by scan lines through
/// the voxel centres; every voxel of `out` is overwritten with 0 or 1.
pub fn fill_even_odd(polygons: &[Vec<[f64; 2]>], ni: usize, nj: usize, out: &mut [u8]) {
    out.fill(0);
    let (mut y_lo, mut y_hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in polygons.iter().flatten() {
        y_lo = y_lo.min(p[1]);
        y_hi = y_hi.max(p[1]);
    }
    if !(y_lo.is_finite() && y_hi.is_finite()) {
        return;
    }
    let j_first = y_lo.ceil().max(0.0) as usize;
    let j_last = (y_hi.floor().min(nj as f64 - 1.0)).max(-1.0);
    if j_last < 0.0 {
        return;
    }
    let mut crossings: Vec<f64> = Vec::new();
    for j in j_first..=j_last as usize {
        let y = j as f64;
        crossings.clear();
        for polygon in polygons {
            let n = polygon.len();
            for k in 0..n {
                let (p, q) = (polygon[k], polygon[(k + 1) % n]);
                // Half-open in y, so a vertex on the line counts once.
                if (p[1] > y) != (q[1] > y) {
                    crossings.push(p[0] + (y - p[1]) * (q[0] - p[0]) / (q[1] - p[1]));
                }
            }
        }
        crossings.sort_unstable_by(f64::total_cmp);
        let row = &mut out[j * ni..(j + 1) * ni];
        for pair in crossings.chunks_exact(2) {
            let from = pair[0].ceil().max(0.0);
            let to = pair[1].ceil().min(ni as f64);
            if from < to {
                row[from as usize..to as usize].fill(1);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(mask: &[u8], ni: usize, nj: usize) -> (Vec<SliceContour>, Vec<u8>) {
        let contours = slice_contours(mask, ni, nj, |v| v != 0);
        let polygons: Vec<Vec<[f64; 2]>> = contours.iter().map(|c| c.points_ij.clone()).collect();
        let mut back = vec![0u8; ni * nj];
        fill_even_odd(&polygons, ni, nj, &mut back);
        (contours, back)
    }

    #[test]
    fn a_ring_gives_an_outer_boundary_and_a_hole_and_fills_back_exactly() {
        let (ni, nj) = (12, 10);
        let mut mask = vec![0u8; ni * nj];
        for j in 2..8 {
            for i in 2..10 {
                let hole = (4..6).contains(&j) && (4..8).contains(&i);
                mask[i + ni * j] = u8::from(!hole);
            }
        }
        let (contours, back) = round_trip(&mask, ni, nj);
        assert_eq!(contours.len(), 2, "{contours:?}");
        assert_eq!(contours.iter().filter(|c| c.hole).count(), 1);
        assert_eq!(back, mask);
        // Straight runs merged: the outer boundary is an octagon (chamfered corners).
        let outer = contours.iter().find(|c| !c.hole).unwrap();
        assert_eq!(outer.points_ij.len(), 8, "{:?}", outer.points_ij);
    }

    #[test]
    fn touching_edges_single_voxels_and_diagonal_pairs_fill_back_exactly() {
        let (ni, nj) = (9, 7);
        let mut state = 12345u64;
        for _ in 0..200 {
            let mask: Vec<u8> = (0..ni * nj)
                .map(|_| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    u8::from((state >> 33).is_multiple_of(3))
                })
                .collect();
            let (_, back) = round_trip(&mask, ni, nj);
            assert_eq!(back, mask);
        }
    }

    #[test]
    fn an_empty_slice_has_no_contour() {
        assert!(slice_contours(&[0u8; 12], 4, 3, |v| v != 0).is_empty());
    }
}
