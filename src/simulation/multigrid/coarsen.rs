//! Coarsening: the next coarser level of the hierarchy (parent cells, coarse nodes,
//! prolongation, Galerkin cell matrices, restricted mass) and the constraints of its
//! directions without stiffness.

use std::collections::HashMap;

use nalgebra::Matrix3;
use rayon::prelude::*;

use super::level::{sparse, Level};
use super::M24;
use crate::model::element::CORNER_SIGNS;

/// Lattice i, j, k and body of a cell or node: what identifies coarse cells and nodes.
type LatticeKey = [u32; 4];

/// Coarse node number of each coarse node's key.
type NodeIndex = HashMap<LatticeKey, u32>;

/// A fine element and its offset (0–7) inside its parent cell.
type Child = (u32, usize);

/// Stiffness below this fraction of a level's largest diagonal block is round-off: the
/// direction is treated as constrained (see `Level::constrain_null_directions`).
const NULL_STIFFNESS_FRACTION: f64 = 1e-10;

/// The next coarser level of `fine`, whose cells and nodes are given as (lattice i, j, k,
/// body); returns it with its own cells and nodes in the same form.
pub(super) fn coarsen(
    fine: &mut Level,
    cells: &[LatticeKey],
    node_ijk: &[LatticeKey],
) -> (Level, Vec<LatticeKey>, Vec<LatticeKey>) {
    let (c_cells, children) = parent_cells(cells);
    let (c_elements, c_nodes, node_index) = coarse_corners(&c_cells);
    fine.prolong = prolongation_rows(node_ijk, &node_index);
    let (matrices, matrix_of) = galerkin_matrices(fine, &children);
    let n_c = c_nodes.len();
    let colors = crate::model::mesh::color_elements(&c_elements, n_c);
    let mass = restricted_mass(fine, n_c);
    let mut level = Level::coarse(c_elements, matrix_of, matrices, colors, mass);
    level.constrain_null_directions();
    level.finish();
    (level, c_cells, c_nodes)
}

/// The parent cells (halved lattice cell, same body) of `cells`, in order of first child,
/// and each parent's children as (fine element, child offset 0–7).
fn parent_cells(cells: &[LatticeKey]) -> (Vec<LatticeKey>, Vec<Vec<Child>>) {
    let mut cell_index: HashMap<LatticeKey, u32> = HashMap::new();
    let mut c_cells: Vec<LatticeKey> = Vec::new();
    let mut children: Vec<Vec<Child>> = Vec::new();
    for (e, c) in cells.iter().enumerate() {
        let parent = [c[0] / 2, c[1] / 2, c[2] / 2, c[3]];
        let o = ((c[0] & 1) | ((c[1] & 1) << 1) | ((c[2] & 1) << 2)) as usize;
        let idx = *cell_index.entry(parent).or_insert_with(|| {
            c_cells.push(parent);
            children.push(Vec::new());
            (c_cells.len() - 1) as u32
        });
        children[idx as usize].push((e as u32, o));
    }
    (c_cells, children)
}

/// The corner nodes of the coarse cells, numbered in order of first use: returns the cells'
/// corners, each node's (lattice i, j, k, body) and the index of each such key.
fn coarse_corners(c_cells: &[LatticeKey]) -> (Vec<[u32; 8]>, Vec<LatticeKey>, NodeIndex) {
    let mut node_index = NodeIndex::new();
    let mut c_nodes: Vec<LatticeKey> = Vec::new();
    let c_elements: Vec<[u32; 8]> = c_cells
        .iter()
        .map(|c| {
            CORNER_SIGNS.map(|s| {
                let l: LatticeKey = std::array::from_fn(|a| {
                    if a < 3 {
                        c[a] + (s[a] > 0.0) as u32
                    } else {
                        c[3]
                    }
                });
                *node_index.entry(l).or_insert_with(|| {
                    c_nodes.push(l);
                    (c_nodes.len() - 1) as u32
                })
            })
        })
        .collect();
    (c_elements, c_nodes, node_index)
}

/// Prolongation rows of the fine nodes: trilinear weights of the coarse nodes around each.
fn prolongation_rows(node_ijk: &[LatticeKey], node_index: &NodeIndex) -> Vec<[(u32, f64); 8]> {
    node_ijk
        .iter()
        .map(|p| {
            let mut row = [(0u32, 0.0f64); 8];
            let mut k = 0;
            let opts = |v: u32| -> [(u32, f64); 2] {
                if v.is_multiple_of(2) {
                    [(v / 2, 1.0), (v / 2, 0.0)]
                } else {
                    [(v / 2, 0.5), (v / 2 + 1, 0.5)]
                }
            };
            let (ox, oy, oz) = (opts(p[0]), opts(p[1]), opts(p[2]));
            for &(i, wi) in &ox {
                for &(j, wj) in &oy {
                    for &(l, wl) in &oz {
                        let w = wi * wj * wl;
                        if w != 0.0 {
                            let c = node_index
                                .get(&[i, j, l, p[3]])
                                .copied()
                                .expect("every fine node lies in an active coarse cell");
                            row[k] = (c, w);
                            k += 1;
                        }
                    }
                }
            }
            row
        })
        .collect()
}

