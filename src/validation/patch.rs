//! Single-element patch tests (thesis §3.3, extraction §1.6): one Baudet brick, loaded so that
//! the continuum definitions (2.3)–(2.6) can be read off its corners, must give back the E, ν
//! and K it was built from, and G for a cube. Non-cubic bricks get G wrong by design (K_d is an
//! average of three per-plane optima, eq. 3.17); the report measures by how much.
//!
//! Also home of the small-scene tools the sweeps and the stability study share: a
//! single-element mesh, axis-aligned symmetry constraints, a dense Newton solver on the real
//! force kernel and a dense solve on the linearised stiffness.

use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use crate::math::V3;
use crate::model::element::CORNER_SIGNS;
use crate::model::{
    BrickCoefficients, BrickShape, ConstraintSet, HexMesh, Loads, Material, NodeConstraint,
    SurfacePressure, VoxelGrid,
};
use crate::simulation::Scene;
use crate::{Error, Result};

/// Builds a one-element mesh with corner 0 at the origin and edges along +x, +y, +z.
pub fn single_element_mesh(edges_m: [f64; 3], material: Material) -> Result<HexMesh> {
    let coeffs = BrickCoefficients::new(BrickShape { edges_m }, material)?;
    let rest = CORNER_SIGNS
        .iter()
        .map(|s| V3::from_fn(|i, _| 0.5 * (s[i] + 1.0) * edges_m[i]))
        .collect();
    HexMesh::new(rest, vec![[0, 1, 2, 3, 4, 5, 6, 7]], vec![0], vec![coeffs])
}

/// The constraint that holds the coordinates of `point_m` flagged in `held` and leaves the
/// other axes free (a plane, a line or a fixed point), or `None` if nothing is held.
pub fn hold_axes(point_m: V3, held: [bool; 3]) -> Option<NodeConstraint> {
    let axis = |want: bool| held.iter().position(|h| *h == want).unwrap_or(0);
    match held.iter().filter(|h| **h).count() {
        0 => None,
        1 => Some(NodeConstraint::Plane {
            point_m,
            normal: V3::ith(axis(true), 1.0),
        }),
        2 => Some(NodeConstraint::Line {
            point_m,
            direction: V3::ith(axis(false), 1.0),
        }),
        _ => Some(NodeConstraint::Fixed { target_m: point_m }),
    }
}

/// Symmetry-plane constraints of a single element: on every corner, the coordinates along
/// which it sits on the negative side are held at their rest values.
pub fn symmetry_constraints(mesh: &HexMesh) -> Result<ConstraintSet> {
    let mut cs = ConstraintSet::new(mesh.node_count());
    for (n, signs) in CORNER_SIGNS.iter().enumerate() {
        let node = mesh.elements[0][n];
        let held = signs.map(|s| s < 0.0);
        if let Some(c) = hold_axes(mesh.rest_positions_m[node as usize], held) {
            cs.set(node, c)?;
        }
    }
    Ok(cs)
}

/// Free coordinate DOFs (3·node + axis) of `scene` at positions `x`.
///
/// The dense solvers work on coordinates, so every constraint must free or hold whole axes;
/// anything else (an oblique plane, a curved surface) is refused.
pub fn free_dofs(scene: &Scene, x: &[V3]) -> Result<Vec<usize>> {
    let mut free = Vec::with_capacity(3 * scene.node_count());
    for (n, xn) in x.iter().enumerate() {
        match scene.constraints.get(n as u32) {
            None => free.extend((0..3).map(|d| 3 * n + d)),
            Some(c) => {
                for d in 0..3 {
                    let e = V3::ith(d, 1.0);
                    let v = scene.constraints.project_free(c, *xn, e);
                    if (v - e).norm() < 1e-12 {
                        free.push(3 * n + d);
                    } else if v.norm() > 1e-12 {
                        return Err(Error::InvalidModel(format!(
                            "node {n}: the dense validation solvers need constraints that hold \
                             or free whole coordinate axes"
                        )));
                    }
                }
            }
        }
    }
    Ok(free)
}

/// Which force model a validation case runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum ForceModel {
    /// `BrickCoefficients::linear_stiffness`, solved densely: checks the formulas alone.
    Linearised,
    /// The production force kernel (`Scene::total_forces`) solved by dense Newton.
    Nonlinear,
}

impl ForceModel {
    /// Short label for tables.
    pub fn label(self) -> &'static str {
        match self {
            ForceModel::Linearised => "linearised K",
            ForceModel::Nonlinear => "force kernel",
        }
    }
}

/// An equilibrium state: positions and the total (internal + external) force at them; on held
/// DOFs that force is minus the reaction.
#[derive(Debug, Clone)]
pub struct Equilibrium {
    /// Node positions in metres.
    pub positions_m: Vec<V3>,
    /// Total force on every node in newtons, constraints not applied.
    pub total_force_n: Vec<V3>,
}

