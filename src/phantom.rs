//! The procedural thorax phantom: a CT of an adult chest drawn from analytic shapes, together
//! with the exact tissue labels it was drawn from, so the README and every test run on a fresh
//! machine without third-party scans.
//!
//! # Convention
//!
//! * Space: DICOM patient space, LPS millimetres (+x patient left, +y posterior, +z superior),
//!   identity direction, origin the centre of voxel (0, 0, 0), voxels i-fastest, as every
//!   [`Volume`] of the crate.
//! * Anatomical frame: the body axis is the line x = 0, y = 0; the carina sits at
//!   [`CARINA_LPS_MM`] (z = 0); the lungs span z ≈ −155 mm (posterior costophrenic recess) to
//!   ≈ +95 mm (apex). The field of view ([`PhantomSettings::field_of_view_mm`] around
//!   [`PhantomSettings::field_of_view_centre_lps_mm`]) only crops this fixed anatomy.
//! * CT values: Hounsfield units, rounded to whole numbers and clamped to −1024…3071 as a
//!   scanner stores them (so an int16 writer loses nothing).
//! * Truth labels: the [`Tissue`] codes, taken at each voxel centre from the same signed
//!   distances that draw the CT, so they are exact; vessels inside the lungs keep the lung label.
//! * Partial volume: each structure's occupancy of a voxel ramps linearly over one voxel of its
//!   signed distance, and structures are composited in a fixed order (later ones cover earlier
//!   ones), so a voxel's label is the last structure whose boundary it is inside.
//! * Noise: a hash of (seed, voxel index), approximately Gaussian with standard deviation
//!   `noise_hu`; the same settings give bit-identical volumes on any number of threads.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::volume::{Volume, VolumeGeometry, MAX_SPACING_MM, MIN_SPACING_MM};
use crate::{Error, IoContext, IoOp, Result};

/// CT number of outside air and airway lumen.
pub const AIR_HU: f32 = -1000.0;
/// CT number of inflated lung parenchyma.
pub const LUNG_HU: f32 = -850.0;
/// CT number of the subcutaneous fat layer.
pub const FAT_HU: f32 = -100.0;
/// CT number of chest-wall muscle and neck soft tissue.
pub const MUSCLE_HU: f32 = 40.0;
/// CT number of the mediastinal tissue around the heart and great vessels.
pub const MEDIASTINUM_HU: f32 = 35.0;
/// CT number of unenhanced blood (heart chambers, aorta).
pub const BLOOD_HU: f32 = 45.0;
/// CT number of the pulmonary vessels inside the lungs.
pub const VESSEL_HU: f32 = 40.0;
/// CT number of the liver and abdomen below the diaphragm.
pub const LIVER_HU: f32 = 60.0;
/// CT number of bone (ribs, vertebrae, sternum).
pub const BONE_HU: f32 = 700.0;
/// CT number of the tumour.
pub const TUMOUR_HU: f32 = 30.0;
/// CT number of the intervertebral discs.
pub const DISC_HU: f32 = 80.0;
/// CT number of the spinal cord in its canal.
pub const CORD_HU: f32 = 20.0;
/// Lowest CT number a scanner stores.
pub const MIN_STORED_HU: f32 = -1024.0;
/// Highest CT number a 12-bit scanner stores.
pub const MAX_STORED_HU: f32 = 3071.0;

/// LPS position of the carina (tracheal bifurcation), in millimetres.
pub const CARINA_LPS_MM: [f64; 3] = [0.0, 22.0, 0.0];

/// Largest phantom grid accepted, so a typo in the spacing cannot exhaust memory.
pub const MAX_PHANTOM_VOXELS: usize = 128 << 20;
/// Largest field of view accepted along one axis, in millimetres.
pub const MAX_FIELD_OF_VIEW_MM: f64 = 2000.0;

/// Tissue label codes of [`Phantom::truth`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u8)]
pub enum Tissue {
    /// Air outside the body.
    OutsideAir = 0,
    /// Right lung parenchyma (patient right, negative LPS x), vessels included.
    RightLung = 1,
    /// Left lung parenchyma (patient left, positive LPS x), vessels included.
    LeftLung = 2,
    /// Airway lumen: trachea and bronchi.
    Airway = 3,
    /// Body soft tissue: fat, muscle, neck, discs, spinal cord.
    SoftTissue = 4,
    /// Bone: ribs, vertebrae, sternum.
    Bone = 5,
    /// Mediastinum, heart and great vessels.
    Mediastinum = 6,
    /// Liver and abdomen below the diaphragm.
    Abdomen = 7,
    /// The tumour.
    Tumour = 8,
}

impl Tissue {
    /// Every label, in code order.
    pub const ALL: [Tissue; 9] = [
        Tissue::OutsideAir,
        Tissue::RightLung,
        Tissue::LeftLung,
        Tissue::Airway,
        Tissue::SoftTissue,
        Tissue::Bone,
        Tissue::Mediastinum,
        Tissue::Abdomen,
        Tissue::Tumour,
    ];

    /// The code stored in the label volume.
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The label with this code, if any.
    pub fn from_code(code: u8) -> Option<Tissue> {
        Tissue::ALL.get(code as usize).copied()
    }

    /// Short snake_case name, as written in descriptions.
    pub fn name(self) -> &'static str {
        match self {
            Tissue::OutsideAir => "outside_air",
            Tissue::RightLung => "right_lung",
            Tissue::LeftLung => "left_lung",
            Tissue::Airway => "airway",
            Tissue::SoftTissue => "soft_tissue",
            Tissue::Bone => "bone",
            Tissue::Mediastinum => "mediastinum",
            Tissue::Abdomen => "abdomen",
            Tissue::Tumour => "tumour",
        }
    }
}

/// A spherical tumour.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tumour {
    /// LPS position of the centre, in millimetres.
    pub centre_lps_mm: [f64; 3],
    /// Radius in millimetres.
    pub radius_mm: f64,
}

/// What to generate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhantomSettings {
    /// Voxel spacing along x, y, z in millimetres.
    pub spacing_mm: [f64; 3],
    /// Extent of the grid along x, y, z in millimetres; the grid has
    /// `round(field_of_view_mm / spacing_mm)` voxels per axis.
    pub field_of_view_mm: [f64; 3],
    /// LPS position of the centre of the grid, in millimetres.
    pub field_of_view_centre_lps_mm: [f64; 3],
    /// The tumour, if any.
    pub tumour: Option<Tumour>,
    /// Standard deviation of the CT noise in HU (0 for a noiseless volume).
    pub noise_hu: f32,
    /// Seed of the noise; it changes nothing else.
    pub seed: u64,
}

impl Default for PhantomSettings {
    /// 5 mm voxels over the whole chest (76 × 56 × 68 ≈ 289 000 voxels) with a 15 mm tumour in
    /// the right lower lobe just above the diaphragm, where breathing moves it most.
    fn default() -> Self {
        PhantomSettings {
            spacing_mm: [5.0; 3],
            field_of_view_mm: [380.0, 280.0, 340.0],
            field_of_view_centre_lps_mm: [0.0, 0.0, -30.0],
            tumour: Some(Tumour {
                centre_lps_mm: [-95.0, 20.0, -80.0],
                radius_mm: 15.0,
            }),
            noise_hu: 20.0,
            seed: 1,
        }
    }
}

