//! Ingest benchmark: lung segmentation time, accuracy and memory.
//!
//! Two measurements:
//!
//! * **CIP case** (`ct-64.nrrd`, 64 × 64 × 79 at ≈ 4 mm): median wall time of N
//!   segmentations and the Dice overlaps with the expert map `lm-64.nrrd`.
//! * **Clinical-size grid**: the CIP CT upsampled by trilinear interpolation to
//!   512 × 512 × 300 (quick mode: 160 × 160 × 120) keeping its physical extent: the first and
//!   last voxel centres stay where they were, so the spacing becomes
//!   `old_spacing · (old_n − 1) / (new_n − 1)` (≈ 0.51 × 0.51 × 1.04 mm) and the anatomy is
//!   unchanged. Median wall time of ≥ 3 segmentations, and memory from `/proc/self/status`:
//!   `VmRSS` just before the runs (the upsampled CT already resident), then `VmHWM` (peak
//!   resident set) after them, having reset the peak with `/proc/self/clear_refs` ← 5 so it
//!   belongs to the segmentation; the report gives the peak and its increase over the
//!   before-RSS. On kernels refusing the reset, the peak includes earlier phases (stated).
//!   CPU time per run (utime + stime of /proc/self/stat) is reported beside the wall time:
//!   on a shared machine, CPU time ÷ cores is what an idle machine would take.
//!
//! Targets: ≤ 1 s on the CIP case; ≤ 10 s and ≤ 4 GB peak on 512 × 512 × 300.

use std::fmt::Write as _;
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use super::{Outcome, TimeStats};
use crate::datasets::cip_chest_ct64;
use crate::formats::nrrd::read_nrrd;
use crate::ingest::segmentation::{
    dice, segment_lungs, SegmentationSettings, LEFT_LUNG, RIGHT_LUNG,
};
use crate::markdown::{mib, or_dash, Table};
use crate::process::{current_rss_bytes, peak_rss_bytes, process_cpu_s, reset_peak_rss};
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, Result};

/// Clinical grid of the full benchmark.
pub const FULL_GRID: [usize; 3] = [512, 512, 300];
/// Smaller grid of the quick benchmark.
pub const QUICK_GRID: [usize; 3] = [160, 160, 120];
/// Target wall time on the CIP case, s.
pub const CIP_TARGET_S: f64 = 1.0;
/// Target wall time on 512 × 512 × 300, s.
pub const FULL_TARGET_S: f64 = 10.0;
/// Target peak memory on 512 × 512 × 300, bytes.
pub const FULL_TARGET_BYTES: u64 = 4 << 30;

/// What to run.
#[derive(Debug, Clone, Serialize)]
pub struct IngestBenchOptions {
    /// Smaller upsampled grid, for smoke tests.
    pub quick: bool,
    /// Segmentations timed per case (at least 3 on the upsampled grid).
    pub repeats: usize,
}

impl Default for IngestBenchOptions {
    fn default() -> Self {
        IngestBenchOptions {
            quick: false,
            repeats: 5,
        }
    }
}

/// Segmentation of the CIP case against its expert map.
#[derive(Debug, Clone, Serialize)]
pub struct CipSegmentationBench {
    /// Wall time of `segment_lungs`.
    pub time: TimeStats,
    /// Dice of both lungs together.
    pub dice_lungs: f64,
    /// Dice of the right lung.
    pub dice_right: f64,
    /// Dice of the left lung.
    pub dice_left: f64,
    /// Our right and left lung volumes, mL.
    pub volume_ml: [f64; 2],
    /// The expert map's right and left lung volumes, mL.
    pub expert_volume_ml: [f64; 2],
    /// Step times of the last run, s.
    pub step_times_s: Vec<(String, f64)>,
}

