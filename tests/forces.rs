//! The force kernel against its reference (the scalar per-element kernel assembled in element
//! order) and against physics: objectivity, the small-strain stiffness, Newton's third law.

use lungmotion::model::element::BrickShape;
use lungmotion::model::{BrickCoefficients, HexMesh, Material, VoxelGrid};
use lungmotion::simulation::forces::ElementKernel;
use lungmotion::simulation::ForceEvaluator;
use nalgebra::{Rotation3, SMatrix, Vector3};

type V3 = Vector3<f64>;

/// Deterministic uniform numbers in [−½, ½) (xorshift64*), so failures reproduce.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }

    fn vector(&mut self, scale: f64) -> V3 {
        V3::new(self.next(), self.next(), self.next()) * scale
    }
}

fn block(cells: [usize; 3], edges_m: [f64; 3], material: Material) -> HexMesh {
    VoxelGrid::filled_box(cells, edges_m, V3::new(0.01, -0.02, 0.03))
        .to_mesh(material)
        .unwrap()
        .mesh
}

/// The original kernel: every element through [`ElementKernel::forces`], in element order.
/// Returns the forces and the largest single element-corner force (the rounding scale).
fn reference(mesh: &HexMesh, x: &[V3], v: Option<&[V3]>) -> (Vec<V3>, f64) {
    let kernels: Vec<ElementKernel> = mesh.classes.iter().map(ElementKernel::new).collect();
    let mut out = vec![V3::zeros(); mesh.node_count()];
    let mut scale: f64 = 0.0;
    for (e, corners) in mesh.elements.iter().enumerate() {
        let k = &kernels[mesh.element_class[e] as usize];
        let xe = corners.map(|c| x[c as usize]);
        let ve = v.map(|v| corners.map(|c| v[c as usize]));
        let fe = k.forces(&xe, ve.as_ref());
        for (n, &c) in corners.iter().enumerate() {
            out[c as usize] += fe[n];
            scale = scale.max(fe[n].norm());
        }
    }
    (out, scale)
}

fn evaluate(mesh: &HexMesh, x: &[V3], v: Option<&[V3]>, threads: usize) -> Vec<V3> {
    let eval = ForceEvaluator::new(mesh);
    let mut out = vec![V3::repeat(f64::NAN); mesh.node_count()];
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(|| eval.internal_forces(mesh, x, v, &mut out));
    out
}

fn max_diff(a: &[V3], b: &[V3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (p - q).norm())
        .fold(0.0, f64::max)
}

fn perturbed(mesh: &HexMesh, rng: &mut Rng, amplitude_m: f64) -> Vec<V3> {
    mesh.rest_positions_m
        .iter()
        .map(|p| p + rng.vector(amplitude_m))
        .collect()
}

/// Checks every thread count against one thread (bit for bit) and against the reference.
fn check_against_reference(mesh: &HexMesh, seed: u64) {
    let mut rng = Rng(seed);
    let x = perturbed(mesh, &mut rng, 1e-3);
    let v: Vec<V3> = x.iter().map(|_| rng.vector(0.05)).collect();
    for vel in [None, Some(&v[..])] {
        let (want, scale) = reference(mesh, &x, vel);
        let one = evaluate(mesh, &x, vel, 1);
        let err = max_diff(&one, &want);
        assert!(
            err <= 1e-12 * scale,
            "fast kernel differs from the reference by {err:.3e} N (scale {scale:.3e} N)"
        );
        for threads in [2, 3, 4] {
            let many = evaluate(mesh, &x, vel, threads);
            assert!(
                many.iter().zip(&one).all(|(a, b)| a == b),
                "{threads} threads differ from 1 thread by {:.3e} N",
                max_diff(&many, &one)
            );
        }
    }
}

#[test]
fn parallel_sequential_and_reference_agree_on_a_large_block() {
    let mut mesh = block([26, 24, 22], [5e-3; 3], Material::LUNG);
    mesh.classes[0] = mesh.classes[0].clone().with_damping_ratio(0.3);
    let eval = ForceEvaluator::new(&mesh);
    assert!(
        eval.colour_passes(&mesh) < mesh.colors.len(),
        "a lattice-ordered block should use the chunk schedule"
    );
    check_against_reference(&mesh, 1);
}

