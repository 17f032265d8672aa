use lungmotion::model::*;
use lungmotion::simulation::*;
use lungmotion::validation::cases::symmetric_block_under_pressure;
use nalgebra::Vector3;
use std::time::Instant;
fn main() {
    let n: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(10);
    let p: f64 = std::env::args().nth(2).and_then(|s| s.parse().ok()).unwrap_or(-5.0);
    let scene = symmetric_block_under_pressure([n; 3], 0.005, Material::LUNG, p).unwrap();
    let x = scene.mesh.rest_positions_m.clone();
    let mut f = vec![Vector3::zeros(); x.len()];
    let t = Instant::now();
    for _ in 0..20 { scene.internal_forces(&x, None, &mut f); }
    println!("force eval: {:.2} ms", t.elapsed().as_secs_f64() * 1000.0 / 20.0);
    let t = Instant::now();
    let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
    let setup = t.elapsed().as_secs_f64();
    for l in solver.preconditioner_profile(11) { println!("{l:?}"); }
    let (xs, rep) = solver.solve(None).unwrap();
    let v0 = scene.mesh.enclosed_volume_m3(&x);
    let v1 = scene.mesh.enclosed_volume_m3(&xs);
    println!("n={n} elems={} setup {setup:.3}s newton {} linear {} res {:.2e} solve {:.3}s levels {}", scene.mesh.element_count(), rep.newton_iterations, rep.linear_iterations, rep.residual, rep.wall_time_s, rep.multigrid_levels);
    println!("dV/V = {:.5}, linear -p/K = {:.5}", (v1 - v0) / v0, -p / Material::LUNG.bulk_modulus_pa());
}
