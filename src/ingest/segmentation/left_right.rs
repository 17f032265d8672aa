//! Left and right lung: two separate components, or one split at the junction by erosion
//! until two cores appear and a watershed from those cores.

use nalgebra::Vector3;
use ndarray::Zip;
use rayon::prelude::*;

use super::components::{label_components, Labelling};
use super::crop::Crop;
use super::morphology::{axial_axis, grid_view, squared_distance_mm2};
use super::report::Steps;
use super::settings::SegmentationSettings;
use super::{DroppedAir, LungAir, ScanGrid, LEFT_LUNG, RIGHT_LUNG};
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

/// Full-grid lung labels and, when the lungs touched, the depth at which they came apart.
pub(super) struct LeftRight {
    /// 0 background, [`RIGHT_LUNG`], [`LEFT_LUNG`].
    pub labels: Vec<u8>,
    /// Erosion depth at which touching lungs came apart, mm (None: they did not touch).
    pub separation_depth_mm: Option<f64>,
}

/// Step 5, left/right: two lung-sized components on either side of the midline are the
/// lungs; one component with substantial volume on both sides holds both (they touch at an
/// anterior/posterior junction) and is split where it is thinnest. Labels follow LPS x.
pub(super) fn label_left_right(
    lung_air: LungAir,
    midline_x_mm: f64,
    grid: &ScanGrid,
    settings: &SegmentationSettings,
    steps: &mut Steps,
    dropped: &mut DroppedAir,
    warnings: &mut Vec<String>,
) -> Result<LeftRight> {
    let g = &grid.geometry;
    let min_lung_voxels = lung_air.min_lung_voxels;
    let lab = label_components(&lung_air.mask, g.dims);
    drop(lung_air);
    let sides = lab.side_voxels(g, midline_x_mm);
    let big: Vec<usize> = (0..lab.components.len())
        .filter(|&c| lab.components[c].voxels >= min_lung_voxels)
        .collect();
    if big.is_empty() {
        return Err(Error::Ingest(format!(
            "no lung found: after removing the airways no air region reaches {:.0} mL",
            settings.min_lung_ml
        )));
    }
    let first = big[0];
    let minority =
        sides[first][0].min(sides[first][1]) as f64 / lab.components[first].voxels as f64;
    if minority >= settings.bilateral_fraction {
        let (labels, depth) = split_touching_lungs(&lab, first, g, midline_x_mm, settings, steps)?;
        dropped.voxels += lab.components[1..].iter().map(|c| c.voxels).sum::<usize>();
        dropped.count += lab.components.len() - 1;
        return Ok(LeftRight {
            labels,
            separation_depth_mm: Some(depth),
        });
    }
    let labels = keep_separate_lungs(&lab, &big, midline_x_mm, grid, settings, dropped, warnings)?;
    Ok(LeftRight {
        labels,
        separation_depth_mm: None,
    })
}

/// The largest component and the largest one on the other side of the midline are the
/// lungs, the rest is dropped; no second lung is refused unless `allow_single_lung`.
fn keep_separate_lungs(
    lab: &Labelling,
    big: &[usize],
    midline_x_mm: f64,
    grid: &ScanGrid,
    settings: &SegmentationSettings,
    dropped: &mut DroppedAir,
    warnings: &mut Vec<String>,
) -> Result<Vec<u8>> {
    let g = &grid.geometry;
    let side_of = |c: usize| {
        let x = g.voxel_to_lps_mm(lab.components[c].centroid_ijk()).x;
        if x < midline_x_mm {
            RIGHT_LUNG
        } else {
            LEFT_LUNG
        }
    };
    let first = big[0];
    let s0 = side_of(first);
    let second = big[1..].iter().copied().find(|&c| side_of(c) != s0);
    let keep = |c: usize| c == first || Some(c) == second;
    for c in 0..lab.components.len() {
        if !keep(c) {
            dropped.voxels += lab.components[c].voxels;
            dropped.count += 1;
        }
    }
    if second.is_none() {
        let (found, missing) = if s0 == RIGHT_LUNG {
            ("right", "left")
        } else {
            ("left", "right")
        };
        let msg = format!(
            "only one lung found: the {found} lung ({:.0} mL); no air region of at least \
             {:.0} mL on the patient's {missing}",
            lab.components[first].voxels as f64 * grid.voxel_ml,
            settings.min_lung_ml
        );
        if settings.allow_single_lung {
            warnings.push(msg);
        } else {
            return Err(Error::Ingest(msg));
        }
    }
    let sides_of: Vec<u8> = (0..lab.components.len())
        .map(|c| if keep(c) { side_of(c) } else { 0 })
        .collect();
    Ok(lab.paint(|c| sides_of[c]))
}

