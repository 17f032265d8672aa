//! The scale benchmark's Markdown table (one row per case and element size) and its
//! time–error plot.

use std::fmt::Write as _;
use std::path::Path;

use super::{ScaleBenchReport, SizePoint};
use crate::bench::Outcome;
use crate::markdown::{mib, one_line, Table};
use crate::outputs::plots::{render_trade_off, TradeOffPoint, TradeOffSeries};
use crate::Result;

/// File name of the time–error plot.
pub const TRADE_OFF_PNG: &str = "bench-scale.png";

impl ScaleBenchReport {
    /// The report as Markdown: one table per case, the exponent, CalculiX.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# Run time against error over element sizes\n");
        let _ = writeln!(
            s,
            "{} cores{}; the default 10-phase cycle of a {} mL Lujan breath (CT at end-exhale) as \
             `lungmotion run` solves it; budget {:.0} s per size. Error: the end-inhale field \
             against the finest size that completed, |Δu| over the CT's lung voxels. Memory: \
             peak of the build and the cycle (VmHWM reset before each size).\n",
            self.cores,
            self.load_average_at_start
                .map_or(String::new(), |l| format!(
                    " (load average {:.2}, {:.2}, {:.2} at the start)",
                    l[0], l[1], l[2]
                )),
            self.tidal_volume_ml,
            self.options.budget_s
        );
        for case in &self.cases {
            let [nx, ny, nz] = case.ct_dims;
            let _ = writeln!(s, "## {} ({nx} × {ny} × {nz})\n", case.name);
            let mut t = Table::new([
                "element",
                "elements",
                "build",
                "cycle",
                "µs/element",
                "peak memory",
                "keys / solves",
                "Newton / GMRES",
                "V-cycle alone",
                "largest displacement",
                "error mean",
                "p95",
                "max",
            ]);
            for p in &case.sizes {
                row(&mut t, p);
            }
            t.write_to(&mut s);
            let failures: Vec<String> = case
                .sizes
                .iter()
                .filter_map(|p| match &p.cycle {
                    Outcome::Failed(e) => {
                        Some(format!("* {} mm: {}", p.element_size_mm, one_line(e)))
                    }
                    _ => None,
                })
                .collect();
            if !failures.is_empty() {
                let _ = writeln!(s, "\n{}", failures.join("\n"));
            }
            match &case.scaling {
                Some(f) => {
                    let _ = writeln!(
                        s,
                        "\nCycle time ∝ elements^{:.2} over {} sizes ({} to {} mm).\n",
                        f.exponent, f.sizes, f.range_mm[0], f.range_mm[1]
                    );
                }
                None => {
                    let _ = writeln!(s, "\nFewer than two sizes completed: no exponent.\n");
                }
            }
        }
        let _ = writeln!(
            s,
            "## CalculiX (C3D8, NLGEOM, the run's default material's law) on the CIP end-inhale frame\n"
        );
        match &self.calculix {
            Outcome::Measured(c) => {
                let _ = writeln!(
                    s,
                    "At {} mm, ours against CalculiX over nodes: mean {:.3} mm, p95 {:.3} mm, max \
                     {:.3} mm; our solve {:.2} s, CalculiX {:.1} s.\n",
                    c.element_size_mm, c.mean_mm, c.p95_mm, c.max_mm, c.ours_s, c.calculix_s
                );
            }
            Outcome::Failed(e) => {
                let _ = writeln!(s, "Failed: {}\n", one_line(e));
            }
            Outcome::Skipped(why) => {
                let _ = writeln!(s, "Skipped: {why}\n");
            }
        }
        s
    }
}

fn row(t: &mut Table, p: &SizePoint) {
    let h = format!("{} mm", p.element_size_mm);
    let elements = if p.elements > 0 {
        p.elements.to_string()
    } else {
        "–".into()
    };
    let build = format!("{:.2} s", p.build_s);
    let (cycle, per, mem, keys, its, umax) = match &p.cycle {
        Outcome::Measured(c) => (
            format!("{:.2} s", c.cycle_s),
            format!("{:.1}", c.per_element_us),
            mib(c.peak_rss_bytes),
            format!("{} / {}", c.keys, c.solves),
            format!("{} / {}", c.newton_iterations, c.linear_iterations),
            format!("{:.1} mm", c.end_inhale_max_displacement_mm),
        ),
        Outcome::Failed(_) => {
            let d = || "–".to_string();
            ("failed (below)".into(), d(), d(), d(), d(), d())
        }
        Outcome::Skipped(why) => {
            let d = || "–".to_string();
            (format!("skipped: {why}"), d(), d(), d(), d(), d())
        }
    };
    let (mean, p95, max) = match &p.error {
        Outcome::Measured(e) => (
            format!("{:.3} mm", e.mean_mm),
            format!("{:.3} mm", e.p95_mm),
            format!("{:.3} mm", e.max_mm),
        ),
        Outcome::Skipped(why) if why.starts_with("the reference") => {
            ("reference".into(), "–".into(), "–".into())
        }
        _ => ("–".into(), "–".into(), "–".into()),
    };
    let alone = match &p.preconditioner {
        Outcome::Measured(c) => format!("{} it", c.iterations),
        _ => "–".into(),
    };
    t.row([
        h, elements, build, cycle, per, mem, keys, its, alone, umax, mean, p95, max,
    ]);
}

/// One series per case: every size with both a cycle time and an error (the reference has
/// none and is left out).
pub(super) fn write_plot(report: &ScaleBenchReport, dir: &Path) -> Result<()> {
    let series: Vec<TradeOffSeries> = report
        .cases
        .iter()
        .map(|case| TradeOffSeries {
            name: case.name.clone(),
            points: case
                .sizes
                .iter()
                .filter_map(|p| {
                    let c = p.cycle.measured()?;
                    let e = p.error.measured()?;
                    Some(TradeOffPoint {
                        label: format!("{} mm", p.element_size_mm),
                        time_s: c.cycle_s,
                        error_mm: e.mean_mm,
                    })
                })
                .collect(),
        })
        .filter(|s| !s.points.is_empty())
        .collect();
    if series.is_empty() {
        return Ok(());
    }
    let image = render_trade_off(
        "10-phase cycle: time against end-inhale error (mean, vs finest)",
        "mean error (mm)",
        &series,
    )?;
    crate::outputs::quicklook::write_png(&dir.join(TRADE_OFF_PNG), &image)
}
