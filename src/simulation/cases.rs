//! Reusable mechanical test cases built on regular grids.

use nalgebra::Vector3;

use crate::model::{ConstraintSet, Loads, Material, NodeConstraint, SurfacePressure, VoxelGrid};
use crate::simulation::Scene;
use crate::Result;

/// One octant of a block of `cells` cubes of `edge_m`, with symmetry planes on its three
/// faces through the origin (each node there slides in that plane; nodes on two or three
/// symmetry planes are held on their line or fixed) and a uniform follower pressure on the
/// three outer faces (negative pressure inflates, as a lung does).
pub fn symmetric_block_under_pressure(
    cells: [usize; 3],
    edge_m: f64,
    material: Material,
    pressure_pa: f64,
) -> Result<Scene> {
    let grid = VoxelGrid::filled_box(cells, [edge_m; 3], Vector3::zeros());
    let gm = grid.to_mesh(material)?;
    let mesh = gm.mesh;
    let mut cs = ConstraintSet::new(mesh.node_count());
    for (i, l) in gm.node_lattice.iter().enumerate() {
        let on: Vec<usize> = (0..3).filter(|&a| l[a] == 0).collect();
        let node = i as u32;
        let x = mesh.rest_positions_m[i];
        match on.len() {
            0 => {}
            1 => cs.set(
                node,
                NodeConstraint::Plane {
                    point_m: x,
                    normal: Vector3::ith(on[0], 1.0),
                },
            )?,
            2 => cs.set(
                node,
                NodeConstraint::Line {
                    point_m: x,
                    direction: Vector3::ith(3 - on[0] - on[1], 1.0),
                },
            )?,
            _ => cs.fix(node, x)?,
        }
    }
    let faces: Vec<[u32; 4]> = mesh
        .external_faces
        .iter()
        .copied()
        .filter(|f| {
            f.iter().any(|&n| {
                let l = gm.node_lattice[n as usize];
                (0..3).all(|a| l[a] > 0)
            }) && (0..3).any(|a| {
                f.iter()
                    .all(|&n| gm.node_lattice[n as usize][a] == cells[a] as u32)
            })
        })
        .collect();
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces,
            pressure_pa,
            follows_deformation: true,
        }],
        ..Loads::default()
    };
    Scene::new(mesh, cs, loads)
}
