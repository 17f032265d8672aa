use lungmotion::model::*;
use lungmotion::simulation::*;
use nalgebra::Vector3;
fn main() {
    let n: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(10);
    let p: f64 = std::env::args().nth(2).and_then(|s| s.parse().ok()).unwrap_or(-20.0);
    let h = 0.005;
    let grid = VoxelGrid::filled_box([n; 3], [h; 3], Vector3::zeros());
    let gm = grid.to_mesh(Material::LUNG).unwrap();
    let mesh = gm.mesh;
    let mut cs = ConstraintSet::new(mesh.node_count());
    for (i, l) in gm.node_lattice.iter().enumerate() {
        for a in 0..3 {
            if l[a] == 0 {
                let mut nrm = Vector3::zeros(); nrm[a] = 1.0;
                cs.set(i as u32, NodeConstraint::Plane { point_m: Vector3::zeros(), normal: nrm }).unwrap();
            }
        }
        if l.iter().filter(|&&v| v == 0).count() >= 2 { cs.fix(i as u32, mesh.rest_positions_m[i]).unwrap(); }
    }
    let faces: Vec<[u32;4]> = mesh.external_faces.iter().cloned().filter(|f| {
        let c: Vector3<f64> = f.iter().map(|&i| mesh.rest_positions_m[i as usize]).sum::<Vector3<f64>>() / 4.0;
        (0..3).all(|a| c[a] > 1e-9)
    }).collect();
    let loads = Loads { pressures: vec![SurfacePressure { faces, pressure_pa: p, follows_deformation: true }], ..Default::default() };
    let scene = Scene::new(mesh, cs, loads).unwrap();
    let t = std::time::Instant::now();
    let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
    let setup = t.elapsed().as_secs_f64();
    let (x, rep) = solver.solve(None).unwrap();
    let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m);
    let v1 = scene.mesh.enclosed_volume_m3(&x);
    let k = Material::LUNG.bulk_modulus_pa();
    println!("n={n} elems={} setup {setup:.3}s {:?}", scene.mesh.element_count(), rep);
    println!("dV/V = {:.5}, linear prediction -p/K = {:.5}", (v1-v0)/v0, -p/k);
}