impl Equilibrium {
    /// Reaction (force the constraints apply) on `node` along `axis`, in newtons.
    pub fn reaction(&self, scene: &Scene, node: u32, axis: usize) -> f64 {
        let n = node as usize;
        match scene.constraints.get(node) {
            None => 0.0,
            Some(c) => {
                let f = self.total_force_n[n];
                (scene.constraints.project_free(c, self.positions_m[n], f) - f)[axis]
            }
        }
    }

    /// Displacement of `node` along `axis` from its rest position, in metres.
    pub fn displacement(&self, scene: &Scene, node: u32, axis: usize) -> f64 {
        let n = node as usize;
        self.positions_m[n][axis] - scene.mesh.rest_positions_m[n][axis]
    }
}

/// Solves `scene` for equilibrium with the chosen force model, starting from `initial`.
pub fn equilibrium(scene: &Scene, model: ForceModel, initial: &[V3]) -> Result<Equilibrium> {
    match model {
        ForceModel::Linearised => linear_equilibrium(scene),
        ForceModel::Nonlinear => {
            let (x, _) = DenseNewton::default().solve(scene, initial)?;
            let mut f = vec![V3::zeros(); scene.node_count()];
            scene.total_forces(&x, None, &mut f);
            Ok(Equilibrium {
                positions_m: x,
                total_force_n: f,
            })
        }
    }
}

/// Dense Newton–Raphson on the free coordinates of a small scene, with a finite-difference
/// Jacobian of the production force kernel and a pseudo-inverse step.
///
/// The pseudo-inverse is there because a lone M2 element has three zero-energy twist modes
/// (16 springs for 18 deformation DOFs): loads orthogonal to them still have a unique,
/// minimum-norm answer.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct DenseNewton {
    /// Converged when the relative residual (`Scene::relative_residual`) is below this…
    pub tolerance: f64,
    /// …or when the Newton step is below this fraction of the largest displacement (the
    /// residual's round-off floor is high at 1e-7 strain).
    pub step_tolerance: f64,
    /// Iterations allowed.
    pub max_iterations: usize,
}

impl Default for DenseNewton {
    fn default() -> Self {
        DenseNewton {
            tolerance: 1e-11,
            step_tolerance: 1e-10,
            max_iterations: 60,
        }
    }
}

/// What a dense Newton solve did.
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct NewtonReport {
    /// Newton iterations taken.
    pub iterations: usize,
    /// Final relative residual.
    pub residual: f64,
    /// Free coordinate DOFs.
    pub free_dofs: usize,
    /// Jacobian singular values treated as zero at the last iteration (mechanisms).
    pub null_modes: usize,
}

impl DenseNewton {
    /// Returns the equilibrium positions reached from `initial` (projected onto the
    /// constraints first).
    pub fn solve(&self, scene: &Scene, initial: &[V3]) -> Result<(Vec<V3>, NewtonReport)> {
        let mut x = initial.to_vec();
        scene.constraints.project_positions(&mut x);
        let dofs = free_dofs(scene, &x)?;
        let n = scene.node_count();
        let rest = &scene.mesh.rest_positions_m;
        let length = characteristic_length(&scene.mesh);
        let h = 1e-6 * length;
        let mut buf = vec![V3::zeros(); n];
        let mut scratch = (vec![V3::zeros(); n], vec![V3::zeros(); n]);
        let mut free_force = |x: &[V3]| -> DVector<f64> {
            scene.total_forces(x, None, &mut buf);
            DVector::from_iterator(dofs.len(), dofs.iter().map(|&k| buf[k / 3][k % 3]))
        };
        let mut report = NewtonReport {
            free_dofs: dofs.len(),
            ..Default::default()
        };
        let mut r = free_force(&x);
        loop {
            report.residual = scene.relative_residual(&x, (&mut scratch.0, &mut scratch.1));
            if !report.residual.is_finite() {
                return Err(Error::Diverged {
                    step: report.iterations,
                    cause: "dense Newton produced a non-finite residual".into(),
                });
            }
            if report.residual <= self.tolerance || dofs.is_empty() {
                return Ok((x, report));
            }
            if report.iterations >= self.max_iterations {
                return Err(Error::NotConverged {
                    iterations: report.iterations,
                    residual: report.residual,
                    tolerance: self.tolerance,
                });
            }
            report.iterations += 1;
            let m = dofs.len();
            let mut jac = DMatrix::zeros(m, m);
            for (col, &k) in dofs.iter().enumerate() {
                let orig = x[k / 3][k % 3];
                x[k / 3][k % 3] = orig + h;
                let rp = free_force(&x);
                x[k / 3][k % 3] = orig - h;
                let rm = free_force(&x);
                x[k / 3][k % 3] = orig;
                jac.set_column(col, &((rp - rm) / (2.0 * h)));
            }
            let (step, null) = pseudo_solve(jac, -&r)?;
            report.null_modes = null;
            let mut alpha = 1.0;
            let r_norm = r.norm();
            let (x_new, r_new) = loop {
                let mut trial = x.clone();
                for (i, &k) in dofs.iter().enumerate() {
                    trial[k / 3][k % 3] += alpha * step[i];
                }
                let r_trial = free_force(&trial);
                if r_trial.norm() < r_norm || alpha < 1e-3 {
                    break (trial, r_trial);
                }
                alpha *= 0.5;
            };
            x = x_new;
            r = r_new;
            let u_max = x
                .iter()
                .zip(rest)
                .map(|(p, q)| (p - q).amax())
                .fold(0.0, f64::max);
            if alpha * step.amax() <= self.step_tolerance * u_max {
                report.residual = scene.relative_residual(&x, (&mut scratch.0, &mut scratch.1));
                return Ok((x, report));
            }
        }
    }
}