#[test]
fn mixed_classes_and_unordered_meshes_agree_with_the_reference() {
    let base = block([18, 17, 16], [4e-3, 4.5e-3, 5e-3], Material::LUNG);
    let shape = BrickShape {
        edges_m: [4e-3, 4.5e-3, 5e-3],
    };
    let classes: Vec<BrickCoefficients> =
        [(390.0, 0.3, 0.0), (1500.0, 0.45, 0.5), (100.0, 0.1, 1.0)]
            .iter()
            .map(|&(e, nu, zeta)| {
                BrickCoefficients::new(shape, Material::new(e, nu, 700.0).unwrap())
                    .unwrap()
                    .with_damping_ratio(zeta)
            })
            .collect();
    let n = base.element_count();
    let class_of: Vec<u32> = (0..n)
        .map(|e| ((e * 7919) % 3 == 0) as u32 + (e % 5 == 0) as u32)
        .collect();
    let mixed = HexMesh::new(
        base.rest_positions_m.clone(),
        base.elements.clone(),
        class_of.clone(),
        classes.clone(),
    )
    .unwrap();
    check_against_reference(&mixed, 2);

    // Shuffled element order: no chunk locality, so the evaluator must use the element colours.
    let mut rng = Rng(3);
    let mut order: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        let j = ((rng.next() + 0.5) * (i + 1) as f64) as usize;
        order.swap(i, j.min(i));
    }
    let shuffled = HexMesh::new(
        base.rest_positions_m.clone(),
        order.iter().map(|&e| base.elements[e]).collect(),
        order.iter().map(|&e| class_of[e]).collect(),
        classes,
    )
    .unwrap();
    let eval = ForceEvaluator::new(&shuffled);
    assert_eq!(eval.colour_passes(&shuffled), shuffled.colors.len());
    check_against_reference(&shuffled, 4);
}

#[test]
fn small_meshes_and_partial_batches_agree_with_the_reference() {
    for cells in [[1, 1, 1], [2, 1, 1], [3, 2, 1], [5, 3, 3]] {
        let mesh = block(cells, [5e-3; 3], Material::LUNG);
        check_against_reference(&mesh, 5);
    }
}

#[test]
fn forces_vanish_at_rest_and_under_rigid_motion() {
    let mut mesh = block([12, 10, 9], [5e-3, 6e-3, 4.5e-3], Material::LUNG);
    mesh.classes[0] = mesh.classes[0].clone().with_damping_ratio(0.5);
    let c = &mesh.classes[0];
    // Force of a spring stretched by its own length: the scale rounding is measured against.
    let scale = c.diagonal_stiffness_n_per_m * c.shape.diagonal_m();
    let rest = &mesh.rest_positions_m;
    let zero_v = vec![V3::zeros(); mesh.node_count()];
    let f = evaluate(&mesh, rest, Some(&zero_v), 2);
    let worst = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
    assert!(worst <= 1e-12 * scale, "force at rest {worst:.3e} N");

    let rotation = Rotation3::from_euler_angles(0.7, -1.1, 2.3);
    let shift = V3::new(0.3, -0.2, 0.05);
    let omega = V3::new(0.4, -1.3, 2.0);
    let x: Vec<V3> = rest.iter().map(|p| rotation * p + shift).collect();
    // Rigid velocity field v = ω × x + u: dampers must not see it either.
    let v: Vec<V3> = x
        .iter()
        .map(|p| omega.cross(p) + V3::new(1.0, 2.0, -3.0))
        .collect();
    for vel in [None, Some(&v[..])] {
        let f = evaluate(&mesh, &x, vel, 2);
        let worst = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
        assert!(
            worst <= 1e-12 * scale,
            "force under rigid motion {worst:.3e} N"
        );
    }
}