/// Segmentation of the upsampled CT.
#[derive(Debug, Clone, Serialize)]
pub struct UpsampledSegmentationBench {
    /// Grid.
    pub dims: [usize; 3],
    /// Spacing after upsampling, mm.
    pub spacing_mm: [f64; 3],
    /// Time to upsample, s.
    pub upsample_s: f64,
    /// Wall time of `segment_lungs`.
    pub time: TimeStats,
    /// CPU time per segmentation (user + system, all threads), s: with `cores` this tells
    /// the wall time on an idle machine when the machine was shared.
    pub cpu_per_run_s: Option<f64>,
    /// Resident memory before the runs (CT resident), bytes.
    pub rss_before_bytes: Option<u64>,
    /// Peak resident memory during the runs, bytes.
    pub peak_rss_bytes: Option<u64>,
    /// Peak minus before, bytes: what segmentation itself needs.
    pub peak_increase_bytes: Option<u64>,
    /// Whether the peak was reset before the runs (else it may include earlier phases).
    pub peak_reset: bool,
    /// Lung volume found, mL (compare with the CIP case: same anatomy).
    pub lung_volume_ml: f64,
    /// Dice of both lungs against the CIP segmentation upsampled by nearest neighbour.
    pub dice_vs_coarse: f64,
    /// Step times of the last run, s.
    pub step_times_s: Vec<(String, f64)>,
}

/// The ingest benchmark report.
#[derive(Debug, Clone, Serialize)]
pub struct IngestBench {
    /// Options used.
    pub options: IngestBenchOptions,
    /// Logical cores available.
    pub cores: usize,
    /// CIP case.
    pub cip: Outcome<CipSegmentationBench>,
    /// Upsampled CT.
    pub upsampled: Outcome<UpsampledSegmentationBench>,
}

/// Trilinear resampling of `ct` onto `dims` voxels spanning the same first-to-last voxel
/// centres (same origin and direction, spacing scaled by `(n − 1)/(dims − 1)`).
pub fn upsample_trilinear(ct: &Volume<f32>, dims: [usize; 3]) -> Result<Volume<f32>> {
    let src = ct.geometry;
    if dims.contains(&0) || src.dims.contains(&0) {
        return Err(Error::argument(
            "resampling target",
            format!("cannot resample grid {:?} to {dims:?}", src.dims),
        ));
    }
    let scale = [0, 1, 2].map(|a| {
        if dims[a] > 1 {
            (src.dims[a] - 1) as f64 / (dims[a] - 1) as f64
        } else {
            0.0
        }
    });
    let geometry = VolumeGeometry {
        dims,
        spacing_mm: [0, 1, 2].map(|a| {
            if dims[a] > 1 {
                src.spacing_mm[a] * scale[a]
            } else {
                src.spacing_mm[a]
            }
        }),
        ..src
    };
    geometry.validate("upsampled CT")?;
    // Source index and weight along each axis, precomputed once.
    let taps = |a: usize| -> Vec<(usize, usize, f32)> {
        (0..dims[a])
            .map(|n| {
                let x = n as f64 * scale[a];
                let i0 = (x.floor() as usize).min(src.dims[a] - 1);
                let i1 = (i0 + 1).min(src.dims[a] - 1);
                (i0, i1, (x - i0 as f64) as f32)
            })
            .collect()
    };
    let (tx, ty, tz) = (taps(0), taps(1), taps(2));
    let [sx, sy, _] = src.dims;
    let mut data = vec![0f32; geometry.voxel_count()];
    data.par_chunks_mut(dims[0] * dims[1])
        .zip(&tz)
        .for_each(|(slice, &(k0, k1, wz))| {
            for (row, &(j0, j1, wy)) in slice.chunks_mut(dims[0]).zip(&ty) {
                let at = |i: usize, j: usize, k: usize| ct.as_slice()[i + sx * (j + sy * k)];
                for (out, &(i0, i1, wx)) in row.iter_mut().zip(&tx) {
                    let lerp = |a: f32, b: f32, w: f32| a + (b - a) * w;
                    let c00 = lerp(at(i0, j0, k0), at(i1, j0, k0), wx);
                    let c10 = lerp(at(i0, j1, k0), at(i1, j1, k0), wx);
                    let c01 = lerp(at(i0, j0, k1), at(i1, j0, k1), wx);
                    let c11 = lerp(at(i0, j1, k1), at(i1, j1, k1), wx);
                    *out = lerp(lerp(c00, c10, wy), lerp(c01, c11, wy), wz);
                }
            }
        });
    Volume::from_data(geometry, data)
}

