//! Each lung's element mask on the lattice, shaped so Baudet's bricks have no mechanism:
//! enclosed cavities filled, one-cell pits closed, one-element-thick parts and parts hanging
//! by an edge or a corner removed (see the module doc, "Mechanisms").

use std::collections::VecDeque;

use super::settings::{LEFT_LUNG, RIGHT_LUNG};

/// Each lung's element mask on the lattice and what shaping them changed.
pub(super) struct LungCells {
    /// (lung label, element mask over the lattice cells), right lung first.
    pub(super) masks: Vec<(u8, Vec<bool>)>,
    /// Cells added by filling cavities enclosed by a lung's elements.
    pub(super) cavity_cells_filled: usize,
    /// Cells added by the 2 × 2 × 2 closing.
    pub(super) notch_cells_filled: usize,
    /// Elements removed by the 2 × 2 × 2 opening.
    pub(super) removed_thin_elements: usize,
    /// Elements removed because they were not face-connected to their lung's largest part.
    pub(super) removed_detached_elements: usize,
}

impl LungCells {
    /// Cells that are an element of either lung.
    pub(super) fn active(&self) -> Vec<bool> {
        let cell_count = self.masks.first().map_or(0, |(_, m)| m.len());
        self.masks
            .iter()
            .fold(vec![false; cell_count], |mut acc, (_, m)| {
                acc.iter_mut().zip(m).for_each(|(a, &b)| *a |= b);
                acc
            })
    }
}

/// Shapes each lung's cells of `cell_lung` (0, 1, 2 per cell) into its element mask.
pub(super) fn shape_lung_cells(cell_lung: &[u8], dims: [usize; 3]) -> LungCells {
    let mut cells = LungCells {
        masks: Vec::new(),
        cavity_cells_filled: 0,
        notch_cells_filled: 0,
        removed_thin_elements: 0,
        removed_detached_elements: 0,
    };
    for lung in [RIGHT_LUNG, LEFT_LUNG] {
        let mut mask: Vec<bool> = cell_lung.iter().map(|&l| l == lung).collect();
        cells.cavity_cells_filled += fill_cavities(&mut mask, dims);
        // Pits may only take cells no other lung claims.
        let free: Vec<bool> = cell_lung.iter().map(|&l| l == 0 || l == lung).collect();
        cells.notch_cells_filled += close_2x2x2(&mut mask, &free, dims);
        cells.removed_thin_elements += open_2x2x2(&mut mask, dims);
        cells.removed_detached_elements += keep_largest_face_component(&mut mask, dims);
        cells.cavity_cells_filled += fill_cavities(&mut mask, dims);
        cells.masks.push((lung, mask));
    }
    cells
}

/// Face neighbours of cell `c` inside `dims`, written into `out`; returns how many.
fn face_neighbours(c: usize, dims: [usize; 3], out: &mut [usize; 6]) -> usize {
    let [nx, ny, nz] = dims;
    let (i, j, k) = (c % nx, c / nx % ny, c / (nx * ny));
    let mut n = 0;
    let mut push = |ok: bool, idx: usize| {
        if ok {
            out[n] = idx;
            n += 1;
        }
    };
    push(i > 0, c.wrapping_sub(1));
    push(i + 1 < nx, c + 1);
    push(j > 0, c.wrapping_sub(nx));
    push(j + 1 < ny, c + nx);
    push(k > 0, c.wrapping_sub(nx * ny));
    push(k + 1 < nz, c + nx * ny);
    n
}

/// Fills background cells not face-connected to the lattice border; returns how many.
fn fill_cavities(mask: &mut [bool], dims: [usize; 3]) -> usize {
    let [nx, ny, nz] = dims;
    let mut outside = vec![false; mask.len()];
    let mut queue = VecDeque::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let border =
                    i == 0 || j == 0 || k == 0 || i + 1 == nx || j + 1 == ny || k + 1 == nz;
                let c = i + nx * (j + ny * k);
                if border && !mask[c] {
                    outside[c] = true;
                    queue.push_back(c);
                }
            }
        }
    }
    let mut nb = [0usize; 6];
    while let Some(c) = queue.pop_front() {
        let n = face_neighbours(c, dims, &mut nb);
        for &d in &nb[..n] {
            if !mask[d] && !outside[d] {
                outside[d] = true;
                queue.push_back(d);
            }
        }
    }
    let mut filled = 0;
    for (m, o) in mask.iter_mut().zip(&outside) {
        if !*m && !*o {
            *m = true;
            filled += 1;
        }
    }
    filled
}