#[test]
fn linearised_response_matches_the_small_strain_stiffness() {
    for edges in [[5e-3; 3], [4e-3, 4.8e-3, 3.6e-3]] {
        let mesh = block([3, 3, 2], edges, Material::LUNG);
        let k = mesh.classes[0].linear_stiffness();
        let mut rng = Rng(7);
        let eps = 1e-7 * edges[0];
        let u: Vec<V3> = (0..mesh.node_count()).map(|_| rng.vector(eps)).collect();
        // Assembled −K·u.
        let mut want = vec![V3::zeros(); mesh.node_count()];
        for corners in &mesh.elements {
            let ue = SMatrix::<f64, 24, 1>::from_fn(|r, _| u[corners[r / 3] as usize][r % 3]);
            let fe = -(k * ue);
            for (n, &c) in corners.iter().enumerate() {
                want[c as usize] += V3::new(fe[3 * n], fe[3 * n + 1], fe[3 * n + 2]);
            }
        }
        // Central difference removes the quadratic term.
        let rest = &mesh.rest_positions_m;
        let plus: Vec<V3> = rest.iter().zip(&u).map(|(p, d)| p + d).collect();
        let minus: Vec<V3> = rest.iter().zip(&u).map(|(p, d)| p - d).collect();
        let fp = evaluate(&mesh, &plus, None, 1);
        let fm = evaluate(&mesh, &minus, None, 1);
        let got: Vec<V3> = fp.iter().zip(&fm).map(|(a, b)| (a - b) / 2.0).collect();
        let norm = |v: &[V3]| v.iter().map(|x| x.norm_squared()).sum::<f64>().sqrt();
        let diff: Vec<V3> = got.iter().zip(&want).map(|(a, b)| a - b).collect();
        let rel = norm(&diff) / norm(&want);
        assert!(rel < 1e-6, "edges {edges:?}: relative difference {rel:.3e}");
    }
}

#[test]
fn internal_forces_sum_to_zero() {
    let mut mesh = block([15, 14, 13], [5e-3; 3], Material::LUNG);
    mesh.classes[0] = mesh.classes[0].clone().with_damping_ratio(0.2);
    let mut rng = Rng(11);
    let x = perturbed(&mesh, &mut rng, 1.5e-3);
    let v: Vec<V3> = x.iter().map(|_| rng.vector(0.1)).collect();
    for vel in [None, Some(&v[..])] {
        let f = evaluate(&mesh, &x, vel, 2);
        let sum: V3 = f.iter().sum();
        let total: f64 = f.iter().map(|f| f.norm()).sum();
        assert!(
            sum.norm() <= 1e-13 * total,
            "Σf = {sum:?} against Σ|f| = {total:.3e}"
        );
    }
}

#[test]
fn chunk_schedule_scatters_every_element_once_with_few_barriers() {
    use lungmotion::simulation::forces::ChunkSchedule;
    for n in [7, 20, 33] {
        let mesh = block([n, n, n], [5e-3; 3], Material::LUNG);
        let schedule = ChunkSchedule::new(&mesh.elements, mesh.node_count()).unwrap();
        if mesh.element_count() >= 4096 {
            assert!(
                schedule.colour_count() <= 3,
                "{n}³: {}",
                schedule.colour_count()
            );
        }
        // Each node counts its elements, in 3 slots per node to exercise `per_node`.
        let mut want = vec![0u32; 3 * mesh.node_count()];
        for corners in &mesh.elements {
            for &c in corners {
                for i in 0..3 {
                    want[3 * c as usize + i] += 1 + i as u32;
                }
            }
        }
        for parallel in [false, true] {
            let mut got = vec![0u32; 3 * mesh.node_count()];
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(3)
                .build()
                .unwrap();
            pool.install(|| {
                schedule.for_each_chunk(&mut got, 3, parallel, |elements, lo, window| {
                    for corners in &mesh.elements[elements] {
                        for &c in corners {
                            for i in 0..3 {
                                window[3 * (c as usize - lo) + i] += 1 + i as u32;
                            }
                        }
                    }
                })
            });
            assert_eq!(got, want, "{n}³, parallel {parallel}");
        }
    }
}

#[test]
fn cubic_springs_and_volumetric_laws_agree_with_the_reference() {
    use lungmotion::model::{ContinuumLaw, SpringLaw};
    for (spring, vol) in [
        (SpringLaw::Cubic(3.0), None),
        (SpringLaw::Linear, Some(ContinuumLaw::Hyperfoam)),
        (SpringLaw::Cubic(1.0), Some(ContinuumLaw::LungBirzle)),
    ] {
        let material = Material::LUNG
            .with_spring_law(spring)
            .unwrap()
            .with_volumetric_law(vol);
        let mut mesh = block([20, 18, 17], [5e-3; 3], material);
        mesh.classes[0] = mesh.classes[0].clone().with_damping_ratio(0.3);
        check_against_reference(&mesh, 7);
    }
}