/// Runs the ingest benchmark; cases whose data are missing are reported as skipped.
pub fn run_ingest_bench(opts: &IngestBenchOptions) -> Result<IngestBench> {
    let cores = rayon::current_num_threads();
    let Some(dir) = cip_chest_ct64() else {
        let why = "shared data not found (set LUNGMOTION_SHARED_DATA)".to_string();
        return Ok(IngestBench {
            options: opts.clone(),
            cores,
            cip: Outcome::Skipped(why.clone()),
            upsampled: Outcome::Skipped(why),
        });
    };
    let ct = read_nrrd(&dir.join("ct-64.nrrd"))?;
    let lm = read_nrrd(&dir.join("lm-64.nrrd"))?;
    let settings = SegmentationSettings::default();
    let cip = Outcome::from_result(bench_cip(&ct, &lm, &settings, opts.repeats.max(1)));
    let grid = if opts.quick { QUICK_GRID } else { FULL_GRID };
    let upsampled =
        Outcome::from_result(bench_upsampled(&ct, grid, &settings, opts.repeats.max(3)));
    Ok(IngestBench {
        options: opts.clone(),
        cores,
        cip,
        upsampled,
    })
}

fn bench_cip(
    ct: &Volume<f32>,
    lm: &Volume<f32>,
    settings: &SegmentationSettings,
    repeats: usize,
) -> Result<CipSegmentationBench> {
    let expert = crate::datasets::cip_expert_labels(lm);
    let mut times = Vec::with_capacity(repeats);
    let mut last = None;
    for _ in 0..repeats {
        let start = Instant::now();
        let seg = segment_lungs(ct, settings)?;
        times.push(start.elapsed().as_secs_f64());
        last = Some(seg);
    }
    let seg = last.ok_or_else(|| Error::argument("ingest benchmark", "no run"))?;
    let union = |v: &Volume<u8>| v.map(|l| (l == RIGHT_LUNG || l == LEFT_LUNG) as u8);
    let voxel_ml = ct.geometry.voxel_volume_mm3() / 1000.0;
    let count = |l: u8| expert.as_slice().iter().filter(|&&x| x == l).count() as f64 * voxel_ml;
    Ok(CipSegmentationBench {
        time: TimeStats::new(&times),
        dice_lungs: dice(&union(&seg.lungs), 1, &union(&expert), 1)?,
        dice_right: dice(&seg.lungs, RIGHT_LUNG, &expert, RIGHT_LUNG)?,
        dice_left: dice(&seg.lungs, LEFT_LUNG, &expert, LEFT_LUNG)?,
        volume_ml: [seg.report.right_volume_ml, seg.report.left_volume_ml],
        expert_volume_ml: [count(RIGHT_LUNG), count(LEFT_LUNG)],
        step_times_s: seg.report.step_times_s,
    })
}

