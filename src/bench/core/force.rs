//! Force-kernel throughput on one and on all threads, and the memory of the block it runs on.

use std::time::Instant;

use super::{
    ForceThroughput, MemoryUsage, ParallelSpeedup, BENCH_DAMPING_RATIO, BENCH_ELEMENT_EDGE_M,
    BENCH_PERTURBATION,
};
use crate::bench::TimeStats;
use crate::math::V3;
use crate::model::{HexMesh, Material, VoxelGrid};
use crate::simulation::ForceEvaluator;
use crate::{Error, Result};

fn block_mesh(n: usize) -> Result<HexMesh> {
    Ok(
        VoxelGrid::filled_box([n; 3], [BENCH_ELEMENT_EDGE_M; 3], V3::zeros())
            .to_mesh(Material::LUNG)?
            .mesh,
    )
}

/// xorshift64*: reproducible positions without a dependency.
fn pseudo_random(state: &mut u64) -> f64 {
    *state ^= *state >> 12;
    *state ^= *state << 25;
    *state ^= *state >> 27;
    (state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64 - 0.5
}

fn pool(threads: usize) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::External(format!("cannot start {threads} threads: {e}")))
}

type ForceBlock = (Vec<ForceThroughput>, Vec<ParallelSpeedup>, MemoryUsage);

pub(super) fn force_block(n: usize, threads: usize, reps: usize) -> Result<ForceBlock> {
    let start = Instant::now();
    let mut mesh = block_mesh(n)?;
    let mesh_build_s = start.elapsed().as_secs_f64();
    let plain = ForceEvaluator::new(&mesh);
    let undamped = mesh.classes.clone();
    mesh.classes = undamped
        .iter()
        .map(|c| c.clone().with_damping_ratio(BENCH_DAMPING_RATIO))
        .collect();
    let damped = ForceEvaluator::new(&mesh);
    mesh.classes = undamped;
    let mut seed = 0x9e37_79b9_7f4a_7c15u64 ^ n as u64;
    let amp = BENCH_PERTURBATION * BENCH_ELEMENT_EDGE_M;
    let mut rnd3 = |scale: f64| {
        V3::new(
            pseudo_random(&mut seed),
            pseudo_random(&mut seed),
            pseudo_random(&mut seed),
        ) * scale
    };
    let x: Vec<V3> = mesh
        .rest_positions_m
        .iter()
        .map(|p| p + rnd3(2.0 * amp))
        .collect();
    let v: Vec<V3> = x.iter().map(|_| rnd3(0.02)).collect();
    let mut out = vec![V3::zeros(); mesh.node_count()];
    let one = pool(1)?;
    let many = pool(threads)?;
    let mut results = Vec::new();
    let mut speedups = Vec::new();
    for with_velocities in [false, true] {
        let (eval, vel) = if with_velocities {
            (&damped, Some(&v[..]))
        } else {
            (&plain, None)
        };
        let mut run = |p: &rayon::ThreadPool| {
            p.install(|| {
                let t = Instant::now();
                eval.internal_forces(&mesh, &x, vel, &mut out);
                t.elapsed().as_secs_f64()
            })
        };
        for _ in 0..2 {
            run(&one);
            run(&many);
        }
        // Interleaved so that load from other processes hits both thread counts alike.
        let mut t1 = Vec::with_capacity(reps);
        let mut tn = Vec::with_capacity(reps);
        for _ in 0..reps {
            t1.push(run(&one));
            tn.push(run(&many));
        }
        let s1 = TimeStats::new(&t1);
        let sn = TimeStats::new(&tn);
        for (t, s) in [(1, s1), (threads, sn)] {
            let e = mesh.element_count() as f64;
            results.push(ForceThroughput {
                cells_per_edge: n,
                elements: mesh.element_count(),
                nodes: mesh.node_count(),
                with_velocities,
                threads: t,
                time: s,
                elements_per_s: e / s.median_s,
                elements_per_s_best: e / s.min_s,
                ns_per_element: s.median_s / e * 1e9,
            });
        }
        let speedup = s1.median_s / sn.median_s;
        speedups.push(ParallelSpeedup {
            cells_per_edge: n,
            with_velocities,
            threads,
            speedup,
            speedup_best: s1.min_s / sn.min_s,
            efficiency: speedup / threads as f64,
        });
    }
    let memory = memory_usage(n, &mesh, &damped, mesh_build_s);
    Ok((results, speedups, memory))
}

fn vec_bytes<T>(v: &Vec<T>) -> usize {
    v.capacity() * std::mem::size_of::<T>()
}

fn memory_usage(n: usize, mesh: &HexMesh, eval: &ForceEvaluator, mesh_build_s: f64) -> MemoryUsage {
    let e = mesh.element_count() as f64;
    let nodes = mesh.node_count() as f64;
    let colours: usize = mesh.colors.iter().map(vec_bytes).sum::<usize>() + vec_bytes(&mesh.colors);
    let element_bytes = vec_bytes(&mesh.elements) + vec_bytes(&mesh.element_class) + colours;
    let node_bytes = vec_bytes(&mesh.rest_positions_m) + vec_bytes(&mesh.node_mass_kg);
    let face_bytes = vec_bytes(&mesh.external_faces);
    let class_bytes = vec_bytes(&mesh.classes);
    let mesh_total = element_bytes + node_bytes + face_bytes + class_bytes;
    let state_per_node = 3.0 * std::mem::size_of::<V3>() as f64;
    let eval_bytes = eval.heap_bytes() + std::mem::size_of::<ForceEvaluator>();
    MemoryUsage {
        cells_per_edge: n,
        elements: mesh.element_count(),
        nodes: mesh.node_count(),
        mesh_bytes_per_element: element_bytes as f64 / e,
        mesh_bytes_per_node: node_bytes as f64 / nodes,
        surface_bytes_per_face: face_bytes as f64 / mesh.external_faces.len().max(1) as f64,
        mesh_total_bytes_per_element: mesh_total as f64 / e,
        state_bytes_per_node: state_per_node,
        force_evaluator_bytes: eval_bytes,
        total_bytes_per_element: (mesh_total as f64 + state_per_node * nodes + eval_bytes as f64)
            / e,
        mesh_build_s,
    }
}
