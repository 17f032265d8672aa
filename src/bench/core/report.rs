//! The core benchmark's Markdown report.

use super::{BenchReport, BENCH_DAMPING_RATIO, BENCH_PERTURBATION};
use crate::bench::Outcome;

impl BenchReport {
    /// The report as a markdown document (tables of every measurement).
    pub fn to_markdown(&self) -> String {
        use std::fmt::Write as _;
        let mut s = String::new();
        let m = &self.machine;
        let _ = writeln!(s, "# lungmotion benchmark\n");
        let _ = writeln!(
            s,
            "{} · CPU: {} · {} cores · {} threads in parallel runs · SIMD: {} · lungmotion {}\n",
            m.date_utc, m.cpu_model, m.cores, m.threads, m.simd, m.lungmotion_version
        );
        let _ = writeln!(
            s,
            "Blocks of {:.0} mm cubes, lung material E = {} Pa, ν = {}, ρ = {} kg/m³. \
             Times are medians with [min – max] over the runs; ratios come from the same run.\n",
            self.element_edge_m * 1e3,
            self.material.youngs_modulus_pa,
            self.material.poisson_ratio,
            self.material.density_kg_per_m3
        );
        let _ = writeln!(s, "## Targets\n");
        let _ = writeln!(s, "| Target | Measured | Met |\n|---|---|---|");
        for t in &self.targets {
            let met = match t.met {
                Some(true) => "yes",
                Some(false) => "**no**",
                None => "not measured",
            };
            let _ = writeln!(s, "| {} | {} | {} |", t.target, t.measured, met);
        }
        let _ = writeln!(s, "\n## Force evaluation\n");
        let _ = writeln!(
            s,
            "Nodes displaced randomly by up to ±{:.0} % of the edge; with velocities: dampers \
             at {} of critical. Wall time per evaluation of all elements.\n",
            BENCH_PERTURBATION * 100.0,
            BENCH_DAMPING_RATIO
        );
        let _ = writeln!(
            s,
            "| Block | Elements | Velocities | Threads | Median ms [min – max] | M elements/s (best) | ns/element |\n|---|---|---|---|---|---|---|"
        );
        for f in &self.force {
            let _ = writeln!(
                s,
                "| {n}³ | {} | {} | {} | {:.2} [{:.2} – {:.2}] | {:.2} ({:.2}) | {:.1} |",
                f.elements,
                if f.with_velocities { "yes" } else { "no" },
                f.threads,
                f.time.median_s * 1e3,
                f.time.min_s * 1e3,
                f.time.max_s * 1e3,
                f.elements_per_s / 1e6,
                f.elements_per_s_best / 1e6,
                f.ns_per_element,
                n = f.cells_per_edge
            );
        }
        let _ = writeln!(
            s,
            "\n| Block | Velocities | Threads | Parallel speed-up (medians) | Efficiency | Speed-up (best runs) |\n|---|---|---|---|---|---|"
        );
        for p in &self.speedups {
            let _ = writeln!(
                s,
                "| {}³ | {} | {} | {:.2}× | {:.0} % | {:.2}× |",
                p.cells_per_edge,
                if p.with_velocities { "yes" } else { "no" },
                p.threads,
                p.speedup,
                p.efficiency * 100.0,
                p.speedup_best
            );
        }
        let _ = writeln!(s, "\n## Memory\n");
        let _ = writeln!(
            s,
            "Counted from vector capacities. Mesh per element: corners, class, colour lists; per \
             node: rest position, mass. State: positions, velocities, forces.\n"
        );
        let _ = writeln!(
            s,
            "| Block | Elements | Nodes | Mesh B/element | Mesh B/node | Mesh total B/element | State B/node | Evaluator B | Total B/element | Mesh build s |\n|---|---|---|---|---|---|---|---|---|---|"
        );
        for mu in &self.memory {
            let _ = writeln!(
                s,
                "| {}³ | {} | {} | {:.1} | {:.1} | {:.1} | {:.0} | {} | {:.1} | {:.3} |",
                mu.cells_per_edge,
                mu.elements,
                mu.nodes,
                mu.mesh_bytes_per_element,
                mu.mesh_bytes_per_node,
                mu.mesh_total_bytes_per_element,
                mu.state_bytes_per_node,
                mu.force_evaluator_bytes,
                mu.total_bytes_per_element,
                mu.mesh_build_s
            );
        }
        if let Some(p) = self.peak_rss_bytes {
            let _ = writeln!(
                s,
                "\nProcess peak resident memory (VmHWM) at the end: {:.1} MB.",
                p as f64 / 1e6
            );
        }
        let _ = writeln!(s, "\n## Quasi-static block\n");
        let _ = writeln!(
            s,
            "One octant of a cube block: symmetry planes x = 0, y = 0, z = 0 (nodes slide in \
             the plane; on two planes, along their line; the corner is fixed), follower \
             pressure {} Pa on the three outer faces. `QuasiStaticSolver` with default settings \
             (relative force residual 1e-6). Total = solver set-up + solve; the scene \
             construction is listed apart.\n",
            self.options.pressure_pa
        );
        let _ = writeln!(
            s,
            "| Block | Elements | Total s [min – max] | Set-up s | Solve s | Newton | Krylov | Residual | MG levels | ΔV/V (linear −p/K) | Peak extra RSS B/element | Scene build s |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        for (o, &n) in self
            .quasistatic
            .iter()
            .zip(&self.options.quasistatic_block_cells)
        {
            match o {
                Outcome::Measured(q) => {
                    let _ = writeln!(
                        s,
                        "| {}³ | {} | {:.3} [{:.3} – {:.3}] | {:.3} | {:.3} | {} | {} | {:.1e} | {} | {:.4} ({:.4}) | {} | {:.3} |",
                        q.cells_per_edge,
                        q.elements,
                        q.total.median_s,
                        q.total.min_s,
                        q.total.max_s,
                        q.setup.median_s,
                        q.solve.median_s,
                        q.newton_iterations,
                        q.linear_iterations,
                        q.residual,
                        q.multigrid_levels,
                        q.volume_change,
                        q.linear_volume_change,
                        q.peak_extra_rss_bytes_per_element
                            .map_or("–".into(), |b| format!("{b:.0}")),
                        q.scene_build_s
                    );
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    let _ = writeln!(s, "| {n}³ | – | {} | | | | | | | | | |", one_line(e));
                }
            }
        }
        if let Some(f) = &self.quasistatic_scaling {
            let _ = writeln!(
                s,
                "\nTime ∝ elements^{:.2} (least-squares fit over blocks {:?}).",
                f.exponent, f.cells_per_edge
            );
        }
        if !self.solver_comparison.is_empty() {
            let _ = writeln!(s, "\n## Choosing the quasi-static method\n");
            let _ = writeln!(
                s,
                "Same block and load, each method to relative residual 1e-6 (one run each, \
                 set-up included). The solver's default is multigrid on lattice meshes; on \
                 tiny blocks its set-up can cost more than it saves.\n"
            );
            let _ = writeln!(s, "| Method | Elements | Wall s | Iterations | Residual |");
            let _ = writeln!(s, "|---|---|---|---|---|");
            for c in &self.solver_comparison {
                match c {
                    Outcome::Measured(c) => {
                        let _ = writeln!(
                            s,
                            "| {} | {} | {:.3} | {} | {:.1e} |",
                            c.method, c.elements, c.wall_time_s, c.iterations, c.residual
                        );
                    }
                    Outcome::Failed(e) | Outcome::Skipped(e) => {
                        let _ = writeln!(s, "| – | – | – | – | {e} |");
                    }
                }
            }
        }
        let _ = writeln!(s, "\n## CalculiX side by side\n");
        let _ = writeln!(
            s,
            "Same scene written as a C3D8 deck (full integration); ours is set-up + solve \
             (median), measured just before CalculiX. Displacement differences are relative to \
             CalculiX's.\n"
        );
        if self.calculix.is_empty() {
            let _ = writeln!(s, "Not run.");
        } else {
            let _ = writeln!(
                s,
                "| Block | Elements | CalculiX analysis | CalculiX s | Ours s | Ratio | Ratio incl. our scene build | max Δu / max u | RMS Δu / RMS u |\n|---|---|---|---|---|---|---|---|---|"
            );
            for o in &self.calculix {
                match o {
                    Outcome::Measured(c) => {
                        let _ = writeln!(
                            s,
                            "| {}³ | {} | {} ({} threads) | {:.2} | {:.3} | {:.1}× | {:.1}× | {:.2e} | {:.2e} |",
                            c.cells_per_edge,
                            c.elements,
                            c.analysis,
                            c.calculix_threads,
                            c.calculix_wall_s,
                            c.ours_wall_s,
                            c.speedup,
                            c.speedup_with_scene_build,
                            c.max_displacement_difference_rel,
                            c.rms_displacement_difference_rel
                        );
                    }
                    Outcome::Failed(e) | Outcome::Skipped(e) => {
                        let _ = writeln!(s, "| | | {} | | | | | | |", one_line(e));
                    }
                }
            }
        }
        s
    }
}

/// First line of an error message, table-safe.
fn one_line(e: &str) -> String {
    e.lines().next().unwrap_or("").replace('|', "/")
}
