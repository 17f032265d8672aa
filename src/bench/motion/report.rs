//! The motion benchmark's Markdown report: per element size the build, the cycle, serving and
//! accuracy, with the targets and verdicts beside the measurements.

use std::fmt::Write as _;

use super::{
    ElementSizeBench, FieldServing, MotionBenchReport, PopiFieldServing, FIELDS_PER_S_TARGET,
    INTERPOLATION_TARGET_MM, VOLUME_ERROR_TARGET_FRACTION,
};
use crate::bench::Outcome;
use crate::markdown::{mib, or_dash, Table};

fn verdict(ok: bool) -> &'static str {
    if ok {
        "met"
    } else {
        "missed"
    }
}

impl MotionBenchReport {
    /// The report as Markdown: per element size the build, the cycle, serving and accuracy,
    /// with the targets and verdicts beside the measurements.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# Motion: 10-phase tidal cycle on the CIP chest CT\n");
        let _ = writeln!(
            s,
            "{} cores{}; trace: Lujan, two 4 s breaths, {} mL tidal, CT at end-exhale; 10 \
             phases of the first cycle; volume driver, keys interpolated within {} mm. \
             Medians of repeated runs [min – max] ×runs. Memory: VmHWM after resetting it \
             with clear_refs.\n",
            self.cores,
            self.load_average_at_start
                .map_or(String::new(), |l| format!(
                    " (load average {:.2}, {:.2}, {:.2} at the start)",
                    l[0], l[1], l[2]
                )),
            self.trace_tidal_volume_ml,
            INTERPOLATION_TARGET_MM
        );
        for size in &self.sizes {
            size.write_markdown(&mut s);
        }
        match &self.popi {
            Outcome::Measured(p) => p.write_markdown(&mut s),
            Outcome::Failed(e) => {
                let _ = writeln!(s, "## The POPI CT\n\n**Serving FAILED**: {e}\n");
            }
            Outcome::Skipped(e) => {
                let _ = writeln!(s, "## The POPI CT\n\nServing not measured: {e}\n");
            }
        }
        s
    }
}

impl ElementSizeBench {
    /// This element size's section of the report.
    pub(super) fn write_markdown(&self, s: &mut String) {
        let h = self.element_size_mm;
        let _ = writeln!(s, "## {h} mm elements\n");
        self.write_build(s);
        self.write_cycle(s);
        self.write_wall_surface(s);
        self.write_serving(s);
        self.write_accuracy(s);
    }

