//! Trachea and main bronchi: a seed on the upper slices, then minimax region growing cut
//! where the volume leaks into the parenchyma.

use std::collections::BinaryHeap;

use nalgebra::Vector3;

use super::components::label_components;
use super::report::AirwayGrowthPoint;
use super::settings::SegmentationSettings;
use super::slices::{in_slice_axes, slice_voxel};
use crate::volume::Volume;

/// Looks for the trachea on the upper slices of the lung air and returns a seed voxel.
pub(super) fn find_trachea_seed(
    ct: &Volume<f32>,
    lung_air: &[u8],
    body: &[u8],
    axial: usize,
    superior_up: bool,
    air_top: usize,
    settings: &SegmentationSettings,
) -> Option<usize> {
    let g = &ct.geometry;
    let dims = g.dims;
    let [ua, va] = in_slice_axes(axial);
    let (nu, nv) = (dims[ua], dims[va]);
    let (su, sv) = (g.spacing_mm[ua], g.spacing_mm[va]);
    let slice_mm = g.spacing_mm[axial];
    let depth = (settings.trachea_search_depth_mm / slice_mm).ceil() as usize + 1;
    let persist = ((15.0 / slice_mm).ceil() as usize).max(2);
    let [dmin, dmax] = settings.trachea_diameter_mm;
    let area_range_mm2 =
        std::f64::consts::FRAC_PI_4 * dmin * dmin..=std::f64::consts::FRAC_PI_4 * dmax * dmax;
    let n_axial = dims[axial];
    let slices: Vec<usize> = (0..depth.min(n_axial))
        .filter_map(|d| {
            if superior_up {
                air_top.checked_sub(d)
            } else {
                Some(air_top + d).filter(|&s| s < n_axial)
            }
        })
        .collect();
    let mut slice_mask = vec![0u8; nu * nv];
    // Per slice, the best trachea-like blob: (its darkest voxel).
    let found: Vec<Option<usize>> = slices
        .iter()
        .map(|&s| {
            let mut body_sum = [0.0f64; 2];
            let mut body_n = 0usize;
            for v in 0..nv {
                for u in 0..nu {
                    let idx = slice_voxel(dims, axial, s, u, v);
                    slice_mask[u + nu * v] = lung_air[idx];
                    if body[idx] != 0 {
                        body_sum[0] += u as f64;
                        body_sum[1] += v as f64;
                        body_n += 1;
                    }
                }
            }
            if body_n == 0 {
                return None;
            }
            let mid_ijk = |u: f64, v: f64| {
                let mut p = Vector3::zeros();
                p[axial] = s as f64;
                p[ua] = u;
                p[va] = v;
                p
            };
            let midline_x = g
                .voxel_to_lps_mm(mid_ijk(
                    body_sum[0] / body_n as f64,
                    body_sum[1] / body_n as f64,
                ))
                .x;
            let lab = label_components(&slice_mask, [nu, nv, 1]);
            let mut best: Option<(f64, usize)> = None;
            for (c, comp) in lab.components.iter().enumerate() {
                let area = comp.voxels as f64 * su * sv;
                if !area_range_mm2.contains(&area) {
                    continue;
                }
                let box_area = (comp.max_ijk[0] - comp.min_ijk[0] + 1) as f64
                    * (comp.max_ijk[1] - comp.min_ijk[1] + 1) as f64;
                // A disc fills π/4 ≈ 0.79 of its box; an apex crescent or a bronchus cut
                // lengthwise much less.
                if (comp.voxels as f64) < 0.5 * box_area {
                    continue;
                }
                let cen = comp.centroid_ijk();
                let offset = (g.voxel_to_lps_mm(mid_ijk(cen.x, cen.y)).x - midline_x).abs();
                if offset > settings.trachea_max_midline_offset_mm {
                    continue;
                }
                if best.is_none_or(|(o, _)| offset < o) {
                    best = Some((offset, c));
                }
            }
            let (_, c) = best?;
            lab.voxels_of(c)
                .map(|p| slice_voxel(dims, axial, s, p % nu, p / nu))
                .min_by(|&a, &b| ct.as_slice()[a].total_cmp(&ct.as_slice()[b]))
        })
        .collect();
    // The topmost slice from which the blob persists over `persist` slices downwards; the
    // seed is taken in the middle of that stretch, away from the partial-volume top.
    (0..found.len().saturating_sub(persist - 1))
        .find(|&d| found[d..d + persist].iter().all(Option::is_some))
        .and_then(|d| found[d + persist / 2])
}

