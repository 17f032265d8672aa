//! The exact-geometry comment extension: f64 spacing, LPS origin and direction as text,
//! trusted on reading only when it agrees with the header's float32 transform.

use crate::volume::VolumeGeometry;

/// NIFTI_ECODE_COMMENT: the extension code of the exact-geometry text written here.
pub(super) const ECODE_COMMENT: i32 = 6;
/// First line of the exact-geometry comment extension.
const GEOMETRY_EXTENSION_TAG: &str = "lungmotion exact geometry, LPS mm";
/// Largest distance (mm) between the header's f32 grid and the extension's exact grid for
/// the extension to be trusted: float32 rounding is far below, any edit by another tool
/// (resampling, re-centring) far above.
const EXTENSION_AGREEMENT_MM: f64 = 1e-3;

/// The exact (f64) geometry from our comment extension when it agrees with the header's
/// float32 transform; otherwise the header's geometry unchanged.
pub(super) fn refine_geometry(
    geometry: VolumeGeometry,
    extensions: &[u8],
    big_endian: bool,
    what: &str,
) -> VolumeGeometry {
    // The 4-byte extension flag precedes the extensions; a zero first byte means none.
    if extensions.len() < 4 || extensions[0] == 0 {
        return geometry;
    }
    let read_i32 = |b: &[u8]| {
        let a = [b[0], b[1], b[2], b[3]];
        if big_endian {
            i32::from_be_bytes(a)
        } else {
            i32::from_le_bytes(a)
        }
    };
    let mut offset = 4;
    while offset + 8 <= extensions.len() {
        let size = read_i32(&extensions[offset..]);
        let code = read_i32(&extensions[offset + 4..]);
        let Some(end) = usize::try_from(size)
            .ok()
            .filter(|&n| n >= 8 && n % 16 == 0)
            .map(|n| offset + n)
            .filter(|&end| end <= extensions.len())
        else {
            tracing::warn!("{what}: malformed header extension at byte {offset}; ignored");
            return geometry;
        };
        if code == ECODE_COMMENT {
            if let Some(exact) = parse_geometry_text(&extensions[offset + 8..end], geometry.dims) {
                let agrees = exact.validate(what).is_ok()
                    && exact.same_grid(&geometry, EXTENSION_AGREEMENT_MM)
                    && (0..3).all(|a| {
                        (exact.spacing_mm[a] - geometry.spacing_mm[a]).abs()
                            <= EXTENSION_AGREEMENT_MM
                    });
                if agrees {
                    return exact;
                }
                tracing::warn!(
                    "{what}: the lungmotion geometry extension disagrees with the header's \
                     transform (the file was edited?); using the header"
                );
            }
        }
        offset = end;
    }
    geometry
}

/// The exact geometry as comment text: a tag line, then spacing, origin and the direction
/// columns, each number in Rust's shortest round-tripping decimal form.
pub(super) fn geometry_text(g: &VolumeGeometry) -> String {
    let numbers = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:?}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let direction: Vec<f64> = g.direction_lps.iter().flatten().copied().collect();
    format!(
        "{GEOMETRY_EXTENSION_TAG}\nspacing_mm {}\norigin_lps_mm {}\ndirection_lps_columns {}\n",
        numbers(&g.spacing_mm),
        numbers(&g.origin_lps_mm),
        numbers(&direction)
    )
}

/// The exact geometry from our comment text, `None` when the text is not ours.
fn parse_geometry_text(bytes: &[u8], dims: [usize; 3]) -> Option<VolumeGeometry> {
    let text = std::str::from_utf8(bytes).ok()?.trim_end_matches('\0');
    let mut lines = text.lines();
    if lines.next()? != GEOMETRY_EXTENSION_TAG {
        return None;
    }
    let mut field = |name: &str, count: usize| -> Option<Vec<f64>> {
        let values = lines.next()?.strip_prefix(name)?;
        let parsed: Vec<f64> = values
            .split_whitespace()
            .map(|v| v.parse().ok())
            .collect::<Option<_>>()?;
        (parsed.len() == count).then_some(parsed)
    };
    let spacing = field("spacing_mm ", 3)?;
    let origin = field("origin_lps_mm ", 3)?;
    let direction = field("direction_lps_columns ", 9)?;
    Some(VolumeGeometry {
        dims,
        spacing_mm: [spacing[0], spacing[1], spacing[2]],
        origin_lps_mm: [origin[0], origin[1], origin[2]],
        direction_lps: std::array::from_fn(|c| std::array::from_fn(|r| direction[3 * c + r])),
    })
}