/// Anatomical landmarks, LPS millimetres, from the analytic shapes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhantomLandmarks {
    /// The tracheal bifurcation.
    pub carina_lps_mm: [f64; 3],
    /// Centre of the tumour, if there is one.
    pub tumour_centre_lps_mm: Option<[f64; 3]>,
    /// Highest point of the right lung.
    pub right_lung_apex_lps_mm: [f64; 3],
    /// Top of the right diaphragm dome, under the right lung base.
    pub right_lung_base_lps_mm: [f64; 3],
    /// Highest point of the left lung.
    pub left_lung_apex_lps_mm: [f64; 3],
    /// Top of the left diaphragm dome, under the left lung base.
    pub left_lung_base_lps_mm: [f64; 3],
}

/// Number of voxels of one label.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LabelCount {
    /// Label code in [`Phantom::truth`].
    pub code: u8,
    /// Label name ([`Tissue::name`]).
    pub name: String,
    /// Voxels carrying the label.
    pub voxels: usize,
}

/// What was generated, for tests, docs and the JSON written beside the volumes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhantomDescription {
    /// The settings the phantom was generated with.
    pub settings: PhantomSettings,
    /// The grid of both volumes.
    pub geometry: VolumeGeometry,
    /// Voxel count of every label, in code order.
    pub label_counts: Vec<LabelCount>,
    /// Volume of the right lung label, in millilitres.
    pub right_lung_volume_ml: f64,
    /// Volume of the left lung label, in millilitres.
    pub left_lung_volume_ml: f64,
    /// Anatomical landmarks.
    pub landmarks: PhantomLandmarks,
}

/// A generated phantom: CT, exact labels and description.
#[derive(Debug, Clone, PartialEq)]
pub struct Phantom {
    /// CT numbers in HU.
    pub ct: Volume<f32>,
    /// [`Tissue`] codes on the same grid.
    pub truth: Volume<u8>,
    /// Settings, label counts, lung volumes and landmarks.
    pub description: PhantomDescription,
}

/// Generates the thorax phantom: one parallel pass over the voxels evaluating analytic shapes.
pub fn generate_thorax_phantom(settings: &PhantomSettings) -> Result<Phantom> {
    generate_breathing_phantom(settings, &BreathingMotion::REST)
}

/// Generates the thorax phantom at the breathing state `motion`: every shape is drawn where
/// the analytic field moves it (each voxel evaluates the anatomy at its source point
/// [`BreathingMotion::source_lps_mm`]), and the landmarks are their moved positions. With
/// [`BreathingMotion::REST`] it is [`generate_thorax_phantom`].
pub fn generate_breathing_phantom(
    settings: &PhantomSettings,
    motion: &BreathingMotion,
) -> Result<Phantom> {
    motion.validate()?;
    let geometry = phantom_geometry(settings)?;
    let [nx, ny, nz] = geometry.dims;
    let slice_len = nx * ny;
    let mut ct = vec![0.0f32; geometry.voxel_count()];
    let mut truth = vec![0u8; geometry.voxel_count()];
    let blend_width_mm = geometry.voxel_volume_mm3().cbrt();
    let anatomy = Anatomy::new(settings.tumour, blend_width_mm);
    let noise = NoiseSource {
        seed: settings.seed,
        sigma_hu: settings.noise_hu,
    };
    let [ox, oy, oz] = geometry.origin_lps_mm;
    let [sx, sy, sz] = geometry.spacing_mm;
    ct.par_chunks_mut(slice_len)
        .zip(truth.par_chunks_mut(slice_len))
        .enumerate()
        .for_each(|(k, (ct_slice, truth_slice))| {
            let z = oz + k as f64 * sz;
            for j in 0..ny {
                let y = oy + j as f64 * sy;
                for i in 0..nx {
                    let x = ox + i as f64 * sx;
                    let (hu, label) = anatomy.evaluate(motion.source_lps_mm([x, y, z]));
                    let index = i + nx * j;
                    let noisy = hu + noise.sample_hu((k * slice_len + index) as u64);
                    ct_slice[index] = noisy.round().clamp(MIN_STORED_HU, MAX_STORED_HU);
                    truth_slice[index] = label.code();
                }
            }
        });
    debug_assert_eq!(ct.len(), slice_len * nz);

    let mut counts = [0usize; Tissue::ALL.len()];
    for &code in &truth {
        counts[code as usize] += 1;
    }
    let voxel_ml = geometry.voxel_volume_mm3() / 1000.0;
    let description = PhantomDescription {
        settings: settings.clone(),
        geometry,
        label_counts: Tissue::ALL
            .iter()
            .map(|&t| LabelCount {
                code: t.code(),
                name: t.name().to_string(),
                voxels: counts[t.code() as usize],
            })
            .collect(),
        right_lung_volume_ml: counts[Tissue::RightLung as usize] as f64 * voxel_ml,
        left_lung_volume_ml: counts[Tissue::LeftLung as usize] as f64 * voxel_ml,
        landmarks: anatomy.landmarks().moved(motion),
    };
    Ok(Phantom {
        ct: Volume::from_data(geometry, ct)?,
        truth: Volume::from_data(geometry, truth)?,
        description,
    })
}

/// The grid of the phantom, after checking the settings.
fn phantom_geometry(settings: &PhantomSettings) -> Result<VolumeGeometry> {
    let bad = |key: &str, reason: String| {
        Err(Error::Config {
            settings: "phantom settings",
            file: None,
            key: Some(key.to_string()),
            reason,
        })
    };
    let mut dims = [0usize; 3];
    for (axis, n) in dims.iter_mut().enumerate() {
        let spacing = settings.spacing_mm[axis];
        let fov = settings.field_of_view_mm[axis];
        if !spacing.is_finite() || !(MIN_SPACING_MM..=MAX_SPACING_MM).contains(&spacing) {
            return bad(
                "spacing_mm",
                format!(
                    "spacing along axis {axis} is {spacing} mm; it must lie in \
                 {MIN_SPACING_MM}–{MAX_SPACING_MM} mm"
                ),
            );
        }
        if !fov.is_finite() || fov <= 0.0 || fov > MAX_FIELD_OF_VIEW_MM {
            return bad(
                "field_of_view_mm",
                format!(
                    "field of view along axis {axis} is {fov} mm; it must lie in \
                 (0, {MAX_FIELD_OF_VIEW_MM}] mm"
                ),
            );
        }
        *n = ((fov / spacing).round() as usize).max(1);
    }
    let voxels = dims.iter().product::<usize>();
    if voxels > MAX_PHANTOM_VOXELS {
        return bad(
            "field_of_view_mm",
            format!("grid {dims:?} has {voxels} voxels, more than {MAX_PHANTOM_VOXELS}"),
        );
    }
    if settings
        .field_of_view_centre_lps_mm
        .iter()
        .any(|v| !v.is_finite() || v.abs() > 1e5)
    {
        return bad(
            "field_of_view_centre_lps_mm",
            format!(
                "field of view centre {:?} mm is not a finite position",
                settings.field_of_view_centre_lps_mm
            ),
        );
    }
    if !settings.noise_hu.is_finite() || !(0.0..=1000.0).contains(&settings.noise_hu) {
        return bad(
            "noise_hu",
            format!(
                "noise of {} HU; it must lie in 0–1000 HU",
                settings.noise_hu
            ),
        );
    }
    if let Some(t) = settings.tumour {
        if !t.radius_mm.is_finite() || t.radius_mm <= 0.0 || t.radius_mm > 150.0 {
            return bad(
                "tumour.radius_mm",
                format!(
                    "tumour radius of {} mm; it must lie in (0, 150] mm",
                    t.radius_mm
                ),
            );
        }
        if t.centre_lps_mm
            .iter()
            .any(|v| !v.is_finite() || v.abs() > 1e5)
        {
            return bad(
                "tumour.centre_lps_mm",
                format!(
                    "tumour centre {:?} mm is not a finite position",
                    t.centre_lps_mm
                ),
            );
        }
    }
    let origin = std::array::from_fn(|a| {
        settings.field_of_view_centre_lps_mm[a]
            - 0.5 * (dims[a] - 1) as f64 * settings.spacing_mm[a]
    });
    let geometry = VolumeGeometry::axis_aligned(dims, settings.spacing_mm, origin);
    geometry.validate("phantom grid")?;
    Ok(geometry)
}