    /// The model build: sizes and where its time went.
    fn write_build(&self, s: &mut String) {
        match &self.build {
            Outcome::Measured(b) => {
                let _ = writeln!(
                    s,
                    "Model: {} elements, {} nodes, {} lung voxels sampled on the {}×{}×{} CT. \
                     Build {:.3} s (CT {:.3}, segmentation {:.3}, model {:.3}, scene {:.3}, \
                     field sampler {:.3}); peak {}.\n",
                    b.elements,
                    b.nodes,
                    b.sampled_voxels,
                    b.ct_dims[0],
                    b.ct_dims[1],
                    b.ct_dims[2],
                    b.total_s,
                    b.load_ct_s,
                    b.segmentation_s,
                    b.model_s,
                    b.scene_s,
                    b.field_sampler_s,
                    mib(b.peak_rss_bytes)
                );
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "Model not built: {e}\n");
            }
        }
    }

    /// The tidal cycle against its target.
    fn write_cycle(&self, s: &mut String) {
        match &self.cycle {
            Outcome::Measured(c) => {
                let target = self.cycle_target_s.map_or("none stated".to_string(), |t| {
                    format!("≤ {t} s: {}", verdict(c.time.median_s <= t))
                });
                let mut table = Table::new([
                    "Cycle s [min – max] ×runs",
                    "Target",
                    "Per phase s",
                    "CPU s per cycle",
                    "Solver set-up s",
                    "Keys",
                    "Key solves",
                    "Key solve s",
                    "Key check error mm",
                    "Max volume error mL (% tidal)",
                    "Peak RSS (before)",
                ]);
                table.row([
                    format!(
                        "{:.3} [{:.3} – {:.3}] ×{}",
                        c.time.median_s, c.time.min_s, c.time.max_s, c.time.runs
                    ),
                    target,
                    format!("{:.4}", c.per_phase_s),
                    or_dash(c.cpu_per_cycle_s, |v| format!("{v:.2}")),
                    format!("{:.3}", c.solver_setup_s),
                    c.keys.to_string(),
                    c.key_solves.to_string(),
                    format!("{:.3}", c.key_solve_time_s),
                    format!("{:.4}", c.key_measured_error_mm),
                    format!(
                        "{:.3} ({:.3} %)",
                        c.max_volume_error_ml,
                        100.0 * c.max_volume_error_ml / c.tidal_volume_ml.max(f64::MIN_POSITIVE)
                    ),
                    format!("{} ({})", mib(c.peak_rss_bytes), mib(c.rss_before_bytes)),
                ]);
                table.write_to(s);
                let frames: Vec<String> = c
                    .frame_wall_s
                    .iter()
                    .map(|t| format!("{:.1}", t * 1e3))
                    .collect();
                let _ = writeln!(
                    s,
                    "\nFrame wall times after the keys (ms, last cycle): {}. Rest volume {:.0} mL, \
                     tidal {:.1} mL.{}\n",
                    frames.join(", "),
                    c.rest_volume_ml,
                    c.tidal_volume_ml,
                    if c.peak_reset {
                        ""
                    } else {
                        " The peak could not be reset: it includes the build."
                    }
                );
            }
            Outcome::Failed(e) => {
                let _ = writeln!(s, "**Cycle FAILED**: {e}\n");
            }
            Outcome::Skipped(e) => {
                let _ = writeln!(s, "Cycle not run: {e}\n");
            }
        }
    }

    /// The cycle sliding on the curved wall, against tangent planes.
    fn write_wall_surface(&self, s: &mut String) {
        match &self.wall_surface {
            Outcome::Measured(w) => {
                let c = &w.cycle;
                let _ = writeln!(
                    s,
                    "Sliding on the curved wall (`sliding = \"wall_surface\"`, {} ridge nodes on \
                     tangent planes): cycle {:.3} s [{:.3} – {:.3}] ×{}, {} keys, key solves \
                     {:.3} s; **{:.2}× the tangent planes' cycle** (target ≤ {}×: {}).\n",
                    w.nodes_on_planes,
                    c.time.median_s,
                    c.time.min_s,
                    c.time.max_s,
                    c.time.runs,
                    c.keys,
                    c.key_solve_time_s,
                    w.ratio_to_tangent_planes,
                    super::WALL_SURFACE_COST_TARGET,
                    verdict(w.ratio_to_tangent_planes <= super::WALL_SURFACE_COST_TARGET)
                );
            }
            Outcome::Failed(e) => {
                let _ = writeln!(s, "**Curved-wall cycle FAILED**: {e}\n");
            }
            Outcome::Skipped(e) => {
                let _ = writeln!(s, "Curved-wall cycle not run: {e}\n");
            }
        }
    }

    /// Fields served per second from the keys.
    fn write_serving(&self, s: &mut String) {
        write_serving(s, &self.serving, Some(FIELDS_PER_S_TARGET));
    }

    /// Interpolated frames against direct solves.
    fn write_accuracy(&self, s: &mut String) {
        match &self.accuracy {
            Outcome::Measured(a) => {
                let vol_target = VOLUME_ERROR_TARGET_FRACTION * a.tidal_volume_ml;
                let _ = writeln!(
                    s,
                    "Interpolated against direct solves: largest node difference {:.4} mm, \
                     largest voxel difference {:.4} mm (target ≤ {INTERPOLATION_TARGET_MM} mm: \
                     {}); at the volumes the direct solves reached, {:.4} mm. Volume error \
                     interpolated {:.3} mL, direct {:.3} mL (target ≤ {:.2} mL \
                     = 0.5 % of tidal: {}). Cycle {:.3} s interpolated, {:.3} s solving every \
                     frame.\n",
                    a.max_node_difference_mm,
                    a.max_field_difference_mm,
                    verdict(
                        a.max_node_difference_mm.max(a.max_field_difference_mm)
                            <= INTERPOLATION_TARGET_MM
                    ),
                    a.max_same_volume_node_difference_mm,
                    a.max_interpolated_volume_error_ml,
                    a.max_direct_volume_error_ml,
                    vol_target,
                    verdict(
                        a.max_interpolated_volume_error_ml
                            .max(a.max_direct_volume_error_ml)
                            <= vol_target
                    ),
                    a.interpolated_cycle_s,
                    a.direct_cycle_s
                );
                let mut table = Table::new([
                    "Frame",
                    "t s",
                    "Target mL",
                    "Interp. mL",
                    "Direct mL",
                    "Node diff mm",
                    "Voxel diff mm",
                    "Node diff at direct volume mm",
                    "Direct solves / Newton / GMRES",
                    "Direct s",
                ]);
                for f in &a.frames {
                    table.row([
                        f.index.to_string(),
                        format!("{:.2}", f.time_s),
                        format!("{:.1}", f.target_volume_ml),
                        format!("{:.1}", f.interpolated_volume_ml),
                        format!("{:.1}", f.direct_volume_ml),
                        format!("{:.4}", f.node_difference_mm),
                        format!("{:.4}", f.field_difference_mm),
                        format!("{:.4}", f.same_volume_node_difference_mm),
                        format!(
                            "{} / {} / {}",
                            f.direct_solves, f.direct_newton_iterations, f.direct_linear_iterations
                        ),
                        format!("{:.3}", f.direct_wall_s),
                    ]);
                }
                table.write_to(s);
                let _ = writeln!(s);
            }
            Outcome::Failed(e) => {
                let _ = writeln!(s, "**Accuracy check FAILED**: {e}\n");
            }
            Outcome::Skipped(e) => {
                let _ = writeln!(s, "Accuracy not measured: {e}\n");
            }
        }
    }
}