#[test]
fn springs_and_volumetric_laws_leave_rest_and_rigid_motion_force_free() {
    use lungmotion::model::{ContinuumLaw, SpringLaw};
    let material = Material::LUNG
        .with_spring_law(SpringLaw::Cubic(2.0))
        .unwrap()
        .with_volumetric_law(Some(ContinuumLaw::Hyperfoam));
    let largest = largest_force_after_a_rigid_motion(material);
    assert!(largest < 1e-12, "rigid motion gave {largest:e} N");
}

/// The largest node force, N, of a 6 × 5 × 4 block of 5 mm cubes of `material` turned and
/// moved rigidly.
fn largest_force_after_a_rigid_motion(material: Material) -> f64 {
    let mesh = block([6, 5, 4], [5e-3; 3], material);
    let r = Rotation3::from_euler_angles(0.4, -1.1, 2.0);
    let x: Vec<V3> = mesh
        .rest_positions_m
        .iter()
        .map(|p| r * p + V3::new(0.3, -0.2, 0.1))
        .collect();
    let f = evaluate(&mesh, &x, None, 2);
    f.iter().map(|v| v.norm()).fold(0.0, f64::max)
}

/// J·v of the internal forces summed spring by spring: for a spring of tension
/// T = k·e + k₃·e³ along n, d f_a = [T′(ℓ)·n nᵀ + T/ℓ·(I − n nᵀ)]·(v_b − v_a) and f_b = −f_a.
/// `cubic = false` drops k₃ from the tangent (what a solver built on the linear law would use).
fn spring_tangent_product(mesh: &HexMesh, x: &[V3], v: &[V3], cubic: bool) -> Vec<V3> {
    use lungmotion::model::element::SPRINGS;
    let mut out = vec![V3::zeros(); mesh.node_count()];
    for (e, corners) in mesh.elements.iter().enumerate() {
        let class = &mesh.classes[mesh.element_class[e] as usize];
        for (a, b, kind) in SPRINGS {
            let (ia, ib) = (corners[a] as usize, corners[b] as usize);
            let d = x[ib] - x[ia];
            let len = d.norm();
            let n = d / len;
            let ext = len - class.rest_length_m(kind);
            let (k, k3) = (
                class.spring_stiffness(kind),
                class.spring_cubic_n_per_m3(kind),
            );
            let tension = k * ext + k3 * ext.powi(3);
            let slope = k + if cubic { 3.0 * k3 * ext * ext } else { 0.0 };
            let nn = n * n.transpose();
            let tangent = nn * slope + (SMatrix::<f64, 3, 3>::identity() - nn) * (tension / len);
            let df = tangent * (v[ib] - v[ia]);
            out[ia] += df;
            out[ib] -= df;
        }
    }
    out
}

#[test]
fn the_newton_jacobian_product_carries_the_cubic_tangent_exactly() {
    use lungmotion::model::SpringLaw;
    // ν = 1/4: a cube's Lagrange corrections vanish (c_ij = (3 − 12ν)/48), so its forces are
    // the springs' alone and the per-spring tangent above is the exact Jacobian.
    let edge = 5e-3;
    let material = Material::new(390.0, 0.25, 700.0)
        .unwrap()
        .with_spring_law(SpringLaw::Cubic(1.3 / 0.15))
        .unwrap();
    let mesh = block([3, 3, 3], [edge; 3], material);
    let w = mesh.classes[0].correction_map;
    assert!(w.abs().max() < 1e-14, "corrections at ν = 1/4: {w}");
    let mut rng = Rng(0x5eed_cafe);
    // Springs strained up to about ±30 %: the cubic term is a third of the tangent or more.
    let x = perturbed(&mesh, &mut rng, 0.15 * edge);
    let v: Vec<V3> = (0..mesh.node_count()).map(|_| rng.vector(1.0)).collect();
    let exact = spring_tangent_product(&mesh, &x, &v, true);
    let linear_only = spring_tangent_product(&mesh, &x, &v, false);
    // The Newton–Krylov product: a one-sided difference of the production kernel with the
    // quasi-static solver's step, 1e-7 × the shortest edge over max |v|.
    let vmax = v
        .iter()
        .flat_map(|p| p.iter())
        .fold(0.0f64, |m, a| m.max(a.abs()));
    let h = 1e-7 * edge / vmax;
    let xp: Vec<V3> = x.iter().zip(&v).map(|(p, d)| p + d * h).collect();
    let (f0, f1) = (evaluate(&mesh, &x, None, 1), evaluate(&mesh, &xp, None, 1));
    // Sign: the solver differentiates the force, the tangent above too (f_a pulls towards b).
    let fd: Vec<V3> = f1.iter().zip(&f0).map(|(a, b)| (a - b) / h).collect();
    let scale = exact.iter().map(|p| p.norm()).fold(0.0, f64::max);
    let fd_error = max_diff(&fd, &exact) / scale;
    let cubic_share = max_diff(&linear_only, &exact) / scale;
    assert!(
        fd_error < 1e-5,
        "finite-difference product off by {fd_error:e}"
    );
    assert!(
        cubic_share > 0.05,
        "the cubic term changes the tangent by only {cubic_share:e}"
    );
}