/// Deterministic, approximately Gaussian CT noise keyed by voxel index.
struct NoiseSource {
    seed: u64,
    sigma_hu: f32,
}

impl NoiseSource {
    /// Noise of one voxel: the sum of four uniform 16-bit draws (Irwin–Hall), scaled to `sigma_hu`.
    #[inline]
    fn sample_hu(&self, voxel_index: u64) -> f32 {
        if self.sigma_hu == 0.0 {
            return 0.0;
        }
        let h = splitmix64(self.seed ^ splitmix64(voxel_index));
        let sum: u32 = (0..4).map(|q| ((h >> (16 * q)) & 0xffff) as u32).sum();
        // Four U(0,1) sum to mean 2, variance 1/3.
        let standard = (sum as f32 / 65536.0 - 2.0) * 3.0f32.sqrt();
        standard * self.sigma_hu
    }
}

/// SplitMix64 finaliser: a fast, well-mixed 64-bit hash.
#[inline]
fn splitmix64(v: u64) -> u64 {
    let mut z = v.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

type P3 = [f64; 3];

/// A straight tube whose radius varies linearly from `start` to `end`.
#[derive(Debug, Clone, Copy)]
struct Tube {
    start: P3,
    end: P3,
    start_radius_mm: f64,
    end_radius_mm: f64,
}

impl Tube {
    const fn new(start: P3, end: P3, start_radius_mm: f64, end_radius_mm: f64) -> Tube {
        Tube {
            start,
            end,
            start_radius_mm,
            end_radius_mm,
        }
    }

    /// Signed distance (mm, negative inside), exact for a constant radius.
    #[inline]
    fn distance_mm(&self, p: P3) -> f64 {
        let ab = sub(self.end, self.start);
        let ap = sub(p, self.start);
        let t = (dot(ap, ab) / dot(ab, ab)).clamp(0.0, 1.0);
        let closest = [
            self.start[0] + t * ab[0],
            self.start[1] + t * ab[1],
            self.start[2] + t * ab[2],
        ];
        let radius = self.start_radius_mm + t * (self.end_radius_mm - self.start_radius_mm);
        norm(sub(p, closest)) - radius
    }

    /// The same tube with its radius grown by `margin_mm` (a wall around a lumen).
    const fn widened(&self, margin_mm: f64) -> Tube {
        Tube::new(
            self.start,
            self.end,
            self.start_radius_mm + margin_mm,
            self.end_radius_mm + margin_mm,
        )
    }
}

/// One lung's own shape: an elliptic cylinder topped by a half ellipsoid (the apex), later cut
/// by the thoracic cavity, the diaphragm and the mediastinum.
#[derive(Debug, Clone, Copy)]
struct LungEnvelope {
    centre: P3,
    semi_axes_mm: P3,
}

impl LungEnvelope {
    #[inline]
    fn distance_mm(&self, p: P3) -> f64 {
        let d = sub(p, self.centre);
        if d[2] <= 0.0 {
            ellipse_distance_mm(d[0], d[1], self.semi_axes_mm[0], self.semi_axes_mm[1])
        } else {
            ellipsoid_distance_mm(d, self.semi_axes_mm)
        }
    }

    fn apex(&self) -> P3 {
        [
            self.centre[0],
            self.centre[1],
            self.centre[2] + self.semi_axes_mm[2],
        ]
    }
}

/// One diaphragm dome: a downward paraboloid `z = peak − depth·(u² + v²)`.
#[derive(Debug, Clone, Copy)]
struct Dome {
    peak: P3,
    depth_mm: f64,
    reach_mm: [f64; 2],
}

impl Dome {
    /// Height of the dome surface above (x, y) and its slope.
    #[inline]
    fn height_and_slope(&self, x: f64, y: f64) -> (f64, [f64; 2]) {
        let u = (x - self.peak[0]) / self.reach_mm[0];
        let v = (y - self.peak[1]) / self.reach_mm[1];
        let z = self.peak[2] - self.depth_mm * (u * u + v * v);
        let slope = [
            -2.0 * self.depth_mm * u / self.reach_mm[0],
            -2.0 * self.depth_mm * v / self.reach_mm[1],
        ];
        (z, slope)
    }
}

const BODY_SEMI_AXES_MM: [f64; 2] = [170.0, 120.0];
const FAT_THICKNESS_MM: f64 = 14.0;
/// The thoracic cavity (inner surface of the rib cage): an ellipse centred slightly posterior.
const CAVITY_CENTRE_Y_MM: f64 = 5.0;
const CAVITY_SEMI_AXES_MM: [f64; 2] = [135.0, 100.0];
/// Above this height the cavity narrows towards the thoracic inlet.
const CAVITY_TAPER_START_Z_MM: f64 = 20.0;
/// Height of the thoracic inlet (top of the cavity); above it is neck.
const THORACIC_INLET_Z_MM: f64 = 115.0;
const CAVITY_INLET_SCALE: f64 = 0.6;
/// Half-width of the central mediastinal column between the lungs.
const MEDIASTINUM_HALF_WIDTH_MM: f64 = 24.0;
const RIB_COUNT: usize = 11;
const TOP_RIB_POSTERIOR_Z_MM: f64 = 105.0;
const RIB_PITCH_MM: f64 = 27.0;
/// Ribs descend anteriorly: z drop per mm towards anterior.
const RIB_SLOPE: f64 = 0.25;
const RIB_OFFSET_OUTSIDE_CAVITY_MM: f64 = 8.0;
const RIB_SEMI_AXES_MM: [f64; 2] = [5.0, 6.0];
/// Ribs stop this close to the midline (spine behind, costal cartilage in front).
const RIB_MEDIAL_LIMIT_MM: f64 = 26.0;
/// The last two ribs float: they stop before this anterior y.
const FLOATING_RIB_ANTERIOR_LIMIT_Y_MM: f64 = -30.0;
const VERTEBRA_CENTRE_Y_MM: f64 = 62.0;
const VERTEBRA_RADIUS_MM: f64 = 18.0;
const VERTEBRA_PITCH_MM: f64 = 28.0;
const DISC_THICKNESS_MM: f64 = 6.0;
const CANAL_CENTRE_Y_MM: f64 = 90.0;
const CANAL_RADIUS_MM: f64 = 8.0;
const NEURAL_ARCH_OUTER_RADIUS_MM: f64 = 13.0;
const TRACHEA_RADIUS_MM: f64 = 9.0;
const AIRWAY_WALL_MM: f64 = 3.0;

/// The trachea runs from above any field of view down to the carina.
const TRACHEA: Tube = Tube::new(
    [0.0, 0.0, 400.0],
    CARINA_LPS_MM,
    TRACHEA_RADIUS_MM,
    TRACHEA_RADIUS_MM,
);
const RIGHT_HILUM: P3 = [-42.0, 24.0, -30.0];
const LEFT_HILUM: P3 = [48.0, 26.0, -35.0];
const RIGHT_INTERMEDIATE: P3 = [-55.0, 28.0, -55.0];
const MAIN_BRONCHI: [Tube; 2] = [
    Tube::new(CARINA_LPS_MM, RIGHT_HILUM, 7.5, 7.0),
    Tube::new(CARINA_LPS_MM, LEFT_HILUM, 6.5, 6.0),
];
const LOBAR_BRONCHI: [Tube; 6] = [
    Tube::new(RIGHT_HILUM, [-72.0, 20.0, 15.0], 5.0, 4.0),
    Tube::new(RIGHT_HILUM, RIGHT_INTERMEDIATE, 6.0, 5.5),
    Tube::new(RIGHT_INTERMEDIATE, [-78.0, -20.0, -65.0], 4.5, 3.5),
    Tube::new(RIGHT_INTERMEDIATE, [-75.0, 50.0, -100.0], 5.0, 4.0),
    Tube::new(LEFT_HILUM, [75.0, 5.0, 10.0], 5.0, 4.0),
    Tube::new(LEFT_HILUM, [70.0, 50.0, -95.0], 5.0, 4.0),
];
const GREAT_VESSELS: [Tube; 4] = [
    // Descending aorta beside the spine, the arch over the left main bronchus, the ascending aorta.
    Tube::new([26.0, 40.0, -400.0], [26.0, 40.0, 35.0], 12.0, 12.0),
    Tube::new([26.0, 40.0, 35.0], [12.0, 5.0, 52.0], 12.0, 13.0),
    Tube::new([12.0, 5.0, 52.0], [2.0, -30.0, 35.0], 13.0, 14.0),
    Tube::new([2.0, -30.0, 35.0], [8.0, -38.0, -35.0], 14.0, 14.0),
];
const HEART_CENTRE: P3 = [18.0, -28.0, -82.0];
const HEART_SEMI_AXES_MM: P3 = [62.0, 52.0, 56.0];
const UPPER_MEDIASTINUM_CENTRE: P3 = [4.0, 0.0, 35.0];
const UPPER_MEDIASTINUM_SEMI_AXES_MM: P3 = [40.0, 50.0, 60.0];
const STERNUM_CENTRE: P3 = [0.0, -100.0, -25.0];
const STERNUM_HALF_EXTENTS_MM: P3 = [16.0, 6.0, 95.0];
const STERNUM_ROUNDING_MM: f64 = 3.0;
const RIGHT_LUNG: LungEnvelope = LungEnvelope {
    centre: [-68.0, 10.0, -45.0],
    semi_axes_mm: [85.0, 115.0, 140.0],
};
const LEFT_LUNG: LungEnvelope = LungEnvelope {
    centre: [68.0, 10.0, -48.0],
    semi_axes_mm: [85.0, 115.0, 138.0],
};
/// The right dome stands higher than the left (the liver pushes it up).
const RIGHT_DOME: Dome = Dome {
    peak: [-65.0, -10.0, -95.0],
    depth_mm: 50.0,
    reach_mm: [85.0, 105.0],
};
const LEFT_DOME: Dome = Dome {
    peak: [75.0, 10.0, -108.0],
    depth_mm: 50.0,
    reach_mm: [85.0, 105.0],
};
const HILUM_VESSEL_ROOT_RIGHT: P3 = [-38.0, 10.0, -25.0];
const HILUM_VESSEL_ROOT_LEFT: P3 = [45.0, 12.0, -30.0];
const RIGHT_VESSELS: [Tube; 6] = [
    Tube::new(HILUM_VESSEL_ROOT_RIGHT, [-80.0, -5.0, 55.0], 4.0, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_RIGHT, [-110.0, 30.0, 10.0], 3.5, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_RIGHT, [-95.0, -55.0, -50.0], 3.5, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_RIGHT, [-95.0, 60.0, -115.0], 4.0, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_RIGHT, [-120.0, 0.0, -100.0], 3.0, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_RIGHT, [-50.0, 75.0, -80.0], 3.0, 1.5),
];
const LEFT_VESSELS: [Tube; 5] = [
    Tube::new(HILUM_VESSEL_ROOT_LEFT, [80.0, -5.0, 55.0], 4.0, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_LEFT, [110.0, 30.0, 0.0], 3.5, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_LEFT, [100.0, 60.0, -120.0], 4.0, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_LEFT, [115.0, -10.0, -95.0], 3.0, 1.5),
    Tube::new(HILUM_VESSEL_ROOT_LEFT, [60.0, 80.0, -70.0], 3.0, 1.5),
];

/// The fixed anatomy plus the per-call parts (tumour, blend width).
struct Anatomy {
    tumour: Option<Tumour>,
    blend_width_mm: f64,
}

/// Running composite of one voxel: later structures cover earlier ones by their occupancy.
struct Canvas {
    hu: f32,
    label: Tissue,
    blend_width_mm: f64,
}

impl Canvas {
    /// Occupancy of the voxel by a structure at signed distance `d_mm` (½ on the boundary).
    #[inline]
    fn occupancy(&self, d_mm: f64) -> f32 {
        (0.5 - d_mm / self.blend_width_mm).clamp(0.0, 1.0) as f32
    }

    /// Covers the voxel with a structure; the label follows the voxel centre.
    #[inline]
    fn paint(&mut self, d_mm: f64, hu: f32, label: Tissue) {
        let a = self.occupancy(d_mm);
        self.hu += a * (hu - self.hu);
        if d_mm < 0.0 {
            self.label = label;
        }
    }

    /// Covers the voxel by `fraction` of a structure without changing its label.
    #[inline]
    fn tint(&mut self, fraction: f32, hu: f32) {
        self.hu += fraction * (hu - self.hu);
    }
}

impl Anatomy {
    fn new(tumour: Option<Tumour>, blend_width_mm: f64) -> Anatomy {
        Anatomy {
            tumour,
            blend_width_mm,
        }
    }

    fn landmarks(&self) -> PhantomLandmarks {
        PhantomLandmarks {
            carina_lps_mm: CARINA_LPS_MM,
            tumour_centre_lps_mm: self.tumour.map(|t| t.centre_lps_mm),
            right_lung_apex_lps_mm: RIGHT_LUNG.apex(),
            right_lung_base_lps_mm: RIGHT_DOME.peak,
            left_lung_apex_lps_mm: LEFT_LUNG.apex(),
            left_lung_base_lps_mm: LEFT_DOME.peak,
        }
    }

    /// HU before noise and the label at LPS point `p`.
    fn evaluate(&self, p: P3) -> (f32, Tissue) {
        let [x, y, z] = p;
        let mut c = Canvas {
            hu: AIR_HU,
            label: Tissue::OutsideAir,
            blend_width_mm: self.blend_width_mm,
        };
        let body = ellipse_distance_mm(x, y, BODY_SEMI_AXES_MM[0], BODY_SEMI_AXES_MM[1]);
        if body > self.blend_width_mm {
            return (c.hu, c.label);
        }
        c.paint(body, FAT_HU, Tissue::SoftTissue);
        let muscle = ellipse_distance_mm(
            x,
            y,
            BODY_SEMI_AXES_MM[0] - FAT_THICKNESS_MM,
            BODY_SEMI_AXES_MM[1] - FAT_THICKNESS_MM,
        );
        c.paint(muscle, MUSCLE_HU, Tissue::SoftTissue);

        let cavity_wall = cavity_wall_distance_mm(x, y, z);
        let cavity = cavity_wall.max(z - THORACIC_INLET_Z_MM);
        let below_diaphragm = below_diaphragm_distance_mm(x, y, z);
        let above_diaphragm = -below_diaphragm;
        c.paint(cavity.max(below_diaphragm), LIVER_HU, Tissue::Abdomen);

        let great_vessels = GREAT_VESSELS
            .iter()
            .fold(f64::INFINITY, |d, t| d.min(t.distance_mm(p)));
        let heart = ellipsoid_distance_mm(sub(p, HEART_CENTRE), HEART_SEMI_AXES_MM);
        let blood = heart.min(great_vessels);
        let airway_walls = MAIN_BRONCHI
            .iter()
            .fold(TRACHEA.widened(AIRWAY_WALL_MM).distance_mm(p), |d, t| {
                d.min(t.widened(AIRWAY_WALL_MM).distance_mm(p))
            });
        let mediastinum_shape = (x.abs() - MEDIASTINUM_HALF_WIDTH_MM)
            .min(ellipsoid_distance_mm(
                sub(p, UPPER_MEDIASTINUM_CENTRE),
                UPPER_MEDIASTINUM_SEMI_AXES_MM,
            ))
            .min(blood)
            .min(airway_walls);
        let thorax = cavity.max(above_diaphragm);
        c.paint(
            thorax.max(mediastinum_shape),
            MEDIASTINUM_HU,
            Tissue::Mediastinum,
        );
        c.paint(thorax.max(blood), BLOOD_HU, Tissue::Mediastinum);

        let lung_space = thorax.max(-mediastinum_shape);
        let right = lung_space.max(RIGHT_LUNG.distance_mm(p)).max(x);
        let left = lung_space.max(LEFT_LUNG.distance_mm(p)).max(-x);
        c.paint(right, LUNG_HU, Tissue::RightLung);
        c.paint(left, LUNG_HU, Tissue::LeftLung);
        // Vessels only exist inside the lung, and keep its label (the lung mask includes them).
        for (lung, vessels) in [(right, &RIGHT_VESSELS[..]), (left, &LEFT_VESSELS[..])] {
            if lung < self.blend_width_mm {
                let vessel = vessels
                    .iter()
                    .fold(f64::INFINITY, |d, t| d.min(t.distance_mm(p)));
                c.tint(c.occupancy(vessel) * c.occupancy(lung), VESSEL_HU);
            }
        }

        if let Some(t) = self.tumour {
            c.paint(
                norm(sub(p, t.centre_lps_mm)) - t.radius_mm,
                TUMOUR_HU,
                Tissue::Tumour,
            );
        }

        let lumen = MAIN_BRONCHI
            .iter()
            .chain(LOBAR_BRONCHI.iter())
            .fold(TRACHEA.distance_mm(p), |d, t| d.min(t.distance_mm(p)));
        c.paint(lumen, AIR_HU, Tissue::Airway);

        let column = (x * x + (y - VERTEBRA_CENTRE_Y_MM).powi(2)).sqrt() - VERTEBRA_RADIUS_MM;
        c.paint(column, DISC_HU, Tissue::SoftTissue);
        let canal_radius = (x * x + (y - CANAL_CENTRE_Y_MM).powi(2)).sqrt();
        c.paint(canal_radius - CANAL_RADIUS_MM, CORD_HU, Tissue::SoftTissue);
        let bone = self
            .vertebra_distance_mm(p, column, canal_radius)
            .min(rib_cage_distance_mm(p))
            .min(rounded_box_distance_mm(
                sub(p, STERNUM_CENTRE),
                STERNUM_HALF_EXTENTS_MM,
                STERNUM_ROUNDING_MM,
            ));
        c.paint(bone, BONE_HU, Tissue::Bone);
        (c.hu, c.label)
    }

    /// Vertebral bodies (the column minus the discs) and the neural arch around the canal.
    #[inline]
    fn vertebra_distance_mm(&self, p: P3, column: f64, canal_radius: f64) -> f64 {
        let [x, y, z] = p;
        let phase = (z - CARINA_LPS_MM[2]).rem_euclid(VERTEBRA_PITCH_MM);
        let half_body = 0.5 * (VERTEBRA_PITCH_MM - DISC_THICKNESS_MM);
        let body = column.max((phase - 0.5 * VERTEBRA_PITCH_MM).abs() - half_body);
        let arch = (canal_radius - NEURAL_ARCH_OUTER_RADIUS_MM).max(CANAL_RADIUS_MM - canal_radius);
        let spinous = rounded_box_distance_mm(
            [x, y - (CANAL_CENTRE_Y_MM + 16.0), 0.0],
            [3.0, 6.0, f64::INFINITY],
            1.0,
        );
        body.min(arch).min(spinous)
    }
}

/// Signed distance to the inner surface of the rib cage (horizontal ellipse narrowing above
/// [`CAVITY_TAPER_START_Z_MM`]), without the inlet cap.
#[inline]
fn cavity_wall_distance_mm(x: f64, y: f64, z: f64) -> f64 {
    let scale = if z <= CAVITY_TAPER_START_Z_MM {
        1.0
    } else {
        let t = (z - CAVITY_TAPER_START_Z_MM) / (THORACIC_INLET_Z_MM - CAVITY_TAPER_START_Z_MM);
        (1.0 - (1.0 - CAVITY_INLET_SCALE) * t * t).max(CAVITY_INLET_SCALE)
    };
    ellipse_distance_mm(
        x,
        y - CAVITY_CENTRE_Y_MM,
        CAVITY_SEMI_AXES_MM[0] * scale,
        CAVITY_SEMI_AXES_MM[1] * scale,
    )
}

/// Signed distance to the diaphragm (upper envelope of both domes), negative below it.
#[inline]
fn below_diaphragm_distance_mm(x: f64, y: f64, z: f64) -> f64 {
    let (zr, sr) = RIGHT_DOME.height_and_slope(x, y);
    let (zl, sl) = LEFT_DOME.height_and_slope(x, y);
    let (height, slope) = if zr >= zl { (zr, sr) } else { (zl, sl) };
    (z - height) / (1.0 + slope[0] * slope[0] + slope[1] * slope[1]).sqrt()
}

/// Signed distance to the nearest rib: tilted elliptic bands just outside the cavity wall.
#[inline]
fn rib_cage_distance_mm(p: P3) -> f64 {
    let [x, y, z] = p;
    let medial = RIB_MEDIAL_LIMIT_MM - x.abs();
    if medial > 0.0 {
        return medial;
    }
    let radial = cavity_wall_distance_mm(x, y, z) - RIB_OFFSET_OUTSIDE_CAVITY_MM;
    let posterior_y = CAVITY_CENTRE_Y_MM + CAVITY_SEMI_AXES_MM[1];
    let drop = RIB_SLOPE * (posterior_y - y);
    let cos_tilt = 1.0 / (1.0 + RIB_SLOPE * RIB_SLOPE).sqrt();
    let nearest = ((TOP_RIB_POSTERIOR_Z_MM - drop - z) / RIB_PITCH_MM).round();
    let mut best = f64::INFINITY;
    for offset in [-1.0, 0.0, 1.0] {
        let n = nearest + offset;
        if n < 0.0 || n >= RIB_COUNT as f64 {
            continue;
        }
        let rib_z = TOP_RIB_POSTERIOR_Z_MM - n * RIB_PITCH_MM - drop;
        let mut d = ellipse_distance_mm(
            radial,
            (z - rib_z) * cos_tilt,
            RIB_SEMI_AXES_MM[0],
            RIB_SEMI_AXES_MM[1],
        );
        if n as usize >= RIB_COUNT - 2 {
            d = d.max(FLOATING_RIB_ANTERIOR_LIMIT_Y_MM - y);
        }
        best = best.min(d);
    }
    best.max(medial)
}

/// First-order signed distance to an ellipse (F/|∇F| with F = q − 1); exact for a circle.
#[inline]
fn ellipse_distance_mm(dx: f64, dy: f64, a: f64, b: f64) -> f64 {
    let q = ((dx / a).powi(2) + (dy / b).powi(2)).sqrt();
    let g = ((dx / (a * a)).powi(2) + (dy / (b * b)).powi(2)).sqrt();
    if g < 1e-12 {
        return -a.min(b);
    }
    (q - 1.0) * q / g
}

/// First-order signed distance to an ellipsoid centred at the origin; exact for a sphere.
#[inline]
fn ellipsoid_distance_mm(d: P3, semi_axes_mm: P3) -> f64 {
    let [a, b, c] = semi_axes_mm;
    let q = ((d[0] / a).powi(2) + (d[1] / b).powi(2) + (d[2] / c).powi(2)).sqrt();
    let g = ((d[0] / (a * a)).powi(2) + (d[1] / (b * b)).powi(2) + (d[2] / (c * c)).powi(2)).sqrt();
    if g < 1e-12 {
        return -a.min(b).min(c);
    }
    (q - 1.0) * q / g
}

/// Exact signed distance to a box centred at the origin with rounded edges.
#[inline]
fn rounded_box_distance_mm(d: P3, half_extents_mm: P3, rounding_mm: f64) -> f64 {
    let q: P3 = std::array::from_fn(|a| d[a].abs() - (half_extents_mm[a] - rounding_mm));
    let outside = norm(q.map(|v| v.max(0.0)));
    let inside = q[0].max(q[1]).max(q[2]).min(0.0);
    outside + inside - rounding_mm
}

#[inline]
fn sub(a: P3, b: P3) -> P3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
fn dot(a: P3, b: P3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn norm(a: P3) -> f64 {
    dot(a, a).sqrt()
}

/// Writes the phantom as `phantom-ct.nii.gz` (HU), `phantom-dicom/` (the same CT as a DICOM
/// series), `phantom-truth.nii.gz` (exact tissue labels) and `phantom.json` (settings,
/// volumes, landmarks) into `out_dir`; returns the paths written.
pub fn write_phantom_files(settings: &PhantomSettings, out_dir: &Path) -> Result<Vec<PathBuf>> {
    use crate::formats::{dicom, nifti};
    let phantom = generate_thorax_phantom(settings)?;
    let ct_path = out_dir.join("phantom-ct.nii.gz");
    let truth_path = out_dir.join("phantom-truth.nii.gz");
    let json_path = out_dir.join("phantom.json");
    let dicom_dir = out_dir.join("phantom-dicom");
    nifti::write_nifti_ct(&ct_path, &phantom.ct)?;
    nifti::write_nifti_labels(&truth_path, &phantom.truth)?;
    // A fresh series replaces the old one whole, so slices of two versions never mix.
    let staging = out_dir.join("phantom-dicom.tmp");
    if staging.exists() {
        std::fs::remove_dir_all(&staging).at(IoOp::Remove, &staging)?;
    }
    std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
    let meta = dicom::CtSeriesMetadata {
        uid_seed: settings.seed,
        series_description: "lungmotion thorax phantom".to_string(),
        ..dicom::CtSeriesMetadata::default()
    };
    dicom::write_ct_series(&phantom.ct, &staging, &meta)?;
    if dicom_dir.exists() {
        std::fs::remove_dir_all(&dicom_dir).at(IoOp::Remove, &dicom_dir)?;
    }
    std::fs::rename(&staging, &dicom_dir).at(IoOp::Replace, &dicom_dir)?;
    let json = serde_json::to_string_pretty(&phantom.description).map_err(|e| Error::Format {
        path: json_path.clone(),
        reason: format!("cannot serialise: {e}"),
    })?;
    crate::durable::write_atomic(&json_path, json.as_bytes())?;
    Ok(vec![ct_path, dicom_dir, truth_path, json_path])
}

/// Height of the lung apex above which the breathing field leaves the anatomy still, mm.
const MOTION_STILL_Z_MM: f64 = 95.0;
/// Height of the domes, at and below which the diaphragm's full descent applies, mm.
const MOTION_DOME_Z_MM: f64 = -100.0;
/// Height of the lower ribs, at and below which the chest wall's full expansion applies, mm.
const MOTION_LOWER_RIBS_Z_MM: f64 = -60.0;
/// Largest magnitude of each component of a [`BreathingMotion`], mm: far beyond quiet or deep
/// breathing, and small enough that the field stays invertible (its slope stays below 1/3).
pub const MAX_BREATHING_MOTION_MM: f64 = 40.0;

/// A breathing state of the phantom as an analytic displacement field that owes nothing to
/// the mass–spring model: the diaphragm descends (most at and below the domes, nothing at the
/// apex), the chest wall widens forward and sideways (most at the lower ribs, nothing at the
/// spine) and the ribs rise at the wall (nothing on the body axis). Every shape, vessels and
/// tumour included, moves with the field.
///
/// The field `u` is Eulerian: the state's image at `x` is the rest image at `x − u(x)`
/// ([`BreathingMotion::source_lps_mm`]), so drawing a state costs one field evaluation per
/// voxel; the tissue at rest point `X` is at the `x` with `x − u(x) = X`
/// ([`BreathingMotion::moved_lps_mm`], a contraction because the field's slope is small).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BreathingMotion {
    /// Downward motion of the diaphragm domes and everything below them, mm.
    pub diaphragm_descent_mm: f64,
    /// Forward motion of the anterior chest wall at the lower ribs, mm.
    pub anterior_expansion_mm: f64,
    /// Outward motion of each lateral chest wall at the lower ribs, mm.
    pub lateral_expansion_mm: f64,
    /// Upward motion of the ribs at the chest wall, mm.
    pub rib_lift_mm: f64,
}

impl BreathingMotion {
    /// No motion: the phantom as [`generate_thorax_phantom`] draws it (end-exhale).
    pub const REST: BreathingMotion = BreathingMotion {
        diaphragm_descent_mm: 0.0,
        anterior_expansion_mm: 0.0,
        lateral_expansion_mm: 0.0,
        rib_lift_mm: 0.0,
    };

    /// End-inhale of quiet breathing: superior–inferior motion dominates as in the DIR-Lab
    /// landmarks (mean |Δz| 3.6–13.5 mm, the other axes 0.6–3.7 mm).
    pub const END_INHALE: BreathingMotion = BreathingMotion {
        diaphragm_descent_mm: 16.0,
        anterior_expansion_mm: 5.0,
        lateral_expansion_mm: 3.0,
        rib_lift_mm: 4.0,
    };

    /// This motion with every component multiplied by `amplitude`.
    pub fn scaled(&self, amplitude: f64) -> BreathingMotion {
        BreathingMotion {
            diaphragm_descent_mm: self.diaphragm_descent_mm * amplitude,
            anterior_expansion_mm: self.anterior_expansion_mm * amplitude,
            lateral_expansion_mm: self.lateral_expansion_mm * amplitude,
            rib_lift_mm: self.rib_lift_mm * amplitude,
        }
    }

    /// Refuses components that are not finite or beyond [`MAX_BREATHING_MOTION_MM`].
    pub fn validate(&self) -> Result<()> {
        let components = [
            ("diaphragm_descent_mm", self.diaphragm_descent_mm),
            ("anterior_expansion_mm", self.anterior_expansion_mm),
            ("lateral_expansion_mm", self.lateral_expansion_mm),
            ("rib_lift_mm", self.rib_lift_mm),
        ];
        for (key, v) in components {
            if !v.is_finite() || v.abs() > MAX_BREATHING_MOTION_MM {
                return Err(Error::Config {
                    settings: "phantom breathing motion",
                    file: None,
                    key: Some(key.to_string()),
                    reason: format!("{v} mm; it must lie within ±{MAX_BREATHING_MOTION_MM} mm"),
                });
            }
        }
        Ok(())
    }

    /// The Eulerian displacement u at LPS point `p`, mm.
    pub fn displacement_mm(&self, p: [f64; 3]) -> [f64; 3] {
        let [x, y, z] = p;
        let descent = smoothstep((MOTION_STILL_Z_MM - z) / (MOTION_STILL_Z_MM - MOTION_DOME_Z_MM));
        let wall =
            smoothstep((MOTION_STILL_Z_MM - z) / (MOTION_STILL_Z_MM - MOTION_LOWER_RIBS_Z_MM));
        let [a, b] = CAVITY_SEMI_AXES_MM;
        let dy = y - CAVITY_CENTRE_Y_MM;
        // Squared elliptic radius in the cavity's own ellipse: 0 on the body axis, 1 at the wall.
        let radius2 = ((x / a).powi(2) + (dy / b).powi(2)).min(1.0);
        // The spine holds the posterior wall: forward motion grows from it to the sternum.
        let forward = ((b - dy) / (2.0 * b)).max(0.0);
        [
            self.lateral_expansion_mm * (x / a) * wall,
            -self.anterior_expansion_mm * forward * wall,
            -self.diaphragm_descent_mm * descent + self.rib_lift_mm * radius2 * wall,
        ]
    }

    /// Where the tissue drawn at `moved_lps_mm` in this state sits at rest: `x − u(x)`.
    pub fn source_lps_mm(&self, moved_lps_mm: [f64; 3]) -> [f64; 3] {
        if *self == BreathingMotion::REST {
            return moved_lps_mm;
        }
        let u = self.displacement_mm(moved_lps_mm);
        std::array::from_fn(|a| moved_lps_mm[a] - u[a])
    }

    /// Where the tissue at rest point `rest_lps_mm` is in this state: the `x` with
    /// `x − u(x) = rest`, by fixed-point iteration `x ← rest + u(x)` (a contraction: the
    /// field's slope is below 1/3), to 1e-12 mm.
    pub fn moved_lps_mm(&self, rest_lps_mm: [f64; 3]) -> [f64; 3] {
        let mut x = rest_lps_mm;
        for _ in 0..200 {
            let u = self.displacement_mm(x);
            let next: [f64; 3] = std::array::from_fn(|a| rest_lps_mm[a] + u[a]);
            let change = norm(sub(next, x));
            x = next;
            if change < 1e-12 {
                break;
            }
        }
        x
    }
}

/// 0 below 0, 1 above 1, 3t² − 2t³ between: a ramp with no kink at either end.
#[inline]
fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

impl PhantomLandmarks {
    /// The same landmarks carried by `motion` to where that breathing state draws them.
    pub fn moved(&self, motion: &BreathingMotion) -> PhantomLandmarks {
        let m = |p: [f64; 3]| motion.moved_lps_mm(p);
        PhantomLandmarks {
            carina_lps_mm: m(self.carina_lps_mm),
            tumour_centre_lps_mm: self.tumour_centre_lps_mm.map(m),
            right_lung_apex_lps_mm: m(self.right_lung_apex_lps_mm),
            right_lung_base_lps_mm: m(self.right_lung_base_lps_mm),
            left_lung_apex_lps_mm: m(self.left_lung_apex_lps_mm),
            left_lung_base_lps_mm: m(self.left_lung_base_lps_mm),
        }
    }
}

/// Spacing of the lattice of lung landmarks, mm.
pub const LUNG_LANDMARK_SPACING_MM: f64 = 24.0;
/// How far inside its lung every lung landmark lies at rest, mm (checked along 26
/// directions), so that no landmark sits on a boundary the segmentation may place a voxel off.
pub const LUNG_LANDMARK_DEPTH_MM: f64 = 8.0;

/// Landmarks throughout both lungs at rest, LPS mm: the points of a
/// [`LUNG_LANDMARK_SPACING_MM`] lattice (through the carina) that lie in a lung at least
/// [`LUNG_LANDMARK_DEPTH_MM`] from its boundary and inside the field of view, then the
/// tumour centre when there is a tumour: DIR-Lab-like point pairs whose every breathing state
/// is known exactly ([`BreathingMotion::moved_lps_mm`]).
pub fn lung_landmarks_lps_mm(settings: &PhantomSettings) -> Result<Vec<[f64; 3]>> {
    let geometry = phantom_geometry(settings)?;
    let anatomy = Anatomy::new(settings.tumour, geometry.voxel_volume_mm3().cbrt());
    let lo: [f64; 3] = std::array::from_fn(|a| geometry.origin_lps_mm[a]);
    let hi: [f64; 3] = std::array::from_fn(|a| {
        geometry.origin_lps_mm[a] + (geometry.dims[a] - 1) as f64 * geometry.spacing_mm[a]
    });
    let step = LUNG_LANDMARK_SPACING_MM;
    let first = |a: usize| CARINA_LPS_MM[a] + ((lo[a] - CARINA_LPS_MM[a]) / step).ceil() * step;
    let mut points = Vec::new();
    let mut z = first(2);
    while z <= hi[2] {
        let mut y = first(1);
        while y <= hi[1] {
            let mut x = first(0);
            while x <= hi[0] {
                let p = [x, y, z];
                let (_, label) = anatomy.evaluate(p);
                let lung = matches!(label, Tissue::RightLung | Tissue::LeftLung);
                // Along the 26 directions to the neighbours of a cube, not only the axes: the
                // domes and the cavity wall are oblique.
                let deep = lung
                    && (0..27).filter(|&n| n != 13).all(|n| {
                        let d = [n % 3, (n / 3) % 3, n / 9].map(|c| c as f64 - 1.0);
                        let scale = LUNG_LANDMARK_DEPTH_MM / norm(d);
                        let q = std::array::from_fn(|a| p[a] + d[a] * scale);
                        anatomy.evaluate(q).1 == label
                    });
                if deep {
                    points.push(p);
                }
                x += step;
            }
            y += step;
        }
        z += step;
    }
    if let Some(t) = settings.tumour {
        points.push(t.centre_lps_mm);
    }
    Ok(points)
}

/// A 4D-CT of the phantom: the same anatomy at several breathing states.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FourDctPhantomSettings {
    /// Grid, tumour, noise and seed of every phase.
    pub phantom: PhantomSettings,
    /// The motion at amplitude 1 (end-inhale).
    pub end_inhale: BreathingMotion,
    /// Each phase's amplitude, in phase order: its motion is `end_inhale` scaled by it.
    pub amplitudes: Vec<f64>,
}