/// Galerkin coarse element matrices, and the matrix of each coarse cell.
///
/// A coarse cell's matrix depends only on its children's offsets, classes and corner
/// projectors; cells agreeing on all three (the interior, and runs along flat constrained
/// faces) share one computed matrix, which keeps the level's matrices few enough to stay in
/// cache during products. The distinct matrices are then computed on all cores, each by the
/// same sum in the same order as alone, so the level is the same bit for bit.
fn galerkin_matrices(fine: &Level, children: &[Vec<Child>]) -> (Vec<M24>, Vec<u32>) {
    let interp: Vec<M24> = (0..8)
        .map(|o| child_interpolation([o & 1, (o >> 1) & 1, (o >> 2) & 1]))
        .collect();
    let node_projector = projector_ids(fine);
    let mut by_children: HashMap<Vec<(usize, u32, [u32; 8])>, u32> = HashMap::new();
    let mut distinct: Vec<&[Child]> = Vec::new();
    let mut matrix_of: Vec<u32> = Vec::with_capacity(children.len());
    for kids in children {
        let mut key: Vec<(usize, u32, [u32; 8])> = kids
            .iter()
            .map(|&(e, o)| {
                let e = e as usize;
                let p =
                    fine.elements[e].map(|n| node_projector.get(n as usize).copied().unwrap_or(0));
                (o, fine.matrix_of[e], p)
            })
            .collect();
        key.sort_unstable();
        let next = distinct.len() as u32;
        let m = *by_children.entry(key).or_insert_with(|| {
            distinct.push(kids);
            next
        });
        matrix_of.push(m);
    }
    // A child none of whose corners is constrained contributes Qᵀ·K·Q for its offset and
    // class alone: computed once per pair (most children of a lung's interior).
    let mut free_pairs: Vec<(usize, u32)> = distinct
        .iter()
        .flat_map(|kids| kids.iter())
        .filter(|&&(e, _)| !child_is_constrained(fine, e))
        .map(|&(e, o)| (o, fine.matrix_of[e as usize]))
        .collect();
    free_pairs.sort_unstable();
    free_pairs.dedup();
    let free_products: HashMap<(usize, u32), M24> = free_pairs
        .par_iter()
        .map(|&(o, m)| {
            let q = &interp[o];
            ((o, m), q.transpose() * fine.matrices[m as usize] * q)
        })
        .collect();
    let matrices = distinct
        .par_iter()
        .map(|kids| galerkin_product(fine, kids, &interp, &free_products))
        .collect();
    (matrices, matrix_of)
}

/// Whether any corner of fine element `e` carries a constraint projector.
fn child_is_constrained(fine: &Level, e: u32) -> bool {
    fine.elements[e as usize]
        .iter()
        .any(|&n| fine.projector.get(n as usize).copied().flatten().is_some())
}

/// Per fine node, an id of its constraint projector (0 = free; equal bits, equal id).
fn projector_ids(fine: &Level) -> Vec<u32> {
    let mut projector_id: HashMap<[u64; 9], u32> = HashMap::new();
    fine.projector
        .iter()
        .map(|p| match p {
            None => 0,
            Some(p) => {
                let bits: [u64; 9] = std::array::from_fn(|i| p.as_slice()[i].to_bits());
                let next = projector_id.len() as u32 + 1;
                *projector_id.entry(bits).or_insert(next)
            }
        })
        .collect()
}

/// Σ Qᵀ·K·Q over a coarse cell's children, Q being the child's interpolation `interp[o]`
/// with its constrained corners' rows projected; an unconstrained child's term is taken from
/// `free_products` (the same product, computed once).
fn galerkin_product(
    fine: &Level,
    kids: &[Child],
    interp: &[M24],
    free_products: &HashMap<(usize, u32), M24>,
) -> M24 {
    let mut kc = M24::zeros();
    for &(e, o) in kids {
        let matrix = fine.matrix_of[e as usize];
        if let Some(term) = free_products.get(&(o, matrix)) {
            if !child_is_constrained(fine, e) {
                kc += term;
                continue;
            }
        }
        let e = e as usize;
        let k = &fine.matrices[matrix as usize];
        let mut q = interp[o];
        for (c, &n) in fine.elements[e].iter().enumerate() {
            if let Some(p) = fine.projector.get(n as usize).copied().flatten() {
                let rows = p * q.fixed_view::<3, 24>(3 * c, 0);
                q.fixed_view_mut::<3, 24>(3 * c, 0).copy_from(&rows);
            }
        }
        kc += q.transpose() * k * q;
    }
    kc
}

