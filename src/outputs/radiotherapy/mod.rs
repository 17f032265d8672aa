//! What a radiotherapy team loads besides the displacement fields: the CT at each breathing
//! phase (virtual 4D-CT), the target's motion and internal target volume, and the DICOM
//! objects (CT series, RTSTRUCT, spatial registrations) a planning system and a PACS accept.

pub mod ct_motion;
pub mod mesh_motion;
pub mod registration;
pub mod virtual_ct;

/// The motion of one output instant over the whole CT grid, both ways, in LPS millimetres:
/// what the virtual CT, the warped target and the spatial registrations are made from, so
/// that all of them agree with each other.
pub trait PhaseMotion: Sync {
    /// Where the tissue at `rest_lps_mm` in the planning CT is at this instant.
    fn moved_lps_mm(&self, rest_lps_mm: [f64; 3]) -> [f64; 3];
    /// Where the tissue found at `moved_lps_mm` at this instant was in the planning CT (the
    /// inverse map, which an image resampler needs).
    fn source_lps_mm(&self, moved_lps_mm: [f64; 3]) -> [f64; 3];
}

pub mod contours;
pub mod rtstruct;
pub mod target;
pub mod target_motion;