fn bench_upsampled(
    ct: &Volume<f32>,
    grid: [usize; 3],
    settings: &SegmentationSettings,
    repeats: usize,
) -> Result<UpsampledSegmentationBench> {
    let coarse = segment_lungs(ct, settings)?;
    let start = Instant::now();
    let fine = upsample_trilinear(ct, grid)?;
    let upsample_s = start.elapsed().as_secs_f64();
    let rss_before = current_rss_bytes();
    let peak_reset = reset_peak_rss();
    let cpu_before = process_cpu_s();
    let mut times = Vec::with_capacity(repeats);
    let mut last = None;
    for _ in 0..repeats {
        // The previous result is dropped first so runs do not stack up in memory.
        drop(last.take());
        let start = Instant::now();
        let seg = segment_lungs(&fine, settings)?;
        times.push(start.elapsed().as_secs_f64());
        last = Some(seg);
    }
    let peak = peak_rss_bytes();
    let cpu_per_run_s = cpu_before
        .zip(process_cpu_s())
        .map(|(b, a)| (a - b) / repeats as f64);
    let seg = last.ok_or_else(|| Error::argument("ingest benchmark", "no run"))?;
    // The coarse result on the fine grid, nearest voxel.
    let g = fine.geometry;
    let cg = coarse.lungs.geometry;
    let coarse_on_fine: Vec<u8> = (0..g.voxel_count())
        .into_par_iter()
        .map(|idx| {
            let [nx, ny, _] = g.dims;
            let ijk = nalgebra::Vector3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            );
            let c = cg.lps_mm_to_voxel(g.voxel_to_lps_mm(ijk));
            let [i, j, k] = [c.x, c.y, c.z].map(|v| v.round().max(0.0) as usize);
            let [i, j, k] = [
                i.min(cg.dims[0] - 1),
                j.min(cg.dims[1] - 1),
                k.min(cg.dims[2] - 1),
            ];
            (coarse.lungs.get(i, j, k) != 0) as u8
        })
        .collect();
    let coarse_on_fine = Volume::from_data(g, coarse_on_fine)?;
    let union = seg.lungs.map(|l| (l != 0) as u8);
    Ok(UpsampledSegmentationBench {
        dims: grid,
        spacing_mm: g.spacing_mm,
        upsample_s,
        time: TimeStats::new(&times),
        cpu_per_run_s,
        rss_before_bytes: rss_before,
        peak_rss_bytes: peak,
        peak_increase_bytes: peak.zip(rss_before).map(|(p, b)| p.saturating_sub(b)),
        peak_reset,
        lung_volume_ml: seg.report.lung_volume_ml,
        dice_vs_coarse: dice(&union, 1, &coarse_on_fine, 1)?,
        step_times_s: seg.report.step_times_s,
    })
}

fn steps(s: &[(String, f64)]) -> String {
    s.iter()
        .map(|(n, t)| format!("{n} {t:.3}"))
        .collect::<Vec<_>>()
        .join(", ")
}

