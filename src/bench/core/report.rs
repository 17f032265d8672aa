//! The core benchmark's Markdown report.

use std::fmt::Write as _;

use super::{BenchReport, BENCH_DAMPING_RATIO, BENCH_PERTURBATION};
use crate::bench::Outcome;
use crate::markdown::{one_line, or_dash, Table};

/// `yes` or `no`.
fn yes_no(v: bool) -> &'static str {
    if v {
        "yes"
    } else {
        "no"
    }
}

impl BenchReport {
    /// The report as a markdown document (tables of every measurement).
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        self.write_header(&mut s);
        self.write_targets(&mut s);
        self.write_force(&mut s);
        self.write_memory(&mut s);
        self.write_quasistatic(&mut s);
        self.write_solver_comparison(&mut s);
        self.write_calculix(&mut s);
        s
    }

    /// Title, machine and material.
    fn write_header(&self, s: &mut String) {
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
    }

    /// The targets and whether they were met.
    fn write_targets(&self, s: &mut String) {
        let _ = writeln!(s, "## Targets\n");
        let mut table = Table::new(["Target", "Measured", "Met"]);
        for t in &self.targets {
            let met = match t.met {
                Some(true) => "yes",
                Some(false) => "**no**",
                None => "not measured",
            };
            table.row([t.target.as_str(), &t.measured, met]);
        }
        table.write_to(s);
    }

    /// Force throughput per block, damping and thread count, then the parallel speed-ups.
    fn write_force(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Force evaluation\n");
        let _ = writeln!(
            s,
            "Nodes displaced randomly by up to ±{:.0} % of the edge; with velocities: dampers \
             at {} of critical. Wall time per evaluation of all elements.\n",
            BENCH_PERTURBATION * 100.0,
            BENCH_DAMPING_RATIO
        );
        let mut throughput = Table::new([
            "Block",
            "Elements",
            "Velocities",
            "Threads",
            "Median ms [min – max]",
            "M elements/s (best)",
            "ns/element",
        ]);
        for f in &self.force {
            throughput.row([
                format!("{}³", f.cells_per_edge),
                f.elements.to_string(),
                yes_no(f.with_velocities).into(),
                f.threads.to_string(),
                format!(
                    "{:.2} [{:.2} – {:.2}]",
                    f.time.median_s * 1e3,
                    f.time.min_s * 1e3,
                    f.time.max_s * 1e3
                ),
                format!(
                    "{:.2} ({:.2})",
                    f.elements_per_s / 1e6,
                    f.elements_per_s_best / 1e6
                ),
                format!("{:.1}", f.ns_per_element),
            ]);
        }
        throughput.write_to(s);
        s.push('\n');
        let mut speedups = Table::new([
            "Block",
            "Velocities",
            "Threads",
            "Parallel speed-up (medians)",
            "Efficiency",
            "Speed-up (best runs)",
        ]);
        for p in &self.speedups {
            speedups.row([
                format!("{}³", p.cells_per_edge),
                yes_no(p.with_velocities).into(),
                p.threads.to_string(),
                format!("{:.2}×", p.speedup),
                format!("{:.0} %", p.efficiency * 100.0),
                format!("{:.2}×", p.speedup_best),
            ]);
        }
        speedups.write_to(s);
    }

    /// Bytes per element and per node of the force-benchmark blocks, and the process peak.
    fn write_memory(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Memory\n");
        let _ = writeln!(
            s,
            "Counted from vector capacities. Mesh per element: corners, class, colour lists; per \
             node: rest position, mass. State: positions, velocities, forces.\n"
        );
        let mut table = Table::new([
            "Block",
            "Elements",
            "Nodes",
            "Mesh B/element",
            "Mesh B/node",
            "Mesh total B/element",
            "State B/node",
            "Evaluator B",
            "Total B/element",
            "Mesh build s",
        ]);
        for mu in &self.memory {
            table.row([
                format!("{}³", mu.cells_per_edge),
                mu.elements.to_string(),
                mu.nodes.to_string(),
                format!("{:.1}", mu.mesh_bytes_per_element),
                format!("{:.1}", mu.mesh_bytes_per_node),
                format!("{:.1}", mu.mesh_total_bytes_per_element),
                format!("{:.0}", mu.state_bytes_per_node),
                mu.force_evaluator_bytes.to_string(),
                format!("{:.1}", mu.total_bytes_per_element),
                format!("{:.3}", mu.mesh_build_s),
            ]);
        }
        table.write_to(s);
        if let Some(p) = self.peak_rss_bytes {
            let _ = writeln!(
                s,
                "\nProcess peak resident memory (VmHWM) at the end: {:.1} MB.",
                p as f64 / 1e6
            );
        }
    }

    /// The quasi-static block solves and the fitted scaling.
    fn write_quasistatic(&self, s: &mut String) {
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
        let mut table = Table::new([
            "Block",
            "Elements",
            "Total s [min – max]",
            "Set-up s",
            "Solve s",
            "Newton",
            "Krylov",
            "Residual",
            "MG levels",
            "ΔV/V (linear −p/K)",
            "Peak extra RSS B/element",
            "Scene build s",
        ]);
        for (o, &n) in self
            .quasistatic
            .iter()
            .zip(&self.options.quasistatic_block_cells)
        {
            match o {
                Outcome::Measured(q) => {
                    table.row([
                        format!("{}³", q.cells_per_edge),
                        q.elements.to_string(),
                        format!(
                            "{:.3} [{:.3} – {:.3}]",
                            q.total.median_s, q.total.min_s, q.total.max_s
                        ),
                        format!("{:.3}", q.setup.median_s),
                        format!("{:.3}", q.solve.median_s),
                        q.newton_iterations.to_string(),
                        q.linear_iterations.to_string(),
                        format!("{:.1e}", q.residual),
                        q.multigrid_levels.to_string(),
                        format!("{:.4} ({:.4})", q.volume_change, q.linear_volume_change),
                        or_dash(q.peak_extra_rss_bytes_per_element, |b| format!("{b:.0}")),
                        format!("{:.3}", q.scene_build_s),
                    ]);
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    table.partial_row([format!("{n}³"), "–".into(), one_line(e)]);
                }
            }
        }
        table.write_to(s);
        if let Some(f) = &self.quasistatic_scaling {
            let _ = writeln!(
                s,
                "\nTime ∝ elements^{:.2} (least-squares fit over blocks {:?}).",
                f.exponent, f.cells_per_edge
            );
        }
    }

    /// The quasi-static methods side by side (skipped when none was compared).
    fn write_solver_comparison(&self, s: &mut String) {
        if self.solver_comparison.is_empty() {
            return;
        }
        let _ = writeln!(s, "\n## Choosing the quasi-static method\n");
        let _ = writeln!(
            s,
            "Same block and load, each method to relative residual 1e-6 (one run each, \
             set-up included). The solver's default is multigrid on lattice meshes; on \
             tiny blocks its set-up can cost more than it saves.\n"
        );
        let mut table = Table::new(["Method", "Elements", "Wall s", "Iterations", "Residual"]);
        for c in &self.solver_comparison {
            match c {
                Outcome::Measured(c) => {
                    table.row([
                        c.method.clone(),
                        c.elements.to_string(),
                        format!("{:.3}", c.wall_time_s),
                        c.iterations.clone(),
                        format!("{:.1e}", c.residual),
                    ]);
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    table.row(["–", "–", "–", "–", e]);
                }
            }
        }
        table.write_to(s);
    }

    /// CalculiX on the same blocks, or why not.
    fn write_calculix(&self, s: &mut String) {
        let _ = writeln!(s, "\n## CalculiX side by side\n");
        let _ = writeln!(
            s,
            "Same scene written as a C3D8 deck (full integration); ours is set-up + solve \
             (median), measured just before CalculiX. Displacement differences are relative to \
             CalculiX's.\n"
        );
        if self.calculix.is_empty() {
            let _ = writeln!(s, "Not run.");
            return;
        }
        let mut table = Table::new([
            "Block",
            "Elements",
            "CalculiX analysis",
            "CalculiX s",
            "Ours s",
            "Ratio",
            "Ratio incl. our scene build",
            "max Δu / max u",
            "RMS Δu / RMS u",
        ]);
        for o in &self.calculix {
            match o {
                Outcome::Measured(c) => {
                    table.row([
                        format!("{}³", c.cells_per_edge),
                        c.elements.to_string(),
                        format!("{} ({} threads)", c.analysis, c.calculix_threads),
                        format!("{:.2}", c.calculix_wall_s),
                        format!("{:.3}", c.ours_wall_s),
                        format!("{:.1}×", c.speedup),
                        format!("{:.1}×", c.speedup_with_scene_build),
                        format!("{:.2e}", c.max_displacement_difference_rel),
                        format!("{:.2e}", c.rms_displacement_difference_rel),
                    ]);
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    table.partial_row([String::new(), String::new(), one_line(e)]);
                }
            }
        }
        table.write_to(s);
    }
}