/// Lumped coarse mass: the fine masses restricted through the prolongation weights, kg.
fn restricted_mass(fine: &Level, n_c: usize) -> Vec<f64> {
    let mut m = vec![0.0; n_c];
    for (row, mf) in fine.prolong.iter().zip(&fine.mass) {
        for &(c, w) in row {
            m[c as usize] += w * mf;
        }
    }
    m
}

/// Trilinear interpolation from a coarse cell's 8 corners to the 8 corners of its child
/// `offset` (each component 0 or 1), as a 24 × 24 matrix (fine DOF × coarse DOF).
fn child_interpolation(offset: [u32; 3]) -> M24 {
    let mut p = M24::zeros();
    for (fc, fs) in CORNER_SIGNS.iter().enumerate() {
        let t: [f64; 3] =
            std::array::from_fn(|a| (offset[a] as f64 + (fs[a] > 0.0) as u32 as f64) / 2.0);
        for (cc, cs) in CORNER_SIGNS.iter().enumerate() {
            let w: f64 = (0..3)
                .map(|a| if cs[a] > 0.0 { t[a] } else { 1.0 - t[a] })
                .product();
            for i in 0..3 {
                p[(3 * fc + i, 3 * cc + i)] = w;
            }
        }
    }
    p
}

impl Level {
    /// Constrains a coarse level's directions of zero stiffness.
    ///
    /// A coarse node whose fine nodes are all fixed, or all slide on one plane, has no
    /// stiffness along the blocked directions: in exact arithmetic its rows there are zero,
    /// but round-off leaves ~1e-16 of the block, which the inverted diagonal block (and the
    /// coarsest LU) then amplifies by ~1e16 and the smoother diverges (it did on the lungs,
    /// where planes with varied normals meet). Such directions are treated as constrained,
    /// exactly as the fine level treats its fixed and sliding nodes.
    fn constrain_null_directions(&mut self) {
        let diag = self.diagonal_blocks();
        let eigen: Vec<_> = diag.iter().map(|d| d.symmetric_eigen()).collect();
        let scale = eigen
            .iter()
            .map(|e| e.eigenvalues.amax())
            .fold(0.0, f64::max);
        // Round-off is ~1e-16 of the largest block; genuine weak couplings (a coarse node
        // seen through one fine corner at weight 1/8) are ~1e-2 of it.
        let null = NULL_STIFFNESS_FRACTION * scale;
        self.projector = eigen
            .iter()
            .map(|e| {
                let mut p = Matrix3::identity();
                let mut any = false;
                for (k, &value) in e.eigenvalues.iter().enumerate() {
                    if value <= null {
                        let v = e.eigenvectors.column(k);
                        p -= v * v.transpose();
                        any = true;
                    }
                }
                any.then_some(p)
            })
            .collect();
        self.constrained = sparse(&self.projector);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::HourglassLaw;
    use crate::simulation::multigrid::product::tests::irregular_multigrid;

    #[test]
    fn shared_and_parallel_galerkin_matrices_equal_each_cells_own_sum_bit_for_bit() {
        // The fine level of a lung-like lattice with plane, line and fixed nodes and two
        // classes; its elements grouped eight by eight into "coarse cells" with offsets
        // 0–7, so free and constrained children, repeated and unique groups all occur.
        let mg = irregular_multigrid(Matrix3::identity(), HourglassLaw::Springs);
        let fine = &mg.levels[0];
        let children: Vec<Vec<Child>> = (0..fine.elements.len() as u32)
            .collect::<Vec<_>>()
            .chunks(8)
            .map(|c| c.iter().map(|&e| (e, (e % 8) as usize)).collect())
            .collect();
        let interp: Vec<M24> = (0..8)
            .map(|o| child_interpolation([o & 1, (o >> 1) & 1, (o >> 2) & 1]))
            .collect();
        let (matrices, matrix_of) = galerkin_matrices(fine, &children);
        assert!(matrices.len() < children.len(), "some cells share a matrix");
        let free = children
            .iter()
            .flatten()
            .filter(|&&(e, _)| !child_is_constrained(fine, e))
            .count();
        assert!(free > 0 && free < fine.elements.len());
        for (c, kids) in children.iter().enumerate() {
            // Each child's term computed in place, as before the products were shared.
            let mut want = M24::zeros();
            for &(e, o) in kids {
                let e = e as usize;
                let mut q = interp[o];
                for (corner, &n) in fine.elements[e].iter().enumerate() {
                    if let Some(p) = fine.projector[n as usize] {
                        let rows = p * q.fixed_view::<3, 24>(3 * corner, 0);
                        q.fixed_view_mut::<3, 24>(3 * corner, 0).copy_from(&rows);
                    }
                }
                want += q.transpose() * fine.matrices[fine.matrix_of[e] as usize] * q;
            }
            assert_eq!(matrices[matrix_of[c] as usize], want, "coarse cell {c}");
        }
    }
}