/// Largest element edge of the mesh, in metres.
fn characteristic_length(mesh: &HexMesh) -> f64 {
    mesh.classes
        .iter()
        .flat_map(|c| c.shape.edges_m)
        .fold(0.0, f64::max)
}

/// Minimum-norm solution of `a·x = b`, and how many singular values were treated as zero.
fn pseudo_solve(a: DMatrix<f64>, b: DVector<f64>) -> Result<(DVector<f64>, usize)> {
    if a.nrows() == 0 {
        return Ok((b, 0));
    }
    let svd = a.svd(true, true);
    let smax = svd.singular_values.max();
    let eps = 1e-10 * smax;
    let null = svd.singular_values.iter().filter(|s| **s <= eps).count();
    let x = svd
        .solve(&b, eps)
        .map_err(|e| Error::InvalidModel(format!("dense solve failed: {e}")))?;
    Ok((x, null))
}

/// Global small-strain stiffness (3n × 3n, force = −K·u) assembled from each class's
/// `linear_stiffness`; the elements must be aligned with the world axes.
pub fn assemble_linear_stiffness(mesh: &HexMesh) -> Result<DMatrix<f64>> {
    let n = mesh.node_count();
    let mut k = DMatrix::zeros(3 * n, 3 * n);
    let blocks: Vec<_> = mesh.classes.iter().map(|c| c.linear_stiffness()).collect();
    for (e, corners) in mesh.elements.iter().enumerate() {
        let p = corners.map(|c| mesh.rest_positions_m[c as usize]);
        for (axis, corner) in [(0, 1), (1, 3), (2, 4)] {
            let d = p[corner] - p[0];
            if d[axis] <= 0.0 || (d.norm() - d[axis]).abs() > 1e-9 * d.norm() {
                return Err(Error::InvalidModel(format!(
                    "element {e} is not aligned with the world axes; the linearised check \
                     assembles element stiffnesses without rotating them"
                )));
            }
        }
        let ke = &blocks[mesh.element_class[e] as usize];
        for (a, &na) in corners.iter().enumerate() {
            for (b, &nb) in corners.iter().enumerate() {
                for i in 0..3 {
                    for j in 0..3 {
                        k[(3 * na as usize + i, 3 * nb as usize + j)] += ke[(3 * a + i, 3 * b + j)];
                    }
                }
            }
        }
    }
    Ok(k)
}

/// Equilibrium of the linearised model: K·u = f_ext on free DOFs, with held DOFs at their
/// constrained positions and external loads evaluated at rest.
pub fn linear_equilibrium(scene: &Scene) -> Result<Equilibrium> {
    let mesh = &scene.mesh;
    let n = mesh.node_count();
    let rest = &mesh.rest_positions_m;
    let x0 = scene.initial_positions();
    let dofs = free_dofs(scene, &x0)?;
    let k = assemble_linear_stiffness(mesh)?;
    let mut f_ext = vec![V3::zeros(); n];
    scene.external_forces(rest, &mut f_ext);
    let mut u = DVector::from_iterator(
        3 * n,
        x0.iter()
            .zip(rest)
            .flat_map(|(x, r)| (x - r).iter().copied().collect::<Vec<_>>()),
    );
    let mut is_free = vec![false; 3 * n];
    for &d in &dofs {
        is_free[d] = true;
        u[d] = 0.0;
    }
    let ku_held = &k * &u;
    let m = dofs.len();
    let kff = DMatrix::from_fn(m, m, |i, j| k[(dofs[i], dofs[j])]);
    let rhs = DVector::from_fn(m, |i, _| f_ext[dofs[i] / 3][dofs[i] % 3] - ku_held[dofs[i]]);
    let (uf, _) = pseudo_solve(kff, rhs)?;
    for (i, &d) in dofs.iter().enumerate() {
        u[d] = uf[i];
    }
    let ku = &k * &u;
    let positions_m = (0..n)
        .map(|i| rest[i] + V3::new(u[3 * i], u[3 * i + 1], u[3 * i + 2]))
        .collect();
    let total_force_n = (0..n)
        .map(|i| f_ext[i] - V3::new(ku[3 * i], ku[3 * i + 1], ku[3 * i + 2]))
        .collect();
    Ok(Equilibrium {
        positions_m,
        total_force_n,
    })
}

/// The element's corners whose side sign along `axis` is `sign`.
pub(crate) fn face_corners(axis: usize, sign: f64) -> impl Iterator<Item = u32> {
    (0..8u32).filter(move |&n| CORNER_SIGNS[n as usize][axis] == sign)
}