/// Result of the airway region growing.
pub(super) struct GrownAirway {
    pub voxels: Vec<u32>,
    pub cutoff_hu: Option<f32>,
    pub curve: Vec<AirwayGrowthPoint>,
}

/// Minimax region growing from `seed` within `lung_air`, cut at the last threshold before the
/// volume explodes.
pub(super) fn grow_airway(
    ct: &Volume<f32>,
    lung_air: &[u8],
    seed: usize,
    threshold_hu: f32,
    settings: &SegmentationSettings,
) -> GrownAirway {
    let g = &ct.geometry;
    let dims = g.dims;
    let voxel_ml = g.voxel_volume_mm3() / 1000.0;
    let max_voxels = (settings.airway_max_ml / voxel_ml).ceil() as usize;
    let min_voxels = (settings.airway_min_ml / voxel_ml).ceil() as usize;
    let ceiling = settings.airway_max_hu.min(threshold_hu);
    let level = |idx: usize| ct.as_slice()[idx].ceil() as i32;
    // One bit per voxel: a hash set of the queued voxels cost more than the flood itself.
    let mut queued = vec![0u64; lung_air.len().div_ceil(64)];
    let mut first_queue = |v: usize| {
        let (word, bit) = (v / 64, 1u64 << (v % 64));
        let new = queued[word] & bit == 0;
        queued[word] |= bit;
        new
    };
    let mut heap = BinaryHeap::new();
    heap.push(std::cmp::Reverse((level(seed), seed as u32)));
    first_queue(seed);
    let mut order: Vec<u32> = Vec::new();
    let mut levels: Vec<i32> = Vec::new();
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    // One step past the cap so the curve shows the explosion.
    while let Some(std::cmp::Reverse((lvl, idx))) = heap.pop() {
        if lvl as f32 > ceiling || order.len() > max_voxels {
            break;
        }
        order.push(idx);
        levels.push(lvl);
        let i = idx as usize;
        let (x, y, z) = (i % nx, (i / nx) % ny, i / plane);
        let mut visit = |n: usize| {
            if lung_air[n] != 0 && first_queue(n) {
                heap.push(std::cmp::Reverse((lvl.max(level(n)), n as u32)));
            }
        };
        if x > 0 {
            visit(i - 1);
        }
        if x + 1 < nx {
            visit(i + 1);
        }
        if y > 0 {
            visit(i - nx);
        }
        if y + 1 < ny {
            visit(i + nx);
        }
        if z > 0 {
            visit(i - plane);
        }
        if z + 1 < nz {
            visit(i + plane);
        }
    }
    let mut curve = Vec::new();
    let mut cutoff: Option<(f32, usize)> = None;
    let step = settings.airway_step_hu;
    let mut t = (levels.first().copied().unwrap_or(0) as f32 / step).ceil() * step;
    let truncated = order.len() > max_voxels;
    let mut previous = 0usize;
    while t <= ceiling {
        let n = levels.partition_point(|&l| l as f32 <= t);
        curve.push(AirwayGrowthPoint {
            threshold_hu: t,
            volume_ml: n as f64 * voxel_ml,
        });
        let exploded = n > max_voxels
            || (previous >= min_voxels && n as f64 > settings.airway_leak_ratio * previous as f64);
        if exploded {
            break;
        }
        if truncated && n == levels.len() {
            break;
        }
        cutoff = Some((t, n));
        previous = n;
        t += step;
    }
    let (cutoff_hu, n) = match cutoff {
        Some((t, n)) => (Some(t), n),
        None => (None, 0),
    };
    order.truncate(n);
    GrownAirway {
        voxels: order,
        cutoff_hu,
        curve,
    }
}
