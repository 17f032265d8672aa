//! The run's quick looks: `breathing.png` and the displacement at a breathing extreme
//! (`end-inhale-displacement.png`, or `deepest-expiration-displacement.png` for a trace that
//! never rises above the scanned volume).

use std::borrow::Cow;
use std::path::Path;

use super::frames::FramesWritten;
use super::RunInputs;
use crate::motion::FrameSummary;
use crate::outputs::displacement_field::FieldSampler;
use crate::volume::Volume;
use crate::Result;

/// `breathing.png` (trace, targets, simulated volumes) and `<extreme>-displacement.png`
/// (coronal slice through the first tracked point, else the lungs' centroid), the latter only
/// when the trace leaves the scanned volume.
pub(super) fn write_quicklooks(
    dir: &Path,
    inputs: &RunInputs,
    backdrop: &LookBackdrop,
    field: &FieldSampler,
    mesh: &crate::model::HexMesh,
    written: &mut FramesWritten,
) -> Result<()> {
    let (records, pictured) = (&written.records, written.pictured.as_ref());
    use crate::outputs::plots::{
        lung_centroid_lps_mm, render_breathing_curve, render_displacement_look, BreathingCurve,
        DisplacementLookInput,
    };
    use crate::outputs::quicklook::write_png;
    let column = |f: fn(&FrameSummary) -> f64| -> Vec<f64> {
        records.iter().map(|r| f(&r.summary)).collect()
    };
    let frame_time_s: Vec<f64> = column(|f| f.time_s);
    let frame_target_ml: Vec<f64> = column(|f| f.target_volume_ml);
    let frame_simulated_ml: Vec<f64> = column(|f| f.simulated_volume_ml);
    let plot = render_breathing_curve(&BreathingCurve {
        trace_time_s: &inputs.trace.time_s,
        trace_volume_ml: &inputs.trace.volume_change_ml,
        frame_time_s: &frame_time_s,
        frame_target_ml: &frame_target_ml,
        frame_simulated_ml: &frame_simulated_ml,
        title: "Breathing trace (line), frame targets (rings) and simulated volumes (dots)",
    })?;
    write_png(&dir.join("breathing.png"), &plot.image)?;
    let Some(pictured) = pictured else {
        return Ok(());
    };
    let (ct, lungs) = (&backdrop.ct, &backdrop.lungs);
    let (coronal_y_mm, through) = match inputs.points.first() {
        Some(p) => (p.rest_lps_mm[1], p.name.clone()),
        None => (
            lung_centroid_lps_mm(lungs).map_or(ct.geometry.origin_lps_mm[1], |c| c[1]),
            "the lungs' centroid".to_string(),
        ),
    };
    let f = &records[pictured.frame].summary;
    let mut title = format!(
        "{} (frame {}, t = {:.2} s, {:+.0} mL): displacement, coronal slice through {}",
        pictured.kind.label(),
        f.index,
        f.time_s,
        f.simulated_volume_ml,
        through
    );
    title[..1].make_ascii_uppercase();
    // The frames' buffer: zero outside the lungs already.
    let field_mm = &mut written.field_buffer_mm;
    field.sample_lung_voxels_mm(mesh, &pictured.positions_m, field_mm);
    let look = render_displacement_look(&DisplacementLookInput {
        ct,
        lungs,
        displacement_mm: field_mm,
        coronal_y_mm,
        colour_max_mm: None,
        title: &title,
    })?;
    let name = format!("{}-displacement.png", pictured.kind.file_stem());
    write_png(&dir.join(name), &look.image)
}

/// The CT and lung labels the displacement quick look is drawn over, on the field's own grid
/// (the lung box by default): cut out once the lung scene is built, so the run can let the
/// whole CT go before its solves.
pub(super) struct LookBackdrop {
    ct: Volume<f32>,
    lungs: Volume<u8>,
}

impl LookBackdrop {
    /// `ct` and `lungs` on the grid of `field`; a CT on that grid already is moved, not copied.
    pub(super) fn of(
        ct: Cow<Volume<f32>>,
        lungs: &Volume<u8>,
        field: &FieldSampler,
    ) -> Result<Self> {
        let (start, dims) = (field.start(), field.geometry().dims);
        let ct = if dims == ct.geometry.dims {
            ct.into_owned()
        } else {
            ct.crop(start, dims)?
        };
        Ok(LookBackdrop {
            ct,
            lungs: lungs.crop(start, dims)?,
        })
    }
}