/// Mean displacement along `axis` of the corners on side `sign` of `face_axis`.
pub(crate) fn face_mean(
    eq: &Equilibrium,
    scene: &Scene,
    face_axis: usize,
    sign: f64,
    axis: usize,
) -> f64 {
    face_corners(face_axis, sign)
        .map(|n| eq.displacement(scene, n, axis))
        .sum::<f64>()
        / 4.0
}

/// Uniaxial traction along `axis` under symmetry planes: returns E_measured / E and the two
/// ν_measured / ν for the lateral axes (in increasing axis order).
fn uniaxial(
    edges: [f64; 3],
    material: Material,
    axis: usize,
    strain: f64,
    model: ForceModel,
) -> Result<(f64, [(usize, f64); 2])> {
    let mesh = single_element_mesh(edges, material)?;
    let cs = symmetry_constraints(&mesh)?;
    let area = edges[(axis + 1) % 3] * edges[(axis + 2) % 3];
    let force = material.youngs_modulus_pa * strain * area;
    let loads = Loads {
        point_forces_n: face_corners(axis, 1.0)
            .map(|n| (n, V3::ith(axis, force / 4.0)))
            .collect(),
        ..Default::default()
    };
    let scene = Scene::new(mesh, cs, loads)?;
    let eq = equilibrium(&scene, model, &scene.initial_positions())?;
    let axial = face_mean(&eq, &scene, axis, 1.0, axis) / edges[axis];
    let e_ratio = force / area / axial / material.youngs_modulus_pa;
    let lateral = [(axis + 1) % 3, (axis + 2) % 3].map(|j| {
        let eps = face_mean(&eq, &scene, j, 1.0, j) / edges[j];
        (j, -eps / axial / material.poisson_ratio)
    });
    let mut lateral = lateral;
    lateral.sort_by_key(|l| l.0);
    Ok((e_ratio, lateral))
}

/// The outward faces of a single element on the positive side of each axis.
pub(crate) fn positive_faces(mesh: &HexMesh) -> Vec<[u32; 4]> {
    mesh.external_faces
        .iter()
        .filter(|f| (0..3).any(|d| f.iter().all(|&c| CORNER_SIGNS[c as usize][d] > 0.0)))
        .copied()
        .collect()
}

/// Hydrostatic compression by a dead pressure on the three positive faces, symmetry planes on
/// the others: returns K_measured / K with K = P / (−ΔV/V0).
fn hydrostatic(edges: [f64; 3], material: Material, strain: f64, model: ForceModel) -> Result<f64> {
    let mesh = single_element_mesh(edges, material)?;
    let cs = symmetry_constraints(&mesh)?;
    let k = material.bulk_modulus_pa();
    let pressure = 3.0 * k * strain;
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces: positive_faces(&mesh),
            pressure_pa: pressure,
            follows_deformation: false,
        }],
        ..Default::default()
    };
    let scene = Scene::new(mesh, cs, loads)?;
    let eq = equilibrium(&scene, model, &scene.initial_positions())?;
    let volumetric = match model {
        // The linearised model's own measure of volume change is the trace of the strain.
        ForceModel::Linearised => (0..3)
            .map(|d| face_mean(&eq, &scene, d, 1.0, d) / edges[d])
            .sum::<f64>(),
        ForceModel::Nonlinear => {
            let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m);
            scene.mesh.enclosed_volume_m3(&eq.positions_m) / v0 - 1.0
        }
    };
    Ok(pressure / (-volumetric) / k)
}

