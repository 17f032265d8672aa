//! Internal forces of Baudet elements: springs, Voigt dampers and Lagrange corrections.
//!
//! Cost: one pass over the elements, 16 spring evaluations (one square root each) and a
//! 3 × 3 correction per element; no allocation. Elements are processed colour by colour so
//! that parallel threads never add into the same node.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::model::element::{BrickCoefficients, CORNER_SIGNS, SPRINGS};
use crate::model::HexMesh;

type V3 = Vector3<f64>;

/// Per-class constants laid out for the force kernel.
#[derive(Debug, Clone)]
pub struct ElementKernel {
    stiffness: [f64; 16],
    rest_length: [f64; 16],
    damping: [f64; 16],
    correction_map: Matrix3<f64>,
}

impl ElementKernel {
    /// Packs one coefficient set.
    pub fn new(c: &BrickCoefficients) -> Self {
        ElementKernel {
            stiffness: SPRINGS.map(|(_, _, k)| c.spring_stiffness(k)),
            rest_length: SPRINGS.map(|(_, _, k)| c.rest_length_m(k)),
            damping: c.spring_damping_n_s_per_m,
            correction_map: c.correction_map,
        }
    }

    /// Forces in newtons on the 8 corners at positions `x` (and velocities `v` for damping).
    ///
    /// The corrections act along the element's current axes (edge directions averaged and
    /// orthonormalised), so they rotate with the element and stay objective under large rotation.
    #[inline]
    pub fn forces(&self, x: &[V3; 8], v: Option<&[V3; 8]>) -> [V3; 8] {
        let mut f = [V3::zeros(); 8];
        for (s, &(a, b, _)) in SPRINGS.iter().enumerate() {
            let d = x[b] - x[a];
            let len = d.norm();
            let n = d / len;
            let mut t = self.stiffness[s] * (len - self.rest_length[s]);
            if let Some(v) = v {
                t += self.damping[s] * (v[b] - v[a]).dot(&n);
            }
            let fa = n * t;
            f[a] += fa;
            f[b] -= fa;
        }
        // Current element axes.
        let ex = (x[1] - x[0]) + (x[2] - x[3]) + (x[5] - x[4]) + (x[6] - x[7]);
        let ey = (x[3] - x[0]) + (x[2] - x[1]) + (x[7] - x[4]) + (x[6] - x[5]);
        let e1 = ex.normalize();
        let e2 = (ey - e1 * ey.dot(&e1)).normalize();
        let e3 = e1.cross(&e2);
        let axes = [e1, e2, e3];
        // Axial resultants a_i = −½ Σ_n s_n,i (f_n · e_i).
        let mut a = V3::zeros();
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                a[i] -= 0.5 * signs[i] * f[n].dot(&axes[i]);
            }
        }
        let w = self.correction_map * a;
        let wa = [axes[0] * w[0], axes[1] * w[1], axes[2] * w[2]];
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            f[n] += wa[0] * signs[0] + wa[1] * signs[1] + wa[2] * signs[2];
        }
        f
    }
}

/// Evaluates internal forces over a whole mesh.
#[derive(Debug, Clone)]
pub struct ForceEvaluator {
    kernels: Vec<ElementKernel>,
}

/// Below this many elements a colour is processed on one thread (spawn cost dominates).
const PARALLEL_MIN_ELEMENTS: usize = 4096;
const CHUNK: usize = 256;

#[derive(Clone, Copy)]
struct SharedOut(*mut V3);
// SAFETY: elements of one colour share no node, so concurrent writers touch disjoint nodes.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// Adds `f` to node `c`.
    ///
    /// # Safety
    /// `c` must be in bounds and no other thread may access node `c` concurrently.
    #[inline]
    unsafe fn add(&self, c: usize, f: V3) {
        *self.0.add(c) += f;
    }
}

impl ForceEvaluator {
    /// Packs the kernels of every class of `mesh`.
    pub fn new(mesh: &HexMesh) -> Self {
        ForceEvaluator {
            kernels: mesh.classes.iter().map(ElementKernel::new).collect(),
        }
    }

    /// Overwrites `out` with the internal (spring + damper + correction) force on every node.
    pub fn internal_forces(&self, mesh: &HexMesh, x: &[V3], v: Option<&[V3]>, out: &mut [V3]) {
        assert_eq!(x.len(), mesh.node_count());
        assert_eq!(out.len(), mesh.node_count());
        if let Some(v) = v {
            assert_eq!(v.len(), mesh.node_count());
        }
        out.iter_mut().for_each(|f| *f = V3::zeros());
        let shared = SharedOut(out.as_mut_ptr());
        let run = |e: u32| {
            let e = e as usize;
            let corners = &mesh.elements[e];
            let kernel = &self.kernels[mesh.element_class[e] as usize];
            let xe = corners.map(|c| x[c as usize]);
            let fe = match v {
                Some(v) => kernel.forces(&xe, Some(&corners.map(|c| v[c as usize]))),
                None => kernel.forces(&xe, None),
            };
            for (k, &c) in corners.iter().enumerate() {
                // SAFETY: `c` < node_count (checked when the mesh was built) and no other
                // thread writes node `c` while this colour is processed.
                unsafe { shared.add(c as usize, fe[k]) };
            }
        };
        for color in &mesh.colors {
            if color.len() < PARALLEL_MIN_ELEMENTS {
                color.iter().for_each(|&e| run(e));
            } else {
                color
                    .par_chunks(CHUNK)
                    .for_each(|chunk| chunk.iter().for_each(|&e| run(e)));
            }
        }
    }
}