/// Splits the component holding both lungs at their junction; returns full-grid labels and
/// the erosion depth in mm at which two cores appeared.
pub(super) fn split_touching_lungs(
    lab: &Labelling,
    component: usize,
    g: &VolumeGeometry,
    midline_x_mm: f64,
    settings: &SegmentationSettings,
    steps: &mut Steps,
) -> Result<(Vec<u8>, f64)> {
    let dims = g.dims;
    let comp = &lab.components[component];
    let crop = Crop::around(comp.min_ijk, comp.max_ijk, [1; 3], dims);
    let full = lab.paint(|c| (c == component) as u8);
    let mask = crop.extract(&full, dims, |v| v);
    drop(full);
    let cd = crop.dims;
    let (axial, _) = axial_axis(&g.direction_lps);
    let depth2 = squared_distance_mm2(&mask, cd, g.spacing_mm, false, Some(axial));
    let crop_geometry = VolumeGeometry {
        dims: cd,
        origin_lps_mm: g
            .voxel_to_lps_mm(Vector3::from(crop.lo.map(|v| v as f64)))
            .into(),
        ..*g
    };
    // Half a voxel, but at least 1 mm: finer steps only move the seeds, not the watershed cut.
    steps.mark("left/right: distance map")?;
    let step_mm = (0.5 * g.spacing_mm.iter().copied().fold(f64::INFINITY, f64::min)).max(1.0);
    let mut r = step_mm;
    let mut seeds = None;
    let mut core = vec![0u8; mask.len()];
    while r <= settings.separation_max_depth_mm {
        steps.cancel.check("the separation of the lungs")?;
        let r2 = (r * r) as f32;
        core.par_iter_mut()
            .zip(&depth2)
            .for_each(|(c, &d)| *c = (d > r2) as u8);
        let core_lab = label_components(&core, cd);
        if core_lab.components.is_empty() {
            break;
        }
        let sides = core_lab.side_voxels(&crop_geometry, midline_x_mm);
        let side_of = |c: usize| {
            let x = crop_geometry
                .voxel_to_lps_mm(core_lab.components[c].centroid_ijk())
                .x;
            if x < midline_x_mm {
                RIGHT_LUNG
            } else {
                LEFT_LUNG
            }
        };
        let first = &core_lab.components[0];
        let minority = sides[0][0].min(sides[0][1]) as f64 / first.voxels as f64;
        if minority < 0.5 * settings.bilateral_fraction {
            let s0 = side_of(0);
            let other = (1..core_lab.components.len()).find(|&c| side_of(c) != s0);
            if let Some(o) = other.filter(|&o| core_lab.components[o].voxels * 10 >= first.voxels) {
                let mut seeded = vec![0u8; mask.len()];
                for (c, label) in [(0, s0), (o, side_of(o))] {
                    for v in core_lab.voxels_of(c) {
                        seeded[v] = label;
                    }
                }
                seeds = Some(seeded);
                break;
            }
        }
        r += step_mm;
    }
    let Some(mut labels_crop) = seeds else {
        return Err(Error::Ingest(format!(
            "only one lung found: the two lungs touch and did not come apart when eroded up to \
             {:.0} mm (separation_max_depth_mm)",
            settings.separation_max_depth_mm
        )));
    };
    steps.mark("left/right: erosion until two cores")?;
    watershed_from_seeds(&mut labels_crop, &depth2, cd, step_mm * 0.5);
    let mut labels = vec![0u8; g.voxel_count()];
    Zip::from(crop.view_mut(&mut labels, dims))
        .and(grid_view(&labels_crop, cd))
        .par_for_each(|l, &c| *l = c);
    Ok((labels, r))
}