/// Shear modulus in plane (i, j) measured two ways, both as G_measured / G.
///
/// * Affine: every corner imposed at u_i = γ·x_j; τ is the reaction along i on the +j face
///   over its area. This is the pure-shear energy test of the extraction.
/// * Free: pure-shear tractions τ on the ±i and ±j faces, only a 3-2-1 support against rigid
///   motion; γ = ∂u_i/∂x_j + ∂u_j/∂x_i from mean face displacements. Lateral DOFs relax.
///
/// Also returns the largest support reaction of the free test over the applied face force
/// (zero when the tractions are self-equilibrated and the support restrains nothing).
fn shear(
    edges: [f64; 3],
    material: Material,
    (i, j): (usize, usize),
    strain: f64,
    model: ForceModel,
) -> Result<(f64, f64, f64)> {
    let g = material.shear_modulus_pa();
    let k_axis = 3 - i - j;
    // Affine imposed simple shear.
    let mesh = single_element_mesh(edges, material)?;
    let mut cs = ConstraintSet::new(8);
    for n in 0..8u32 {
        let r = mesh.rest_positions_m[n as usize];
        cs.fix(n, r + V3::ith(i, strain * r[j]))?;
    }
    let scene = Scene::new(mesh, cs, Loads::default())?;
    let eq = equilibrium(&scene, model, &scene.initial_positions())?;
    let f: f64 = face_corners(j, 1.0)
        .map(|n| eq.reaction(&scene, n, i))
        .sum();
    let affine = f / (edges[i] * edges[k_axis]) / strain / g;

    // Traction-driven pure shear with free lateral DOFs.
    let mesh = single_element_mesh(edges, material)?;
    let tau = g * strain;
    let f_on_j = tau * edges[i] * edges[k_axis];
    let f_on_i = tau * edges[j] * edges[k_axis];
    let loads = Loads {
        point_forces_n: (0..8u32)
            .map(|n| {
                let s = CORNER_SIGNS[n as usize];
                (
                    n,
                    V3::ith(i, s[j] * f_on_j / 4.0) + V3::ith(j, s[i] * f_on_i / 4.0),
                )
            })
            .collect(),
        ..Default::default()
    };
    let mut cs = ConstraintSet::new(8);
    let corner = |want: [f64; 3]| CORNER_SIGNS.iter().position(|s| *s == want).unwrap() as u32;
    let minus = [-1.0; 3];
    let mut plus_i = minus;
    plus_i[i] = 1.0;
    let mut plus_j = minus;
    plus_j[j] = 1.0;
    let hold = |axes: &[usize]| std::array::from_fn(|d| axes.contains(&d));
    let supports = [
        (corner(minus), hold(&[0, 1, 2])),
        (corner(plus_i), hold(&[j, k_axis])),
        (corner(plus_j), hold(&[k_axis])),
    ];
    for (n, held) in supports {
        if let Some(c) = hold_axes(mesh.rest_positions_m[n as usize], held) {
            cs.set(n, c)?;
        }
    }
    let scene = Scene::new(mesh, cs, loads)?;
    let eq = equilibrium(&scene, model, &scene.initial_positions())?;
    let gamma = (face_mean(&eq, &scene, j, 1.0, i) - face_mean(&eq, &scene, j, -1.0, i)) / edges[j]
        + (face_mean(&eq, &scene, i, 1.0, j) - face_mean(&eq, &scene, i, -1.0, j)) / edges[i];
    let free = tau / gamma / g;
    let support = supports
        .iter()
        .flat_map(|(n, _)| (0..3).map(|d| eq.reaction(&scene, *n, d).abs()))
        .fold(0.0, f64::max)
        / f_on_j.min(f_on_i);
    Ok((affine, free, support))
}

/// G_measured / G that the pure-shear energy of a brick predicts for plane (i, j):
/// D² / (3·k0²), D the body diagonal and k0 the edge normal to the plane.
pub fn predicted_shear_ratio(edges: [f64; 3], (i, j): (usize, usize)) -> f64 {
    let d2: f64 = edges.iter().map(|e| e * e).sum();
    let k0 = edges[3 - i - j];
    d2 / (3.0 * k0 * k0)
}

/// G_measured / G that the free-traction shear test of a lone element predicts for plane
/// (i, j): the affine ratio times K_k / (K_k + K_d·k0²/D²).
///
/// The free test relaxes one non-affine mode, u_k ∝ s_i·s_j·s_k (the two k-faces warp into
/// opposite saddles), which shortens the body diagonals that shear stretches at the cost of
/// the k-edges: the diagonals and the k-edges then act in series. In a grid that mode must
/// alternate in sign from one element to the next, so homogeneous shear cannot use it and the
/// interior recovers the affine value (see `grid_free_shear_ratio`).
pub fn predicted_free_shear_ratio(coeffs: &BrickCoefficients, (i, j): (usize, usize)) -> f64 {
    let edges = coeffs.shape.edges_m;
    let k = 3 - i - j;
    let d2: f64 = edges.iter().map(|e| e * e).sum();
    let kk = coeffs.edge_stiffness_n_per_m[k];
    predicted_shear_ratio(edges, (i, j)) * kk
        / (kk + coeffs.diagonal_stiffness_n_per_m * edges[k] * edges[k] / d2)
}

