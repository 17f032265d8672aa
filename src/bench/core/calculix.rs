//! CalculiX and ours on the same block and load, timed and compared node by node.

use super::quasistatic::{block_scene, time_solves};
use super::CalculixComparison;
use crate::bench::Outcome;
use crate::validation::calculix::{self, CalculixOptions};
use crate::Result;

pub(super) fn calculix_block(
    n: usize,
    pressure_pa: f64,
    nlgeom: bool,
    threads: usize,
    runs: usize,
) -> Outcome<CalculixComparison> {
    let analysis = if nlgeom { "nlgeom" } else { "linear" };
    if let Err(e) = calculix::require_ccx() {
        return Outcome::Skipped(format!("calculix: not available ({e})"));
    }
    let run = || -> Result<CalculixComparison> {
        let (scene, scene_build_s) = block_scene(n, pressure_pa)?;
        let (x, _, [_, _, total]) = time_solves(&scene, runs)?;
        let ours = scene.displacements(&x);
        let options = CalculixOptions {
            threads,
            ..if nlgeom {
                CalculixOptions::default()
            } else {
                CalculixOptions::linear()
            }
        };
        let ccx = calculix::solve(&scene, &options)?;
        let theirs = &ccx.displacements_m;
        let max_ccx = theirs.iter().map(|u| u.norm()).fold(0.0, f64::max);
        let max_diff = ours
            .iter()
            .zip(theirs)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        let rms = |it: &mut dyn Iterator<Item = f64>| {
            let (s, c) = it.fold((0.0, 0usize), |(s, c), v| (s + v * v, c + 1));
            (s / c.max(1) as f64).sqrt()
        };
        let rms_diff = rms(&mut ours.iter().zip(theirs).map(|(a, b)| (a - b).norm()));
        let rms_ccx = rms(&mut theirs.iter().map(|u| u.norm()));
        Ok(CalculixComparison {
            cells_per_edge: n,
            elements: scene.mesh.element_count(),
            analysis: analysis.into(),
            calculix_wall_s: ccx.wall_time_s,
            calculix_threads: threads,
            ours_wall_s: total.median_s,
            ours_scene_build_s: scene_build_s,
            speedup: ccx.wall_time_s / total.median_s,
            speedup_with_scene_build: ccx.wall_time_s / (total.median_s + scene_build_s),
            max_displacement_difference_rel: max_diff / max_ccx,
            rms_displacement_difference_rel: rms_diff / rms_ccx,
            calculix_max_displacement_m: max_ccx,
        })
    };
    Outcome::from_result(run())
}
