//! Flat vector kernels for the solvers (node fields viewed as `[f64]` of length 3·nodes).

use nalgebra::Vector3;
use rayon::prelude::*;

/// Below this length, vector kernels run on one thread.
const PAR_MIN: usize = 1 << 16;
const CHUNK: usize = 1 << 13;

/// Views a node field as a flat slice of coordinates.
pub fn flat(v: &[Vector3<f64>]) -> &[f64] {
    const _: () = assert!(std::mem::size_of::<Vector3<f64>>() == 24);
    // SAFETY: nalgebra's Vector3<f64> is `repr(C)` storage of exactly three f64.
    unsafe { std::slice::from_raw_parts(v.as_ptr() as *const f64, v.len() * 3) }
}

/// Views a flat coordinate slice as a node field.
pub fn nodes(v: &[f64]) -> &[Vector3<f64>] {
    assert_eq!(v.len() % 3, 0);
    // SAFETY: see `flat`; the length is a multiple of three.
    unsafe { std::slice::from_raw_parts(v.as_ptr() as *const Vector3<f64>, v.len() / 3) }
}

/// Mutable node view of a flat coordinate slice.
pub fn nodes_mut(v: &mut [f64]) -> &mut [Vector3<f64>] {
    assert_eq!(v.len() % 3, 0);
    // SAFETY: see `flat`; the length is a multiple of three.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr() as *mut Vector3<f64>, v.len() / 3) }
}

/// Dot product.
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    if a.len() < PAR_MIN {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    } else {
        a.par_chunks(CHUNK)
            .zip(b.par_chunks(CHUNK))
            .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>())
            .sum()
    }
}

/// Euclidean norm.
pub fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

/// y ← y + α·x.
pub fn axpy(alpha: f64, x: &[f64], y: &mut [f64]) {
    if y.len() < PAR_MIN {
        y.iter_mut().zip(x).for_each(|(y, x)| *y += alpha * x);
    } else {
        y.par_chunks_mut(CHUNK)
            .zip(x.par_chunks(CHUNK))
            .for_each(|(y, x)| y.iter_mut().zip(x).for_each(|(y, x)| *y += alpha * x));
    }
}

/// y ← α·y.
pub fn scale(alpha: f64, y: &mut [f64]) {
    if y.len() < PAR_MIN {
        y.iter_mut().for_each(|y| *y *= alpha);
    } else {
        y.par_chunks_mut(CHUNK)
            .for_each(|y| y.iter_mut().for_each(|y| *y *= alpha));
    }
}

/// The Krylov basis of [`gmres`] and its preconditioned images, kept from one call to the
/// next: at 4 mm on the lungs GMRES(40) holds 81 vectors of 2 MB, and allocating and zeroing
/// them afresh cost a Newton step more than its V-cycles when it took one or two iterations.
#[derive(Default)]
pub struct KrylovWorkspace {
    v: Vec<Vec<f64>>,
    z: Vec<Vec<f64>>,
    w: Vec<f64>,
}

impl KrylovWorkspace {
    /// The workspace for systems of `n` unknowns and restart length `m`. Vectors kept from an
    /// earlier call are not zeroed: [`gmres`] writes each one whole before reading it.
    fn sized(&mut self, n: usize, m: usize) -> &mut Self {
        let fit = |vs: &mut Vec<Vec<f64>>, count: usize| {
            vs.truncate(count);
            vs.iter_mut().for_each(|v| v.resize(n, 0.0));
            while vs.len() < count {
                vs.push(vec![0.0; n]);
            }
        };
        fit(&mut self.v, m + 1);
        fit(&mut self.z, m);
        self.w.resize(n, 0.0);
        self
    }
}