/// G_measured / G of an n × n × n grid of cubes under pure-shear tractions in the xy plane
/// (3-2-1 support, linearised model), γ from trapezoid-weighted mean face displacements.
pub fn grid_free_shear_ratio(n: usize, edge_m: f64, material: Material) -> Result<f64> {
    let gm = VoxelGrid::filled_box([n; 3], [edge_m; 3], V3::zeros()).to_mesh(material)?;
    let mesh = gm.mesh;
    let g = material.shear_modulus_pa();
    let tau = g * 1e-7;
    let mut forces = vec![V3::zeros(); mesh.node_count()];
    for f in &mesh.external_faces {
        let p = f.map(|c| mesh.rest_positions_m[c as usize]);
        let area = 0.5 * (p[2] - p[0]).cross(&(p[3] - p[1]));
        // Traction τ along y on ±x faces and along x on ±y faces.
        let t = V3::new(area[1], area[0], 0.0) * tau / 4.0;
        for &c in f {
            forces[c as usize] += t;
        }
    }
    let lattice = |l: [u32; 3]| {
        gm.node_lattice
            .iter()
            .position(|q| *q == l)
            .map(|i| i as u32)
    };
    let nn = n as u32;
    let mut cs = ConstraintSet::new(mesh.node_count());
    let supports = [
        ([0, 0, 0], [true, true, true]),
        ([nn, 0, 0], [false, true, true]),
        ([0, nn, 0], [false, false, true]),
    ];
    for (l, held) in supports {
        let node = lattice(l).ok_or_else(|| Error::InvalidModel("grid corner missing".into()))?;
        if let Some(c) = hold_axes(mesh.rest_positions_m[node as usize], held) {
            cs.set(node, c)?;
        }
    }
    let loads = Loads {
        point_forces_n: forces
            .iter()
            .enumerate()
            .map(|(i, f)| (i as u32, *f))
            .collect(),
        ..Default::default()
    };
    let lattice_of = gm.node_lattice.clone();
    let scene = Scene::new(mesh, cs, loads)?;
    let eq = linear_equilibrium(&scene)?;
    // Trapezoid weight of a node on a face: halved on each face edge it lies on.
    let weight = |l: &[u32; 3], normal: usize| -> f64 {
        (0..3)
            .filter(|&d| d != normal)
            .map(|d| if l[d] == 0 || l[d] == nn { 0.5 } else { 1.0 })
            .product()
    };
    let face_mean = |normal: usize, at: u32, axis: usize| -> f64 {
        let (mut sum, mut wsum) = (0.0, 0.0);
        for (node, l) in lattice_of.iter().enumerate() {
            if l[normal] == at {
                let w = weight(l, normal);
                sum += w * eq.displacement(&scene, node as u32, axis);
                wsum += w;
            }
        }
        sum / wsum
    };
    let side = n as f64 * edge_m;
    let gamma = (face_mean(1, nn, 0) - face_mean(1, 0, 0)) / side
        + (face_mean(0, nn, 1) - face_mean(0, 0, 1)) / side;
    Ok(tau / gamma / g)
}

/// Largest relative difference between the force kernel's finite-difference Jacobian at rest
/// and `−linear_stiffness()`, over the largest stiffness entry.
pub fn kernel_linearisation_error(edges: [f64; 3], material: Material) -> Result<f64> {
    let mesh = single_element_mesh(edges, material)?;
    let k = mesh.classes[0].linear_stiffness();
    let scene = Scene::new(mesh, ConstraintSet::new(8), Loads::default())?;
    let h = 1e-6 * edges.iter().cloned().fold(0.0, f64::max);
    let mut x = scene.mesh.rest_positions_m.clone();
    let (mut fp, mut fm) = (vec![V3::zeros(); 8], vec![V3::zeros(); 8]);
    let mut worst: f64 = 0.0;
    for col in 0..24 {
        let orig = x[col / 3][col % 3];
        x[col / 3][col % 3] = orig + h;
        scene.internal_forces(&x, None, &mut fp);
        x[col / 3][col % 3] = orig - h;
        scene.internal_forces(&x, None, &mut fm);
        x[col / 3][col % 3] = orig;
        for row in 0..24 {
            let jac = (fp[row / 3][row % 3] - fm[row / 3][row % 3]) / (2.0 * h);
            worst = worst.max((jac + k[(row, col)]).abs());
        }
    }
    Ok(worst / k.amax())
}

/// What the patch tests run.
#[derive(Debug, Clone, Serialize)]
pub struct PatchConfig {
    /// Element shapes (edges x, y, z in metres).
    pub shapes_m: Vec<[f64; 3]>,
    /// Poisson ratios.
    pub poisson_ratios: Vec<f64>,
    /// Young's modulus in pascals.
    pub youngs_modulus_pa: f64,
    /// Density in kg/m³ (irrelevant to statics; needed to build the material).
    pub density_kg_per_m3: f64,
    /// Imposed strain (or stress over modulus) of every test.
    pub strain: f64,
    /// Relative error allowed on E, ν and K (and on G for cubes).
    pub tolerance: f64,
    /// Cube-grid sizes n of the free-traction shear study (n × n × n elements).
    pub grid_sizes: Vec<usize>,
}

impl Default for PatchConfig {
    fn default() -> Self {
        PatchConfig {
            shapes_m: vec![[0.01; 3], [0.010, 0.012, 0.009]],
            poisson_ratios: vec![0.1, 0.3, 0.45],
            youngs_modulus_pa: 1000.0,
            density_kg_per_m3: 700.0,
            strain: 1e-7,
            tolerance: 1e-5,
            grid_sizes: vec![1, 2, 3, 4],
        }
    }
}

/// Shear measured in one plane.
#[derive(Debug, Clone, Serialize)]
pub struct ShearResult {
    /// Plane (i, j): displacement along i varying with x_j.
    pub plane: (usize, usize),
    /// G_measured / G, affine imposed shear (pure-shear energy test).
    pub affine_ratio: f64,
    /// G_measured / G, traction-driven pure shear with free lateral DOFs.
    pub free_ratio: f64,
    /// D²/(3·k0²): what the pure-shear energy predicts (extraction §1.6 table).
    pub predicted_ratio: f64,
    /// What the free test predicts: `predicted_free_shear_ratio`.
    pub predicted_free_ratio: f64,
    /// Largest support reaction of the free test over the applied face force.
    pub free_support_reaction: f64,
}