/// Morphological closing by a 2 × 2 × 2 block, restricted to `free` cells away from the
/// lattice border: fills one-cell-wide pits and notches of the surface. Their walls are
/// sliding nodes whose tangent planes lean towards each other, and as the base descends they
/// crush the element at the pit's bottom (CIP at 4 mm: an element inverted before 400 mL).
/// Returns how many cells were added.
fn close_2x2x2(mask: &mut [bool], free: &[bool], dims: [usize; 3]) -> usize {
    let [nx, ny, nz] = dims;
    let mut outside: Vec<bool> = mask.iter().map(|&m| !m).collect();
    open_2x2x2(&mut outside, dims);
    let mut added = 0;
    for k in 1..nz.saturating_sub(1) {
        for j in 1..ny.saturating_sub(1) {
            for i in 1..nx.saturating_sub(1) {
                let c = i + nx * (j + ny * k);
                if !mask[c] && !outside[c] && free[c] {
                    mask[c] = true;
                    added += 1;
                }
            }
        }
    }
    added
}

/// Morphological opening by a 2 × 2 × 2 block: keeps the cells lying in some fully occupied
/// block. Returns how many cells were removed.
fn open_2x2x2(mask: &mut [bool], dims: [usize; 3]) -> usize {
    let [nx, ny, nz] = dims;
    if nx < 2 || ny < 2 || nz < 2 {
        let n = mask.iter().filter(|&&m| m).count();
        mask.iter_mut().for_each(|m| *m = false);
        return n;
    }
    let idx = |i: usize, j: usize, k: usize| i + nx * (j + ny * k);
    // A block is named by its lowest cell.
    let mut block_full = vec![false; mask.len()];
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                block_full[idx(i, j, k)] =
                    (0..8).all(|o| mask[idx(i + (o & 1), j + (o >> 1 & 1), k + (o >> 2))]);
            }
        }
    }
    let mut removed = 0;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let c = idx(i, j, k);
                if !mask[c] {
                    continue;
                }
                let kept = (0..8).any(|o| {
                    let (di, dj, dk) = (o & 1, o >> 1 & 1, o >> 2);
                    i >= di && j >= dj && k >= dk && block_full[idx(i - di, j - dj, k - dk)]
                });
                if !kept {
                    mask[c] = false;
                    removed += 1;
                }
            }
        }
    }
    removed
}

/// Keeps the largest face-connected component; returns how many cells were removed.
fn keep_largest_face_component(mask: &mut [bool], dims: [usize; 3]) -> usize {
    let mut component = vec![u32::MAX; mask.len()];
    let mut sizes: Vec<usize> = Vec::new();
    let mut queue = VecDeque::new();
    let mut nb = [0usize; 6];
    for seed in 0..mask.len() {
        if !mask[seed] || component[seed] != u32::MAX {
            continue;
        }
        let id = sizes.len() as u32;
        let mut size = 0;
        component[seed] = id;
        queue.push_back(seed);
        while let Some(c) = queue.pop_front() {
            size += 1;
            let n = face_neighbours(c, dims, &mut nb);
            for &d in &nb[..n] {
                if mask[d] && component[d] == u32::MAX {
                    component[d] = id;
                    queue.push_back(d);
                }
            }
        }
        sizes.push(size);
    }
    let Some(largest) = (0..sizes.len()).max_by_key(|&c| sizes[c]) else {
        return 0;
    };
    let mut removed = 0;
    for (m, &c) in mask.iter_mut().zip(&component) {
        if *m && c != largest as u32 {
            *m = false;
            removed += 1;
        }
    }
    removed
}