impl FourDctPhantomSettings {
    /// `count` phases over one cycle as a scanner bins them: phase k at (1 + cos 2πk/count)/2
    /// of the end-inhale motion, so phase 0 is end-inhale and phase count/2 end-exhale.
    pub fn with_phases(phantom: PhantomSettings, count: usize) -> FourDctPhantomSettings {
        let amplitudes = (0..count)
            .map(|k| 0.5 * (1.0 + (std::f64::consts::TAU * k as f64 / count as f64).cos()))
            .collect();
        FourDctPhantomSettings {
            phantom,
            end_inhale: BreathingMotion::END_INHALE,
            amplitudes,
        }
    }

    /// The name of phase `index` of this 4D-CT, DIR-Lab style: `T` and its percent of the
    /// cycle (`T00` end-inhale, `T50` end-exhale of ten phases).
    pub fn phase_name(&self, index: usize) -> String {
        format!("T{:02}", index * 100 / self.amplitudes.len().max(1))
    }
}

/// One phase of a written 4D phantom.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FourDctPhantomPhase {
    /// Its name (also its files' stem).
    pub name: String,
    /// Its amplitude (0 rest, 1 end-inhale).
    pub amplitude: f64,
    /// The motion it was drawn with.
    pub motion: BreathingMotion,
    /// Right lung label volume, mL.
    pub right_lung_volume_ml: f64,
    /// Left lung label volume, mL.
    pub left_lung_volume_ml: f64,
    /// The named landmarks at this phase.
    pub landmarks: PhantomLandmarks,
}

