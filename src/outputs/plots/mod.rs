//! Pictures a medical physicist checks at a glance: the breathing curve with the frames'
//! targets and simulated volumes, a coronal quick look of the displacement field, and a CT
//! slice labelled with a title, orientation letters and a legend of its overlay colours.
//!
//! Conventions. Images are 8-bit RGB ([`RgbImage`], rows top to bottom, written with
//! [`write_png`](crate::outputs::quicklook::write_png)); text uses the embedded font of
//! [`raster_text`](crate::outputs::raster_text), so no system font is needed. Continuous
//! pixel coordinates `[col, row]` put the centre of pixel (c, r) at (c, r).
//!
//! * Breathing curve: time (s) to the right, volume change (mL, relative to the CT's
//!   breathing state) upwards. The trace is a blue line, each frame's target volume an orange
//!   ring, each frame's simulated volume a red dot drawn on top (a dot centred in its ring is
//!   a frame that met its target).
//! * Displacement quick look: a coronal slice of the CT at a given LPS y, in lung window,
//!   with the radiological display convention of
//!   [`quicklook`](crate::outputs::quicklook) (patient's right on the image's left, superior
//!   at the top), the same pixel grid as
//!   [`render_slice`](crate::outputs::quicklook::render_slice) refined by an integer factor
//!   (each CT-slice pixel becomes a block). Inside the lungs the displacement magnitude
//!   |u| (mm, all three LPS components) is blended over the CT in the viridis colour map,
//!   with a colour bar in mm; arrows on a regular grid show the in-plane displacement (x to
//!   the image's right for +x = patient left, z upwards), magnified by a factor written in
//!   the image together with a reference arrow. The field is read per CT voxel (nearest
//!   voxel), as the pipeline samples it.

mod breathing_curve;
mod displacement_look;
mod draw;
mod line_chart;
mod scale;
mod slice_look;
mod trade_off;

pub use breathing_curve::{
    render_breathing_curve, BreathingCurve, BreathingCurvePlot, PlotAxes, CURVE_HEIGHT_PX,
    CURVE_WIDTH_PX,
};
pub use displacement_look::{
    lung_centroid_lps_mm, render_displacement_look, viridis, Arrow, DisplacementLook,
    DisplacementLookInput, SlicePanel,
};
pub use line_chart::{
    render_line_chart, ChartAxes, LineSeries, LINE_CHART_HEIGHT_PX, LINE_CHART_WIDTH_PX,
    SERIES_COLOURS,
};
pub use slice_look::{
    render_labelled_slice, LabelledSlice, LabelledSliceInput, LegendEntry, PixelRect,
};
pub use trade_off::{
    render_trade_off, TradeOffPoint, TradeOffSeries, TRADE_OFF_HEIGHT_PX, TRADE_OFF_WIDTH_PX,
};

/// Colour of the breathing trace line.
pub const TRACE_COLOUR: [u8; 3] = [31, 119, 180];
/// Colour of a frame's target-volume ring.
pub const TARGET_COLOUR: [u8; 3] = [255, 127, 14];
/// Colour of a frame's simulated-volume dot.
pub const SIMULATED_COLOUR: [u8; 3] = [214, 39, 40];
/// Colour of displacement arrows (over a black halo).
pub const ARROW_COLOUR: [u8; 3] = [255, 255, 255];
/// Weight of the magnitude colour over the CT grey inside the lungs.
pub const OVERLAY_OPACITY: f32 = 0.6;

const WHITE: [u8; 3] = [255, 255, 255];
const BLACK: [u8; 3] = [0, 0, 0];
const GRID_GREY: [u8; 3] = [225, 225, 225];
const FRAME_GREY: [u8; 3] = [120, 120, 120];
/// Text scale of every label (the 5×7 font doubled: 14 px high).
const TEXT_SCALE: usize = 2;

/// Outer and inner radius of a target ring, pixels.
const RING_RADII_PX: (f64, f64) = (7.0, 4.5);
/// Radius of a simulated-volume dot, pixels.
const DOT_RADIUS_PX: f64 = 3.5;