/// One shape, one ν, one force model.
#[derive(Debug, Clone, Serialize)]
pub struct PatchCase {
    /// Element edges in metres.
    pub edges_m: [f64; 3],
    /// Poisson ratio imposed.
    pub poisson_ratio: f64,
    /// Force model solved.
    pub model: ForceModel,
    /// E_measured / E for traction along x, y, z.
    pub youngs_ratio: [f64; 3],
    /// (load axis, lateral axis, ν_measured / ν) for the six pairs.
    pub poisson_ratio_ratios: Vec<(usize, usize, f64)>,
    /// K_measured / K under hydrostatic dead pressure.
    pub bulk_ratio: f64,
    /// Shear in planes xy, xz, yz.
    pub shear: Vec<ShearResult>,
    /// Largest |ratio − 1| over E, ν and K.
    pub max_error_e_nu_k: f64,
}

/// Outcome of the patch tests.
#[derive(Debug, Clone, Serialize)]
pub struct PatchReport {
    /// What was run.
    pub config: PatchConfig,
    /// Every case, linearised and nonlinear.
    pub cases: Vec<PatchCase>,
    /// Per shape and ν: how far the kernel's Jacobian at rest is from `linear_stiffness()`.
    pub kernel_linearisation: Vec<([f64; 3], f64, f64)>,
    /// (n, ν, G_measured / G) of n × n × n cube grids under free pure-shear tractions.
    pub grid_shear: Vec<(usize, f64, f64)>,
    /// Whether every E, ν, K (and cube G) error is within the tolerance.
    pub passed: bool,
}

/// Runs the single-element patch tests.
pub fn run_patch_tests(config: &PatchConfig) -> Result<PatchReport> {
    let mut cases = Vec::new();
    let mut kernel_linearisation = Vec::new();
    let mut grid_shear = Vec::new();
    let mut passed = true;
    for &edges in &config.shapes_m {
        let cube = edges
            .iter()
            .all(|e| (e - edges[0]).abs() <= 1e-12 * edges[0]);
        for &nu in &config.poisson_ratios {
            let material = Material::new(config.youngs_modulus_pa, nu, config.density_kg_per_m3)?;
            kernel_linearisation.push((edges, nu, kernel_linearisation_error(edges, material)?));
            if cube {
                for &n in &config.grid_sizes {
                    grid_shear.push((n, nu, grid_free_shear_ratio(n, edges[0], material)?));
                }
            }
            for model in [ForceModel::Linearised, ForceModel::Nonlinear] {
                let case = patch_case(edges, material, config.strain, model)?;
                passed &= case.max_error_e_nu_k <= config.tolerance;
                for s in &case.shear {
                    let close = |a: f64, b: f64| (a / b - 1.0).abs() <= config.tolerance;
                    passed &= close(s.affine_ratio, s.predicted_ratio);
                    passed &= close(s.free_ratio, s.predicted_free_ratio);
                    passed &= !cube || close(s.affine_ratio, 1.0);
                }
                cases.push(case);
            }
        }
    }
    Ok(PatchReport {
        config: config.clone(),
        cases,
        kernel_linearisation,
        grid_shear,
        passed,
    })
}

/// Every measurement for one shape, material and force model.
pub fn patch_case(
    edges_m: [f64; 3],
    material: Material,
    strain: f64,
    model: ForceModel,
) -> Result<PatchCase> {
    let mut youngs_ratio = [0.0; 3];
    let mut poisson_ratio_ratios = Vec::new();
    for (axis, e) in youngs_ratio.iter_mut().enumerate() {
        let (er, lateral) = uniaxial(edges_m, material, axis, strain, model)?;
        *e = er;
        for (j, r) in lateral {
            poisson_ratio_ratios.push((axis, j, r));
        }
    }
    let bulk_ratio = hydrostatic(edges_m, material, strain, model)?;
    let coeffs = BrickCoefficients::new(BrickShape { edges_m }, material)?;
    let mut shear_results = Vec::new();
    for plane in [(0, 1), (0, 2), (1, 2)] {
        let (affine_ratio, free_ratio, free_support_reaction) =
            shear(edges_m, material, plane, strain, model)?;
        shear_results.push(ShearResult {
            plane,
            affine_ratio,
            free_ratio,
            predicted_ratio: predicted_shear_ratio(edges_m, plane),
            predicted_free_ratio: predicted_free_shear_ratio(&coeffs, plane),
            free_support_reaction,
        });
    }
    let max_error_e_nu_k = youngs_ratio
        .iter()
        .chain(poisson_ratio_ratios.iter().map(|p| &p.2))
        .chain(std::iter::once(&bulk_ratio))
        .map(|r| (r - 1.0).abs())
        .fold(0.0, f64::max);
    Ok(PatchCase {
        edges_m,
        poisson_ratio: material.poisson_ratio,
        model,
        youngs_ratio,
        poisson_ratio_ratios,
        bulk_ratio,
        shear: shear_results,
        max_error_e_nu_k,
    })
}