/// The batched kernel's continuum correction against the scalar reference, for every law,
/// with cubic springs and dampers, and on a mesh mixing classes with and without a law (lanes
/// of one batch then differ in law and moduli).
#[test]
fn the_continuum_correction_agrees_with_the_reference() {
    use lungmotion::model::{ContinuumLaw, SpringLaw};
    for (spring, law) in [
        (SpringLaw::Linear, ContinuumLaw::NeoHookean),
        (SpringLaw::Cubic(1.0), ContinuumLaw::Hyperfoam),
        (SpringLaw::Linear, ContinuumLaw::LungBirzle),
    ] {
        let material = Material::LUNG
            .with_spring_law(spring)
            .unwrap()
            .with_continuum_correction(Some(law))
            .unwrap();
        let mut mesh = block([20, 18, 17], [5e-3; 3], material);
        mesh.classes[0] = mesh.classes[0].clone().with_damping_ratio(0.3);
        check_against_reference(&mesh, 11);
        // With the hourglass response of a continuum element (evaluated lane by lane).
        let material = material.with_hourglass(lungmotion::model::HourglassLaw::IncompatibleModes);
        let mesh = block([12, 11, 10], [5e-3, 5.5e-3, 4.5e-3], material);
        check_against_reference(&mesh, 13);
    }
    let base = block([18, 17, 16], [4e-3, 4.5e-3, 5e-3], Material::LUNG);
    let shape = BrickShape {
        edges_m: [4e-3, 4.5e-3, 5e-3],
    };
    let classes: Vec<BrickCoefficients> = [
        (390.0, 0.3, Some(ContinuumLaw::NeoHookean)),
        (1500.0, 0.45, None),
        (100.0, 0.1, Some(ContinuumLaw::Hyperfoam)),
    ]
    .iter()
    .map(|&(e, nu, law)| {
        let m = Material::new(e, nu, 700.0)
            .unwrap()
            .with_continuum_correction(law)
            .unwrap();
        BrickCoefficients::new(shape, m).unwrap()
    })
    .collect();
    let n = base.element_count();
    let mixed = HexMesh::new(
        base.rest_positions_m.clone(),
        base.elements.clone(),
        (0..n)
            .map(|e| ((e * 7919) % 3 == 0) as u32 + (e % 5 == 0) as u32)
            .collect(),
        classes,
    )
    .unwrap();
    check_against_reference(&mixed, 12);
}

/// Rest and rigid motion stay force-free with the continuum correction: the law's stress at a
/// rotation is zero and so is the springs' (to round-off of the law's α·F − α·cof F at rest).
#[test]
fn the_continuum_correction_leaves_rest_and_rigid_motion_force_free() {
    use lungmotion::model::{ContinuumLaw, SpringLaw};
    for law in [
        ContinuumLaw::NeoHookean,
        ContinuumLaw::Hyperfoam,
        ContinuumLaw::LungBirzle,
    ] {
        let material = Material::LUNG
            .with_spring_law(SpringLaw::Cubic(2.0))
            .unwrap()
            .with_continuum_correction(Some(law))
            .unwrap();
        let largest = largest_force_after_a_rigid_motion(material);
        // E·h² = 390 Pa × 25 mm² ≈ 1e-2 N: 1e-12 N is 1e-10 of it.
        assert!(largest < 1e-12, "{law:?}: rigid motion gave {largest:e} N");
        let material = material.with_hourglass(lungmotion::model::HourglassLaw::FullIntegration);
        let largest = largest_force_after_a_rigid_motion(material);
        assert!(
            largest < 1e-12,
            "{law:?} with the hourglass correction: rigid motion gave {largest:e} N"
        );
    }
}