/// Restarted GMRES(m) with right preconditioning, so the residual it tracks is the true one.
///
/// Solves A·x = b starting from x; stops at ‖b − A·x‖ ≤ rtol·‖b‖ or `max_iter` iterations.
/// Returns (iterations, relative residual of the Givens recurrence, which right
/// preconditioning makes that of A·x = b itself). Returns early, with the iterate so
/// far, once `stop()` answers true (checked every iteration: a cancelled job stops here).
/// `precondition` must write the whole of its output, as `apply` must.
#[allow(clippy::too_many_arguments)]
pub fn gmres(
    apply: &mut dyn FnMut(&[f64], &mut [f64]),
    precondition: &mut dyn FnMut(&[f64], &mut [f64]),
    stop: &dyn Fn() -> bool,
    b: &[f64],
    x: &mut [f64],
    restart: usize,
    rtol: f64,
    max_iter: usize,
    workspace: &mut KrylovWorkspace,
) -> (usize, f64) {
    let n = b.len();
    let bnorm = norm(b);
    if bnorm == 0.0 {
        x.iter_mut().for_each(|v| *v = 0.0);
        return (0, 0.0);
    }
    let m = restart.max(1);
    let KrylovWorkspace { v, z, w } = workspace.sized(n, m);
    let mut h = vec![vec![0.0; m]; m + 1];
    let (mut cs, mut sn, mut g) = (vec![0.0; m], vec![0.0; m], vec![0.0; m + 1]);
    let mut iters = 0;
    let mut rel;
    loop {
        apply(x, w);
        for (r, (bi, wi)) in v[0].iter_mut().zip(b.iter().zip(w.iter())) {
            *r = bi - wi;
        }
        let beta = norm(&v[0]);
        rel = beta / bnorm;
        if rel <= rtol || iters >= max_iter {
            return (iters, rel);
        }
        scale(1.0 / beta, &mut v[0]);
        g.iter_mut().for_each(|x| *x = 0.0);
        g[0] = beta;
        let mut k_done = 0;
        for k in 0..m {
            precondition(&v[k], &mut z[k]);
            apply(&z[k], w);
            // Modified Gram–Schmidt.
            for i in 0..=k {
                h[i][k] = dot(w, &v[i]);
                axpy(-h[i][k], &v[i], w);
            }
            h[k + 1][k] = norm(w);
            if h[k + 1][k] > 0.0 {
                let inv = 1.0 / h[k + 1][k];
                v[k + 1]
                    .iter_mut()
                    .zip(w.iter())
                    .for_each(|(a, b)| *a = b * inv);
            } else {
                // A lucky breakdown: the basis ends here, as a fresh zero vector would.
                v[k + 1].fill(0.0);
            }
            for i in 0..k {
                let t = cs[i] * h[i][k] + sn[i] * h[i + 1][k];
                h[i + 1][k] = -sn[i] * h[i][k] + cs[i] * h[i + 1][k];
                h[i][k] = t;
            }
            let d = (h[k][k] * h[k][k] + h[k + 1][k] * h[k + 1][k]).sqrt();
            let (c, s) = if d == 0.0 {
                (1.0, 0.0)
            } else {
                (h[k][k] / d, h[k + 1][k] / d)
            };
            cs[k] = c;
            sn[k] = s;
            h[k][k] = d;
            h[k + 1][k] = 0.0;
            g[k + 1] = -s * g[k];
            g[k] *= c;
            iters += 1;
            k_done = k + 1;
            rel = g[k + 1].abs() / bnorm;
            if rel <= rtol || iters >= max_iter || h[k][k] == 0.0 || stop() {
                break;
            }
        }
        // Back-substitution for the Krylov coefficients, then x += Z·y.
        let mut y = vec![0.0; k_done];
        for i in (0..k_done).rev() {
            let mut s = g[i];
            for j in i + 1..k_done {
                s -= h[i][j] * y[j];
            }
            y[i] = if h[i][i] != 0.0 { s / h[i][i] } else { 0.0 };
        }
        for (j, yj) in y.iter().enumerate() {
            axpy(*yj, &z[j], x);
        }
        if rel <= rtol || iters >= max_iter || stop() {
            // The Givens recurrence's residual: with right preconditioning it is that of the
            // unpreconditioned system, so one more product (a force evaluation for the
            // finite-difference Jacobian) to recompute it would buy nothing.
            return (iters, rel);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gmres_solves_nonsymmetric_system() {
        let n = 50;
        // Tridiagonal, non-symmetric, diagonally dominant.
        let mut apply = |x: &[f64], y: &mut [f64]| {
            for i in 0..n {
                y[i] = 4.0 * x[i];
                if i > 0 {
                    y[i] -= 1.5 * x[i - 1];
                }
                if i + 1 < n {
                    y[i] -= 0.5 * x[i + 1];
                }
            }
        };
        let mut id = |x: &[f64], y: &mut [f64]| y.copy_from_slice(x);
        let want: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
        let mut b = vec![0.0; n];
        apply(&want, &mut b);
        let mut x = vec![0.0; n];
        let mut workspace = KrylovWorkspace::default();
        let (_, rel) = gmres(
            &mut apply,
            &mut id,
            &|| false,
            &b,
            &mut x,
            10,
            1e-12,
            500,
            &mut workspace,
        );
        assert!(rel < 1e-11);
        for (a, b) in x.iter().zip(&want) {
            assert!((a - b).abs() < 1e-9);
        }
    }
}