const AXES: [&str; 3] = ["x", "y", "z"];

fn shape_label(edges: [f64; 3]) -> String {
    format!(
        "{} × {} × {} mm",
        edges[0] * 1e3,
        edges[1] * 1e3,
        edges[2] * 1e3
    )
}

impl PatchReport {
    /// Markdown tables: measured over imposed, beside what the thesis and its extraction state.
    pub fn to_markdown(&self) -> String {
        use crate::markdown::Table;
        let mut s = String::new();
        s.push_str("## Single-element patch tests\n\n");
        s.push_str(&format!(
            "One element, symmetry planes on the three negative faces; traction F/4 on each \
             corner of a positive face, hydrostatic dead pressure on the three positive faces; \
             strain {:.0e}; E = {} Pa. Ratios are measured / imposed, with the continuum \
             definitions (2.3)–(2.6). Thesis (§3.3.3, verified in the extraction §1.6): E, both \
             ν and K exact for any admissible brick, G exact for cubes.\n\n",
            self.config.strain, self.config.youngs_modulus_pa
        ));
        let mut table = Table::new([
            "shape",
            "ν",
            "model",
            "E/E (x, y, z)",
            "worst ν/ν",
            "K/K",
            "max error E, ν, K",
            "thesis",
        ]);
        for c in &self.cases {
            let worst_nu = c
                .poisson_ratio_ratios
                .iter()
                .map(|p| p.2)
                .max_by(|a, b| (a - 1.0).abs().total_cmp(&(b - 1.0).abs()))
                .unwrap_or(f64::NAN);
            let [ex, ey, ez] = c.youngs_ratio;
            table.row([
                shape_label(c.edges_m),
                c.poisson_ratio.to_string(),
                c.model.label().into(),
                format!("{ex:.9}, {ey:.9}, {ez:.9}"),
                format!("{worst_nu:.9}"),
                format!("{:.9}", c.bulk_ratio),
                format!("{:.1e}", c.max_error_e_nu_k),
                "exact".into(),
            ]);
        }
        table.write_to(&mut s);
        s.push_str("\n### Shear modulus, G_measured / G\n\n");
        s.push_str(
            "*Affine*: all corners imposed at u_i = γ·x_j, τ = reaction on the +j face / area \
             (the pure-shear energy test of the extraction). *Free*: pure-shear tractions on the \
             four faces, 3-2-1 support only, γ from mean face displacements. *Extraction*: \
             D²/(3·k0²), k0 the edge normal to the plane (1.337, 0.752, 1.083 for \
             1 × 1.2 × 0.9). *Free, predicted*: the affine value times K_k / (K_k + K_d·k0²/D²): \
             with free corners the element relaxes its warping mode u_k ∝ s_i·s_j·s_k, which \
             relieves the body diagonals through the k-edges (in series); for a cube this is \
             (1+4ν)/(2+4ν).\n\n",
        );
        let mut table = Table::new([
            "shape",
            "ν",
            "model",
            "plane",
            "affine",
            "extraction",
            "free",
            "free, predicted",
            "free-test support reaction",
        ]);
        for c in &self.cases {
            for g in &c.shear {
                table.row([
                    shape_label(c.edges_m),
                    c.poisson_ratio.to_string(),
                    c.model.label().into(),
                    format!("{}{}", AXES[g.plane.0], AXES[g.plane.1]),
                    format!("{:.6}", g.affine_ratio),
                    format!("{:.6}", g.predicted_ratio),
                    format!("{:.6}", g.free_ratio),
                    format!("{:.6}", g.predicted_free_ratio),
                    format!("{:.1e}", g.free_support_reaction),
                ]);
            }
        }
        table.write_to(&mut s);
        if !self.grid_shear.is_empty() {
            s.push_str(
                "\n### Free-traction shear of n × n × n cube grids (linearised, xy plane)\n\n\
                 The warping mode that softens a lone element must alternate in sign between \
                 neighbours, so a grid under homogeneous shear can only use it in a boundary \
                 layer: G_measured / G should rise towards 1 with n.\n\n",
            );
            let mut table = Table::new(["n", "ν", "G_measured / G"]);
            for (n, nu, r) in &self.grid_shear {
                table.row([n.to_string(), nu.to_string(), format!("{r:.6}")]);
            }
            table.write_to(&mut s);
        }
        s.push_str("\n### Force kernel vs `linear_stiffness()`\n\n");
        let mut table = Table::new(["shape", "ν", "max abs(J_kernel + K) / max abs(K)"]);
        for (edges, nu, err) in &self.kernel_linearisation {
            table.row([shape_label(*edges), nu.to_string(), format!("{err:.1e}")]);
        }
        table.write_to(&mut s);
        s.push_str(&format!(
            "\nAll E, ν, K (and cube G) within {:.0e}: **{}**\n",
            self.config.tolerance,
            if self.passed { "yes" } else { "NO" }
        ));
        s
    }
}