impl IngestBench {
    /// The report as Markdown: a table per case with the targets beside the measurements.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# Ingest: lung segmentation\n");
        let _ = writeln!(
            s,
            "{} cores; medians of repeated runs [min – max]. Memory from /proc/self/status: \
             VmRSS before the runs, VmHWM after (peak reset by clear_refs first).\n",
            self.cores
        );
        let _ = writeln!(s, "## CIP chest CT (64 × 64 × 79, ≈ 4 mm)\n");
        match &self.cip {
            Outcome::Measured(c) => {
                let mut table = Table::new([
                    "Time s [min – max]",
                    "Target",
                    "Dice both",
                    "Dice right",
                    "Dice left",
                    "Right mL (expert)",
                    "Left mL (expert)",
                ]);
                let met = if c.time.median_s <= CIP_TARGET_S {
                    "met"
                } else {
                    "missed"
                };
                table.row([
                    format!(
                        "{:.3} [{:.3} – {:.3}] ×{}",
                        c.time.median_s, c.time.min_s, c.time.max_s, c.time.runs
                    ),
                    format!("≤ {CIP_TARGET_S} s: {met}"),
                    format!("{:.4}", c.dice_lungs),
                    format!("{:.4}", c.dice_right),
                    format!("{:.4}", c.dice_left),
                    format!("{:.0} ({:.0})", c.volume_ml[0], c.expert_volume_ml[0]),
                    format!("{:.0} ({:.0})", c.volume_ml[1], c.expert_volume_ml[1]),
                ]);
                table.write_to(&mut s);
                let _ = writeln!(s, "\nSteps (s): {}", steps(&c.step_times_s));
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "Not measured: {e}");
            }
        }
        let _ = writeln!(
            s,
            "\n## CIP CT upsampled (trilinear, same physical extent)\n"
        );
        match &self.upsampled {
            Outcome::Measured(u) => {
                let full = u.dims == FULL_GRID;
                let judge = |ok: bool| match (full, ok) {
                    (false, _) => "n/a (quick grid)",
                    (true, true) => "met",
                    (true, false) => "missed",
                };
                let mut table = Table::new([
                    "Grid".to_string(),
                    "Spacing mm".into(),
                    "Time s [min – max]".into(),
                    format!("Target ≤ {FULL_TARGET_S} s"),
                    "CPU s per run".into(),
                    "RSS before".into(),
                    "Peak RSS".into(),
                    "Peak increase".into(),
                    "Target ≤ 4 GiB".into(),
                    "Lungs mL".into(),
                    "Dice vs 4 mm result".into(),
                ]);
                table.row([
                    format!("{}×{}×{}", u.dims[0], u.dims[1], u.dims[2]),
                    format!(
                        "{:.2}×{:.2}×{:.2}",
                        u.spacing_mm[0], u.spacing_mm[1], u.spacing_mm[2]
                    ),
                    format!(
                        "{:.2} [{:.2} – {:.2}] ×{}",
                        u.time.median_s, u.time.min_s, u.time.max_s, u.time.runs
                    ),
                    judge(u.time.median_s <= FULL_TARGET_S).into(),
                    or_dash(u.cpu_per_run_s, |c| format!("{c:.2}")),
                    mib(u.rss_before_bytes),
                    mib(u.peak_rss_bytes),
                    mib(u.peak_increase_bytes),
                    judge(u.peak_rss_bytes.is_some_and(|p| p <= FULL_TARGET_BYTES)).into(),
                    format!("{:.0}", u.lung_volume_ml),
                    format!("{:.4}", u.dice_vs_coarse),
                ]);
                table.write_to(&mut s);
                let _ = writeln!(
                    s,
                    "\nUpsampling took {:.2} s (not included).{} Steps of the last run (s): {}",
                    u.upsample_s,
                    if u.peak_reset {
                        ""
                    } else {
                        " The peak could not be reset: it includes earlier phases."
                    },
                    steps(&u.step_times_s)
                );
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "Not measured: {e}");
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trilinear_upsampling_reproduces_a_linear_field_and_keeps_the_extent() {
        let g = VolumeGeometry {
            dims: [4, 3, 5],
            spacing_mm: [2.0, 3.0, 1.5],
            origin_lps_mm: [-10.0, 5.0, 100.0],
            direction_lps: [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let field = |p: nalgebra::Vector3<f64>| (0.5 * p.x - 2.0 * p.y + 0.25 * p.z) as f32;
        let mut data = Vec::new();
        for k in 0..5 {
            for j in 0..3 {
                for i in 0..4 {
                    data.push(field(g.voxel_to_lps_mm(nalgebra::Vector3::new(
                        i as f64, j as f64, k as f64,
                    ))));
                }
            }
        }
        let ct = Volume::from_data(g, data).unwrap();
        let up = upsample_trilinear(&ct, [7, 9, 13]).unwrap();
        let ug = up.geometry;
        let last = |g: &VolumeGeometry| {
            g.voxel_to_lps_mm(nalgebra::Vector3::from(g.dims.map(|n| (n - 1) as f64)))
        };
        assert!((last(&ug) - last(&g)).norm() < 1e-9);
        for k in 0..13 {
            for j in 0..9 {
                for i in 0..7 {
                    let p =
                        ug.voxel_to_lps_mm(nalgebra::Vector3::new(i as f64, j as f64, k as f64));
                    assert!((up.get(i, j, k) - field(p)).abs() < 1e-3);
                }
            }
        }
    }

    #[test]
    fn quick_bench_reports_both_cases_or_says_why_not() {
        let bench = run_ingest_bench(&IngestBenchOptions {
            quick: true,
            repeats: 1,
        })
        .unwrap();
        let md = bench.to_markdown();
        assert!(
            md.contains("## CIP chest CT") && md.contains("upsampled"),
            "{md}"
        );
        serde_json::to_string(&bench).unwrap();
        if cip_chest_ct64().is_none() {
            println!("skipped: shared data not found");
            return;
        }
        let cip = bench.cip.measured().expect("CIP case measured");
        assert!(cip.dice_lungs > 0.9, "{cip:?}");
        let up = bench.upsampled.measured().expect("upsampled case measured");
        assert_eq!(up.dims, QUICK_GRID);
        assert!(up.dice_vs_coarse > 0.9, "{up:?}");
        println!("{md}");
    }

    /// The full benchmark; run with
    /// `cargo test --release --lib bench::ingest -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn full_ingest_bench() {
        let bench = run_ingest_bench(&IngestBenchOptions::default()).unwrap();
        println!("{}", bench.to_markdown());
        println!("{}", serde_json::to_string_pretty(&bench).unwrap());
    }
}