/// What [`write_four_dct_phantom`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FourDctPhantomDescription {
    /// The settings.
    pub settings: FourDctPhantomSettings,
    /// The grid shared by every phase.
    pub geometry: VolumeGeometry,
    /// The phases in order.
    pub phases: Vec<FourDctPhantomPhase>,
    /// The lung landmarks at every phase (`[phase][point]`, LPS mm, exact).
    pub lung_landmarks_lps_mm: Vec<Vec<[f64; 3]>>,
}

/// Writes a 4D-CT of the phantom into `out_dir`: `phases/<name>.nii.gz` (the CT of each
/// phase, HU), `landmarks/<name>.txt` (DIR-Lab style: the lung landmarks of that phase as
/// 1-based voxel indices `x y z`, one point per line, fractional because the moved points are
/// exact, not rounded to voxels), `landmarks.csv` (the same points in LPS mm: `phase,point,
/// x_mm,y_mm,z_mm`) and `phantom-4d.json` (the [`FourDctPhantomDescription`]).
pub fn write_four_dct_phantom(
    settings: &FourDctPhantomSettings,
    out_dir: &Path,
) -> Result<FourDctPhantomDescription> {
    use crate::formats::nifti;
    use std::fmt::Write as _;
    let bad = |reason: String| Error::Config {
        settings: "4D phantom settings",
        file: None,
        key: Some("amplitudes".to_string()),
        reason,
    };
    if !(2..=100).contains(&settings.amplitudes.len()) {
        return Err(bad(format!(
            "{} phases; a 4D-CT has 2 to 100",
            settings.amplitudes.len()
        )));
    }
    if let Some(a) = settings
        .amplitudes
        .iter()
        .find(|a| !a.is_finite() || a.abs() > 2.0)
    {
        return Err(bad(format!("amplitude {a}; it must lie within ±2")));
    }
    let geometry = phantom_geometry(&settings.phantom)?;
    let rest_points = lung_landmarks_lps_mm(&settings.phantom)?;
    let phases_dir = out_dir.join("phases");
    let landmarks_dir = out_dir.join("landmarks");
    for dir in [&phases_dir, &landmarks_dir] {
        std::fs::create_dir_all(dir).at(IoOp::CreateDir, dir)?;
    }
    let mut csv = String::from("phase,point,x_mm,y_mm,z_mm\n");
    let mut phases = Vec::with_capacity(settings.amplitudes.len());
    let mut all_points = Vec::with_capacity(settings.amplitudes.len());
    for (index, &amplitude) in settings.amplitudes.iter().enumerate() {
        let name = settings.phase_name(index);
        let motion = settings.end_inhale.scaled(amplitude);
        let phantom = generate_breathing_phantom(&settings.phantom, &motion)?;
        nifti::write_nifti_ct(&phases_dir.join(format!("{name}.nii.gz")), &phantom.ct)?;
        let points: Vec<[f64; 3]> = rest_points
            .iter()
            .map(|&p| motion.moved_lps_mm(p))
            .collect();
        let mut dirlab = String::new();
        for (n, p) in points.iter().enumerate() {
            let v = geometry.lps_mm_to_voxel(nalgebra::Vector3::from(*p));
            let inside = (0..3).all(|a| v[a] >= 0.0 && v[a] <= (geometry.dims[a] - 1) as f64);
            if !inside {
                return Err(bad(format!(
                    "landmark {} of phase {name} moves to {p:?} mm, outside the field of view",
                    n + 1
                )));
            }
            // Rust's shortest round-trip formatting: the reader gets the same f64 back.
            let _ = writeln!(dirlab, "{}\t{}\t{}", v[0] + 1.0, v[1] + 1.0, v[2] + 1.0);
            let _ = writeln!(csv, "{name},{},{},{},{}", n + 1, p[0], p[1], p[2]);
        }
        let txt = landmarks_dir.join(format!("{name}.txt"));
        crate::durable::write_atomic(&txt, dirlab.as_bytes())?;
        let d = phantom.description;
        phases.push(FourDctPhantomPhase {
            name,
            amplitude,
            motion,
            right_lung_volume_ml: d.right_lung_volume_ml,
            left_lung_volume_ml: d.left_lung_volume_ml,
            landmarks: d.landmarks,
        });
        all_points.push(points);
    }
    crate::durable::write_atomic(&out_dir.join("landmarks.csv"), csv.as_bytes())?;
    let description = FourDctPhantomDescription {
        settings: settings.clone(),
        geometry,
        phases,
        lung_landmarks_lps_mm: all_points,
    };
    let json_path = out_dir.join("phantom-4d.json");
    let json = serde_json::to_string_pretty(&description).map_err(|e| Error::Format {
        path: json_path.clone(),
        reason: format!("cannot serialise: {e}"),
    })?;
    crate::durable::write_atomic(&json_path, json.as_bytes())?;
    Ok(description)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_are_exact_where_the_shape_is_simple() {
        // Circle and sphere: the first-order ellipse distance is exact.
        assert!((ellipse_distance_mm(30.0, 40.0, 20.0, 20.0) - 30.0).abs() < 1e-12);
        assert!((ellipsoid_distance_mm([0.0, 0.0, -5.0], [10.0; 3]) + 5.0).abs() < 1e-12);
        // On an ellipse's axis the first-order distance is exact too.
        assert!((ellipse_distance_mm(0.0, 130.0, 170.0, 120.0) - 10.0).abs() < 1e-9);
        let tube = Tube::new([0.0; 3], [0.0, 0.0, 10.0], 2.0, 2.0);
        assert!((tube.distance_mm([5.0, 0.0, 5.0]) - 3.0).abs() < 1e-12);
        assert!((tube.distance_mm([0.0, 0.0, 14.0]) - 2.0).abs() < 1e-12);
        let b = rounded_box_distance_mm([0.0, 0.0, 12.0], [5.0, 5.0, 10.0], 1.0);
        assert!((b - 2.0).abs() < 1e-12);
        assert!((rounded_box_distance_mm([0.0; 3], [5.0, 6.0, 10.0], 1.0) + 5.0).abs() < 1e-12);
    }

    #[test]
    fn noise_has_the_requested_spread_and_no_bias() {
        let noise = NoiseSource {
            seed: 7,
            sigma_hu: 20.0,
        };
        let n = 200_000;
        let samples: Vec<f64> = (0..n).map(|i| noise.sample_hu(i) as f64).collect();
        let mean = samples.iter().sum::<f64>() / n as f64;
        let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.2, "mean {mean}");
        assert!((var.sqrt() - 20.0).abs() < 0.3, "sd {}", var.sqrt());
    }

    #[test]
    fn breathing_motion_moves_points_to_where_their_source_is_drawn() {
        let motion = BreathingMotion::END_INHALE;
        for rest in [
            [-95.0, 20.0, -80.0],
            [60.0, -40.0, -120.0],
            [0.0, 0.0, 150.0],
        ] {
            let moved = motion.moved_lps_mm(rest);
            let back = motion.source_lps_mm(moved);
            assert!(
                norm(sub(back, rest)) < 1e-9,
                "{rest:?} → {moved:?} → {back:?}"
            );
        }
        // The apex region stays, the base descends by the full descent, the field is SI-dominant.
        let apex = motion.moved_lps_mm([0.0, 10.0, 100.0]);
        assert!(norm(sub(apex, [0.0, 10.0, 100.0])) < 1e-9);
        let base = sub(
            motion.moved_lps_mm([-65.0, -10.0, -110.0]),
            [-65.0, -10.0, -110.0],
        );
        assert!(
            base[2] < -12.0 && base[0].abs() < 4.0 && base[1].abs() < 6.0,
            "{base:?}"
        );
    }
}