/// Fields served per second from the keys, with the verdict against `target` if one is set.
fn write_serving(s: &mut String, serving: &Outcome<FieldServing>, target: Option<f64>) {
    match serving {
        Outcome::Measured(v) => write_serving_table(s, v, target),
        Outcome::Failed(e) => {
            let _ = writeln!(s, "**Serving FAILED**: {e}\n");
        }
        Outcome::Skipped(e) => {
            let _ = writeln!(s, "Serving not measured: {e}\n");
        }
    }
}

/// The serving table of a measured pass.
fn write_serving_table(s: &mut String, v: &FieldServing, target: Option<f64>) {
    let mut table = Table::new([
        "Fields served per pass".to_string(),
        "Pass s [min – max] ×runs".into(),
        "Fields/s".into(),
        target.map_or("Target".into(), |t| format!("Target ≥ {t}")),
        "Node states/s".into(),
        "Keys (build s)".into(),
        "Newton / GMRES of final key level".into(),
    ]);
    let t = &v.fields_time;
    table.row([
        format!("{} × {} voxels", v.fields, v.voxels_per_field),
        format!(
            "{:.4} [{:.4} – {:.4}] ×{}",
            t.median_s, t.min_s, t.max_s, t.runs
        ),
        format!("{:.0}", v.fields_per_s),
        target.map_or("none stated".into(), |t| {
            verdict(v.fields_per_s >= t).to_string()
        }),
        format!("{:.0}", v.node_states_per_s),
        format!("{} ({:.3})", v.keys, v.key_build_s),
        format!(
            "{} / {}",
            v.final_level_newton_iterations, v.final_level_linear_iterations
        ),
    ]);
    table.write_to(s);
    s.push('\n');
}

impl PopiFieldServing {
    /// The POPI section of the report.
    fn write_markdown(&self, s: &mut String) {
        let b = &self.build;
        let [nx, ny, nz] = b.ct_dims;
        let _ = writeln!(
            s,
            "## Serving at clinical scale: the POPI CT, {} mm elements\n\n\
             CT {nx} × {ny} × {nz} (read in {:.2} s), {} elements; the fields are the lung box \
             as `lungmotion run` writes them by default, sampled in memory (positions from the \
             keys, then every lung voxel), without NIfTI or gzip (`lungmotion bench --suite \
             service` measures those through the service).\n",
            self.element_size_mm, b.load_ct_s, b.elements
        );
        write_serving_table(s, &self.serving, None);
    }
}