/// Floods the labels of the seeds over the voxels with positive depth, deepest first
/// (buckets of `bucket_mm`), so two floods meet where the mask is thinnest.
fn watershed_from_seeds(labels: &mut [u8], depth2: &[f32], dims: [usize; 3], bucket_mm: f64) {
    let bucket_of = |d2: f32| (d2.max(0.0).sqrt() as f64 / bucket_mm) as usize;
    let top = depth2
        .par_iter()
        .filter(|d| d.is_finite())
        .fold(|| 0.0f32, |a, &b| a.max(b))
        .reduce(|| 0.0f32, f32::max);
    let mut buckets: Vec<Vec<u32>> = vec![Vec::new(); bucket_of(top) + 1];
    for (v, &l) in labels.iter().enumerate() {
        if l != 0 {
            buckets[bucket_of(depth2[v])].push(v as u32);
        }
    }
    // The bucket of each voxel still to flood (unlabelled, positive depth), computed on all
    // cores; `CLOSED` for the others. The serial flood then reads two bytes per neighbour
    // instead of a label and a depth on separate cache lines. A bucket is capped below
    // `CLOSED` (only an infinite depth, 16 m at the least, reaches the cap), which changes
    // nothing: a voxel is queued in the smaller of its bucket and the current one.
    const CLOSED: u16 = u16::MAX;
    let mut pending: Vec<u16> = labels
        .par_iter()
        .zip(depth2)
        .map(|(&l, &d2)| {
            if l == 0 && d2 > 0.0 {
                bucket_of(d2).min(CLOSED as usize - 1) as u16
            } else {
                CLOSED
            }
        })
        .collect();
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    for b in (0..buckets.len()).rev() {
        while let Some(v) = buckets[b].pop() {
            let v = v as usize;
            let label = labels[v];
            // Two divisions instead of three: this loop visits every lung voxel once.
            let z = v / plane;
            let in_plane = v - z * plane;
            let y = in_plane / nx;
            let x = in_plane - y * nx;
            let neighbours = [
                (x > 0).then(|| v - 1),
                (x + 1 < nx).then(|| v + 1),
                (y > 0).then(|| v - nx),
                (y + 1 < ny).then(|| v + nx),
                (z > 0).then(|| v - plane),
                (z + 1 < nz).then(|| v + plane),
            ];
            for n in neighbours.into_iter().flatten() {
                let bn = pending[n];
                if bn != CLOSED {
                    pending[n] = CLOSED;
                    labels[n] = label;
                    buckets[b.min(bn as usize)].push(n as u32);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The flood as first written: label and depth read per neighbour, bucket computed there.
    fn reference_watershed(labels: &mut [u8], depth2: &[f32], dims: [usize; 3], bucket_mm: f64) {
        let bucket_of = |d2: f32| (d2.max(0.0).sqrt() as f64 / bucket_mm) as usize;
        let top = depth2.iter().fold(0.0f32, |a, &b| a.max(b));
        let mut buckets: Vec<Vec<u32>> = vec![Vec::new(); bucket_of(top) + 1];
        for (v, &l) in labels.iter().enumerate() {
            if l != 0 {
                buckets[bucket_of(depth2[v])].push(v as u32);
            }
        }
        let [nx, ny, nz] = dims;
        for b in (0..buckets.len()).rev() {
            while let Some(v) = buckets[b].pop() {
                let v = v as usize;
                let (x, y, z) = (v % nx, (v / nx) % ny, v / (nx * ny));
                let neighbours = [
                    (x > 0).then(|| v - 1),
                    (x + 1 < nx).then(|| v + 1),
                    (y > 0).then(|| v - nx),
                    (y + 1 < ny).then(|| v + nx),
                    (z > 0).then(|| v - nx * ny),
                    (z + 1 < nz).then(|| v + nx * ny),
                ];
                for n in neighbours.into_iter().flatten() {
                    if labels[n] == 0 && depth2[n] > 0.0 {
                        labels[n] = labels[v];
                        buckets[b.min(bucket_of(depth2[n]))].push(n as u32);
                    }
                }
            }
        }
    }

    #[test]
    fn watershed_equals_the_plain_flood_voxel_for_voxel() {
        // Two blobs joined by a thin neck, deepest in their middles, with pseudo-random
        // wrinkles so many voxels share a bucket; one seed in each: the floods meet in the neck.
        let dims = [30, 12, 9];
        let n: usize = dims.iter().product();
        let depth2: Vec<f32> = (0..n)
            .map(|x| {
                let (i, j, k) = (x % 30, x / 30 % 12, x / 360);
                let wrinkle = (x.wrapping_mul(2_654_435_761) % 7) as f32 * 0.1;
                let (i, j, k) = (i as f32, j as f32, k as f32);
                let depth = if !(1.0..11.0).contains(&j) || !(1.0..8.0).contains(&k) {
                    0.0
                } else if i < 12.0 {
                    (i + 1.0)
                        .min(12.0 - i)
                        .min(j)
                        .min(11.0 - j)
                        .min(k)
                        .min(8.0 - k)
                } else if i > 17.0 {
                    (i - 17.0)
                        .min(30.0 - i)
                        .min(j)
                        .min(11.0 - j)
                        .min(k)
                        .min(8.0 - k)
                } else if (5.0..7.0).contains(&j) {
                    0.5
                } else {
                    0.0
                };
                if depth > 0.0 {
                    (depth + wrinkle).powi(2)
                } else {
                    0.0
                }
            })
            .collect();
        let mut seeds = vec![0u8; n];
        seeds[5 + 30 * (6 + 12 * 4)] = RIGHT_LUNG;
        seeds[25 + 30 * (6 + 12 * 4)] = LEFT_LUNG;
        let mut expected = seeds.clone();
        reference_watershed(&mut expected, &depth2, dims, 0.5);
        let mut labels = seeds;
        watershed_from_seeds(&mut labels, &depth2, dims, 0.5);
        assert_eq!(labels, expected);
        for label in [RIGHT_LUNG, LEFT_LUNG] {
            assert!(labels.iter().filter(|&&l| l == label).count() > 100);
        }
    }
}
