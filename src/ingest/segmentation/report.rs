//! What a segmentation returns: the masks on the CT grid, the report of its numbers and
//! decisions, and the timer of its steps.

use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::settings::ThresholdMethod;
use crate::ingest::Cancel;
use crate::volume::Volume;
use crate::Result;

/// One point of the airway region-growing curve.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct AirwayGrowthPoint {
    /// Threshold, HU.
    pub threshold_hu: f32,
    /// Volume of the region grown from the seed below that threshold, mL.
    pub volume_ml: f64,
}

/// Numbers and decisions of one segmentation, for logs and reports.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SegmentationReport {
    /// Volume of the right lung, mL.
    pub right_volume_ml: f64,
    /// Volume of the left lung, mL.
    pub left_volume_ml: f64,
    /// Volume of both lungs, mL.
    pub lung_volume_ml: f64,
    /// Air/tissue threshold used, HU.
    pub threshold_hu: f32,
    /// How it was chosen.
    pub threshold_method: ThresholdMethod,
    /// Trachea and main bronchi outside the lungs, mL.
    pub airway_volume_ml: f64,
    /// LPS position of the trachea seed, mm (None: not found, airways not removed).
    pub airway_seed_lps_mm: Option<[f64; 3]>,
    /// Threshold where airway growth stopped (the last before the leak), HU.
    pub airway_cutoff_hu: Option<f32>,
    /// Airway volume against threshold, the curve the leak was read from.
    pub airway_growth: Vec<AirwayGrowthPoint>,
    /// Erosion depth at which touching lungs came apart, mm (None: they did not touch).
    pub separation_depth_mm: Option<f64>,
    /// Air components dropped (too small, or fragments of a lung), count.
    pub components_removed: usize,
    /// Their total volume, mL.
    pub components_removed_ml: f64,
    /// Body volume, mL.
    pub body_volume_ml: f64,
    /// Wall time of the whole segmentation, s.
    pub wall_time_s: f64,
    /// Wall time of each step, s.
    pub step_times_s: Vec<(String, f64)>,
    /// Anything a user should check.
    pub warnings: Vec<String>,
}

/// Result of [`segment_lungs`](super::segment_lungs): masks on the CT grid and the report.
#[derive(Debug, Clone)]
pub struct LungSegmentation {
    /// 0 background, [`RIGHT_LUNG`](super::RIGHT_LUNG) (1) patient's right, [`LEFT_LUNG`](super::LEFT_LUNG) (2) patient's left.
    pub lungs: Volume<u8>,
    /// 1 = trachea and main bronchi outside the lungs (from region growing), else 0.
    pub airways: Volume<u8>,
    /// 1 = inside the patient's body (outside air removed), else 0.
    pub body: Volume<u8>,
    /// Volumes, thresholds and decisions.
    pub report: SegmentationReport,
}

/// Step timer that records (name, seconds), and where a cancelled segmentation stops.
pub(super) struct Steps<'c> {
    last: Instant,
    pub times: Vec<(String, f64)>,
    /// The flag looked at after each step and inside the long ones.
    pub cancel: Cancel<'c>,
}

impl<'c> Steps<'c> {
    /// A timer whose first step starts at `start`, stopping when `cancel` is raised.
    pub fn new(start: Instant, cancel: Cancel<'c>) -> Self {
        Steps {
            last: start,
            times: Vec::new(),
            cancel,
        }
    }

    /// Records the time since the previous mark under `name`; [`crate::Error::Cancelled`]
    /// when the flag was raised meanwhile.
    pub fn mark(&mut self, name: &str) -> Result<()> {
        let now = Instant::now();
        self.times
            .push((name.into(), (now - self.last).as_secs_f64()));
        self.last = now;
        self.cancel.check("the lung segmentation")
    }
}
