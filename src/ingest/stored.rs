//! The file form of an ingest, so that a CT ingested once (the service's upload, in its
//! child process) need not be segmented and its wall field computed again by the first job
//! that uses it with the same settings.
//!
//! What it holds, and what is left to recompute: the segmentation (lung, airway and body
//! masks, run-length coded: a few MB for a 512 × 512 × 141 CT, and its report) and the wall's
//! smoothed distance field, the two costly parts (on the POPI CT at 6 mm, `lungmotion ingest`:
//! 2.0 s and 3.3 s of the
//! 6.1 s ingest). The rest of the model (lattice, cells, mesh, groups, constraints, the
//! groups painted on the CT grid) is rebuilt from those masks in under a second, by the code
//! that built it the first time, so the file holds no copy of it that could drift from that
//! code. The CT voxels are not in it: they are the upload.
//!
//! The wall is stored as the `f32` samples it is blurred in, before the scale to metres that
//! makes them `f64` (half the bytes); a sample whose `f64` value is not exactly that scale of
//! an `f32` would not come back bit for bit, and then no file is written.
//!
//! Layout (little-endian): the magic `LMINGEST`, the format version ([`FORMAT_VERSION`]),
//! the software version, the key it was made with (the ingest settings, DICOM read options
//! and series choice, as the caller words them), the payload's length and CRC-32, then the
//! payload: the CT grid, the segmentation report (JSON), the three masks and the wall.
//!
//! Trust: a file is used only if its magic, versions and key match, its length is the one
//! its header states and its checksum holds, the CT grid is the loaded CT's, every mask
//! decodes to exactly that grid's voxel count and the wall lies on the grid the model build
//! samples; anything else is an error the caller logs before ingesting as if there were no
//! file. Nothing is allocated from a size the file states before that size is checked
//! against the bytes the file really has or the CT's own grid.

use std::io::{Read, Seek, Write};
use std::path::Path;

use nalgebra::Vector3;

use super::lung_model::PrebuiltWall;
use super::pipeline::{ingest_from_parts, IngestOutcome, IngestSettings};
use super::scan::LoadedScan;
use super::segmentation::{LungSegmentation, SegmentationReport};
use super::Cancel;
use crate::model::SignedDistanceField;
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, IoContext, IoOp, Result};

/// Version of the layout and of what the ingest computes: raised whenever either changes,
/// so that files of an older server are ignored rather than misread.
pub const FORMAT_VERSION: u32 = 1;

const MAGIC: &[u8; 8] = b"LMINGEST";

/// Longest key or software version accepted in a header, bytes.
const MAX_TEXT_BYTES: u32 = 1 << 20;

/// Highest label of each mask: lungs 0–2, airways and body 0–1.
const MASK_MAX_LABEL: [u8; 3] = [2, 1, 1];

/// Writes `outcome` (the ingest of a CT on grid `ct`, made with `key`) to `path`, through a
/// temporary file renamed into place; the bytes written.
pub fn write_stored_ingest(
    path: &Path,
    key: &str,
    ct: &VolumeGeometry,
    outcome: &IngestOutcome,
) -> Result<u64> {
    let wall = &outcome.model.wall;
    let wall_f32 = wall_as_f32(wall).ok_or_else(|| {
        Error::format(
            path,
            "the wall field is not an f32 field scaled to metres; not stored",
        )
    })?;
    let mut payload = Vec::new();
    put_geometry(&mut payload, ct);
    let report = serde_json::to_vec(&outcome.segmentation.report)
        .map_err(|e| Error::format(path, format!("segmentation report: {e}")))?;
    put_bytes(&mut payload, &report);
    let seg = &outcome.segmentation;
    for mask in [&seg.lungs, &seg.airways, &seg.body] {
        put_bytes(&mut payload, &run_length_encode(mask.as_slice()));
    }
    for v in wall.origin_m.iter() {
        payload.extend_from_slice(&v.to_le_bytes());
    }
    payload.extend_from_slice(&wall.spacing_m[0].to_le_bytes());
    for n in wall.samples {
        payload.extend_from_slice(&(n as u64).to_le_bytes());
    }
    payload.extend_from_slice(&(outcome.model.report.wall_contact_voxels as u64).to_le_bytes());
    // The wall's samples follow the payload built so far, streamed rather than copied.
    let wall_bytes = wall_f32.len() as u64 * 4;
    let mut crc = crc32fast::Hasher::new();
    crc.update(&payload);
    let mut wall_buffer = Vec::with_capacity(1 << 16);
    for chunk in wall_f32.chunks(1 << 14) {
        wall_buffer.clear();
        chunk
            .iter()
            .for_each(|v| wall_buffer.extend_from_slice(&v.to_le_bytes()));
        crc.update(&wall_buffer);
    }
    let mut header = Vec::new();
    header.extend_from_slice(MAGIC);
    header.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    put_text(&mut header, env!("CARGO_PKG_VERSION"));
    put_text(&mut header, key);
    header.extend_from_slice(&(payload.len() as u64 + wall_bytes).to_le_bytes());
    header.extend_from_slice(&crc.finalize().to_le_bytes());

    let partial = path.with_extension("partial");
    let written = (|| -> std::io::Result<u64> {
        let mut out = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(&partial)?);
        out.write_all(&header)?;
        out.write_all(&payload)?;
        for chunk in wall_f32.chunks(1 << 14) {
            wall_buffer.clear();
            chunk
                .iter()
                .for_each(|v| wall_buffer.extend_from_slice(&v.to_le_bytes()));
            out.write_all(&wall_buffer)?;
        }
        out.flush()?;
        Ok(header.len() as u64 + payload.len() as u64 + wall_bytes)
    })();
    let written = match written {
        Ok(n) => n,
        Err(e) => {
            let _ = std::fs::remove_file(&partial);
            return Err(Error::io(IoOp::Write, &partial, e));
        }
    };
    std::fs::rename(&partial, path).at(IoOp::Rename, &partial)?;
    Ok(written)
}

/// What a stored ingest came to.
pub enum StoredIngest {
    /// The ingest, from the stored segmentation and wall.
    Used(Box<IngestOutcome>),
    /// The file is sound but was made with other settings (a job that chose its own).
    OtherSettings,
}

/// The ingest of `scan` with `settings` from the file at `path`, written for `key`: the
/// stored segmentation and wall, and the rest of the model rebuilt from them; an error
/// (the file is missing, of another version, truncated, corrupt or of another CT) when the
/// file cannot be trusted, and the caller then ingests anew.
pub fn read_stored_ingest(
    path: &Path,
    key: &str,
    scan: &LoadedScan,
    settings: &IngestSettings,
    cancel: Cancel<'_>,
) -> Result<StoredIngest> {
    let t = std::time::Instant::now();
    let bad = |reason: String| Error::format(path, reason);
    let mut file = std::fs::File::open(path).at(IoOp::Open, path)?;
    let file_len = file.metadata().at(IoOp::Metadata, path)?.len();
    let mut magic = [0u8; 8];
    file.read_exact(&mut magic)
        .map_err(|_| bad("shorter than its header".into()))?;
    if &magic != MAGIC {
        return Err(bad("not a stored ingest (no LMINGEST magic)".into()));
    }
    let version = read_u32(&mut file).map_err(|_| bad("header cut short".into()))?;
    if version != FORMAT_VERSION {
        return Err(bad(format!(
            "format version {version}, this server reads {FORMAT_VERSION}"
        )));
    }
    let software = read_text(&mut file, file_len).map_err(bad)?;
    if software != env!("CARGO_PKG_VERSION") {
        return Err(bad(format!(
            "written by lungmotion {software}, this is {}",
            env!("CARGO_PKG_VERSION")
        )));
    }
    let stored_key = read_text(&mut file, file_len).map_err(bad)?;
    if stored_key != key {
        return Ok(StoredIngest::OtherSettings);
    }
    let payload_len = read_u64(&mut file).map_err(|_| bad("header cut short".into()))?;
    let crc = read_u32(&mut file).map_err(|_| bad("header cut short".into()))?;
    let header_len = file.stream_position().at(IoOp::Read, path)?;
    if header_len.checked_add(payload_len) != Some(file_len) {
        return Err(bad(format!(
            "{file_len} bytes where its header announces {}",
            header_len.saturating_add(payload_len)
        )));
    }
    // Sized by the file's real length, checked just above.
    let mut payload = vec![0u8; payload_len as usize];
    file.read_exact(&mut payload).at(IoOp::Read, path)?;
    drop(file);
    if crc32fast::hash(&payload) != crc {
        return Err(bad("checksum mismatch: the file is corrupt".into()));
    }
    cancel.check("the reading of the stored ingest")?;
    let mut r = Reader {
        bytes: &payload,
        at: 0,
    };
    let geometry = take_geometry(&mut r).map_err(bad)?;
    if geometry != scan.ct.geometry {
        return Err(bad(format!(
            "made for a CT grid of {:?} voxels, the CT read has {:?}",
            geometry.dims, scan.ct.geometry.dims
        )));
    }
    let report: SegmentationReport = serde_json::from_slice(r.bytes_field().map_err(bad)?)
        .map_err(|e| bad(format!("segmentation report: {e}")))?;
    let voxels = geometry.voxel_count();
    let mut masks = Vec::with_capacity(3);
    for (name, max_label) in ["lungs", "airways", "body"].into_iter().zip(MASK_MAX_LABEL) {
        let coded = r.bytes_field().map_err(bad)?;
        let data = run_length_decode(coded, voxels, max_label)
            .map_err(|e| bad(format!("{name} mask: {e}")))?;
        masks.push(Volume::from_data(geometry, data)?);
    }
    let [lungs, airways, body]: [Volume<u8>; 3] = masks
        .try_into()
        .map_err(|_| bad("three masks expected".into()))?;
    let wall = take_wall(&mut r).map_err(bad)?;
    if r.at != payload.len() {
        return Err(bad(format!(
            "{} bytes after the wall field",
            payload.len() - r.at
        )));
    }
    drop(payload);
    let read_s = t.elapsed().as_secs_f64();
    let segmentation = LungSegmentation {
        lungs,
        airways,
        body,
        report,
    };
    let mut outcome = ingest_from_parts(scan, settings, Some(segmentation), Some(wall), cancel)?;
    outcome
        .summary
        .timings_s
        .insert("stored_ingest_read".to_string(), read_s);
    Ok(StoredIngest::Used(Box::new(outcome)))
}

/// The wall's samples as the `f32` values that, scaled by its spacing, give them bit for bit;
/// `None` when one does not.
fn wall_as_f32(wall: &SignedDistanceField) -> Option<std::borrow::Cow<'_, [f32]>> {
    let scale = wall.spacing_m[0];
    if wall.spacing_m.iter().any(|&s| s != scale) {
        return None;
    }
    if let Some((values, unit_m)) = wall.scaled_samples() {
        if unit_m == scale {
            return Some(std::borrow::Cow::Borrowed(values));
        }
    }
    (0..wall.len())
        .map(|i| {
            let v = wall.value_m(i);
            let x = (v / scale) as f32;
            ((x as f64 * scale).to_bits() == v.to_bits()).then_some(x)
        })
        .collect::<Option<Vec<f32>>>()
        .map(std::borrow::Cow::Owned)
}

/// `(value, run length as LEB128)` pairs.
fn run_length_encode(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut rest = data;
    while let Some(&value) = rest.first() {
        let run = rest.iter().position(|&v| v != value).unwrap_or(rest.len());
        out.push(value);
        let mut n = run as u64;
        loop {
            let byte = (n & 0x7f) as u8;
            n >>= 7;
            if n == 0 {
                out.push(byte);
                break;
            }
            out.push(byte | 0x80);
        }
        rest = &rest[run..];
    }
    out
}

/// The `voxels` values of a run-length coded mask whose labels are at most `max_label`.
fn run_length_decode(
    coded: &[u8],
    voxels: usize,
    max_label: u8,
) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(voxels);
    let mut at = 0;
    while at < coded.len() {
        let value = coded[at];
        at += 1;
        if value > max_label {
            return Err(format!("label {value} above {max_label}"));
        }
        let mut run: u64 = 0;
        let mut shift = 0;
        loop {
            let Some(&byte) = coded.get(at) else {
                return Err("a run length is cut short".into());
            };
            at += 1;
            if shift > 56 {
                return Err("a run length is too long".into());
            }
            run |= u64::from(byte & 0x7f) << shift;
            shift += 7;
            if byte & 0x80 == 0 {
                break;
            }
        }
        let end = usize::try_from(run)
            .ok()
            .and_then(|r| out.len().checked_add(r))
            .filter(|&end| end <= voxels)
            .ok_or_else(|| format!("runs cover more than the CT's {voxels} voxels"))?;
        out.resize(end, value);
    }
    if out.len() != voxels {
        return Err(format!(
            "runs cover {} of the CT's {voxels} voxels",
            out.len()
        ));
    }
    Ok(out)
}

fn put_text(out: &mut Vec<u8>, text: &str) {
    out.extend_from_slice(&(text.len() as u32).to_le_bytes());
    out.extend_from_slice(text.as_bytes());
}

fn put_bytes(out: &mut Vec<u8>, bytes: &[u8]) {
    out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
    out.extend_from_slice(bytes);
}

fn put_geometry(out: &mut Vec<u8>, g: &VolumeGeometry) {
    for n in g.dims {
        out.extend_from_slice(&(n as u64).to_le_bytes());
    }
    let floats = g
        .spacing_mm
        .iter()
        .chain(&g.origin_lps_mm)
        .chain(g.direction_lps.iter().flatten());
    for v in floats {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

fn read_u32(r: &mut impl Read) -> std::io::Result<u32> {
    let mut b = [0u8; 4];
    r.read_exact(&mut b)?;
    Ok(u32::from_le_bytes(b))
}

fn read_u64(r: &mut impl Read) -> std::io::Result<u64> {
    let mut b = [0u8; 8];
    r.read_exact(&mut b)?;
    Ok(u64::from_le_bytes(b))
}

/// A length-prefixed text of the header, its length checked against [`MAX_TEXT_BYTES`] and
/// the file's before it is read.
fn read_text(file: &mut std::fs::File, file_len: u64) -> std::result::Result<String, String> {
    let len = read_u32(file).map_err(|_| "header cut short".to_string())?;
    let at = file.stream_position().map_err(|e| e.to_string())?;
    if len > MAX_TEXT_BYTES || at + u64::from(len) > file_len {
        return Err(format!("a header text of {len} bytes runs past the file"));
    }
    let mut bytes = vec![0u8; len as usize];
    file.read_exact(&mut bytes)
        .map_err(|_| "header cut short".to_string())?;
    String::from_utf8(bytes).map_err(|_| "a header text is not UTF-8".into())
}

/// The payload, read front to back; every field is checked against what is left.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> std::result::Result<&'a [u8], String> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.bytes.len())
            .ok_or_else(|| format!("cut short at byte {} of the payload", self.at))?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }

    fn u64(&mut self) -> std::result::Result<u64, String> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }

    fn f64(&mut self) -> std::result::Result<f64, String> {
        Ok(f64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }

    fn usize(&mut self) -> std::result::Result<usize, String> {
        usize::try_from(self.u64()?).map_err(|_| "a count beyond this machine's range".into())
    }

    fn bytes_field(&mut self) -> std::result::Result<&'a [u8], String> {
        let n = self.usize()?;
        self.take(n)
    }
}

fn take_geometry(r: &mut Reader) -> std::result::Result<VolumeGeometry, String> {
    let dims = [r.usize()?, r.usize()?, r.usize()?];
    let mut f = [0f64; 15];
    for v in &mut f {
        *v = r.f64()?;
    }
    Ok(VolumeGeometry {
        dims,
        spacing_mm: [f[0], f[1], f[2]],
        origin_lps_mm: [f[3], f[4], f[5]],
        direction_lps: [
            [f[6], f[7], f[8]],
            [f[9], f[10], f[11]],
            [f[12], f[13], f[14]],
        ],
    })
}

fn take_wall(r: &mut Reader) -> std::result::Result<PrebuiltWall, String> {
    let origin_m = Vector3::new(r.f64()?, r.f64()?, r.f64()?);
    let spacing_m = r.f64()?;
    let samples = [r.usize()?, r.usize()?, r.usize()?];
    let contact_voxels = r.usize()?;
    let n = samples
        .iter()
        .try_fold(1usize, |acc, &s| acc.checked_mul(s))
        .and_then(|n| n.checked_mul(4))
        .ok_or("a wall field too large to address")?;
    // The samples' bytes are taken (checked against what is left) before any allocation.
    let raw = r.take(n)?;
    let values = raw
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
        .collect();
    let field = SignedDistanceField::scaled(origin_m, [spacing_m; 3], samples, values, spacing_m)
        .map_err(|e| format!("wall field: {e}"))?;
    Ok(PrebuiltWall {
        field,
        contact_voxels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_lengths_round_trip_and_refuse_what_does_not_fit_the_grid() {
        let mut data = vec![0u8; 1000];
        data[10..300].fill(1);
        data[300..301].fill(2);
        data[999] = 1;
        let coded = run_length_encode(&data);
        assert!(coded.len() < 20, "{}", coded.len());
        assert_eq!(run_length_decode(&coded, 1000, 2).unwrap(), data);
        assert!(run_length_decode(&coded, 999, 2)
            .unwrap_err()
            .contains("more than"));
        assert!(run_length_decode(&coded, 1001, 2)
            .unwrap_err()
            .contains("cover 1000"));
        assert!(run_length_decode(&coded, 1000, 1)
            .unwrap_err()
            .contains("label 2"));
        assert!(run_length_decode(&coded[..coded.len() - 1], 1000, 2).is_err());
        // A run claiming 2⁶³ voxels allocates nothing.
        let huge = [0u8, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f];
        assert!(run_length_decode(&huge, 1000, 2).is_err());
        assert!(run_length_encode(&[]).is_empty());
    }

    /// The phantom CT ingested at 12 mm, and its ingest written to a scratch file.
    fn phantom_ingest(
        name: &str,
    ) -> (
        LoadedScan,
        IngestSettings,
        IngestOutcome,
        std::path::PathBuf,
    ) {
        let ct = Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz");
        let scan = crate::ingest::scan::load_ct(&ct).unwrap();
        let mut settings = IngestSettings::default();
        settings.model.element_size_mm = 12.0;
        let outcome = crate::ingest::ingest_scan(&scan, &settings).unwrap();
        let path =
            std::env::temp_dir().join(format!("lm-stored-{name}-{}.bin", std::process::id()));
        let bytes = write_stored_ingest(&path, "key", &scan.ct.geometry, &outcome).unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), bytes);
        (scan, settings, outcome, path)
    }

    fn read(
        path: &Path,
        key: &str,
        scan: &LoadedScan,
        settings: &IngestSettings,
    ) -> Result<IngestOutcome> {
        match read_stored_ingest(path, key, scan, settings, Cancel::NEVER)? {
            StoredIngest::Used(outcome) => Ok(*outcome),
            StoredIngest::OtherSettings => Err(Error::Ingest("other settings".into())),
        }
    }

    #[test]
    fn a_stored_ingest_gives_the_same_model_as_the_ingest_it_stores() {
        let (scan, settings, fresh, path) = phantom_ingest("same");
        let back = read(&path, "key", &scan, &settings).unwrap();
        let (s1, s2) = (&fresh.segmentation, &back.segmentation);
        assert_eq!(s1.lungs, s2.lungs);
        assert_eq!(s1.airways, s2.airways);
        assert_eq!(s1.body, s2.body);
        assert_eq!(s1.report.threshold_hu, s2.report.threshold_hu);
        let (m1, m2) = (&fresh.model, &back.model);
        assert_eq!(m1.mesh.mesh.elements, m2.mesh.mesh.elements);
        assert_eq!(m1.mesh.mesh.rest_positions_m, m2.mesh.mesh.rest_positions_m);
        assert_eq!(m1.mesh.mesh.node_mass_kg, m2.mesh.mesh.node_mass_kg);
        assert_eq!(m1.node_group, m2.node_group);
        assert_eq!(m1.element_lung, m2.element_lung);
        assert!(m1.wall.same_samples(&m2.wall));
        assert_eq!(m1.wall.origin_m, m2.wall.origin_m);
        assert_eq!(m1.groups_volume, m2.groups_volume);
        assert_eq!(m1.constraints.entries, m2.constraints.entries);
        assert_eq!(
            serde_json::to_value(&m1.report.group_nodes).unwrap(),
            serde_json::to_value(&m2.report.group_nodes).unwrap()
        );
        assert_eq!(fresh.summary.warnings, back.summary.warnings);
        assert!(back.summary.timings_s.contains_key("stored_ingest_read"));
        // Another key is told apart from a bad file.
        assert!(matches!(
            read_stored_ingest(&path, "other", &scan, &settings, Cancel::NEVER),
            Ok(StoredIngest::OtherSettings)
        ));
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn a_truncated_corrupt_foreign_or_newer_file_is_refused_by_name() {
        let (scan, settings, _, path) = phantom_ingest("bad");
        let good = std::fs::read(&path).unwrap();
        let refused = |bytes: &[u8], scan: &LoadedScan| -> String {
            std::fs::write(&path, bytes).unwrap();
            match read(&path, "key", scan, &settings) {
                Ok(_) => panic!("a spoiled file was used"),
                Err(e) => e.to_string(),
            }
        };
        let e = refused(&good[..good.len() - 1], &scan);
        assert!(e.contains("header announces"), "{e}");
        let e = refused(&good[..30], &scan);
        assert!(e.contains("header") || e.contains("runs past"), "{e}");
        let mut flipped = good.clone();
        let middle = flipped.len() / 2;
        flipped[middle] ^= 0x10;
        let e = refused(&flipped, &scan);
        assert!(e.contains("checksum"), "{e}");
        let mut newer = good.clone();
        newer[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        let e = refused(&newer, &scan);
        assert!(e.contains("format version"), "{e}");
        let e = refused(b"", &scan);
        assert!(e.contains("shorter than its header"), "{e}");
        // A header announcing a gigantic key allocates nothing.
        let mut long_key = good[..12].to_vec();
        long_key.extend_from_slice(&u32::MAX.to_le_bytes());
        let e = refused(&long_key, &scan);
        assert!(e.contains("runs past"), "{e}");
        // The file of another CT.
        let mut other = scan.clone();
        other.ct.geometry.origin_lps_mm[0] += 1.0;
        let e = refused(&good, &other);
        assert!(e.contains("CT grid"), "{e}");
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn a_wall_comes_back_bit_for_bit_through_f32_or_is_not_stored() {
        let s = 0.857_142_857_142_857_1e-3;
        let values: Vec<f64> = (0..1000)
            .map(|i| ((i as f32 - 500.0) * 0.731) as f64 * s)
            .collect();
        let wall = SignedDistanceField::new(Vector3::zeros(), [s; 3], [10, 10, 10], values.clone())
            .unwrap();
        let f = wall_as_f32(&wall).unwrap();
        let back: Vec<f64> = f.iter().map(|&x| x as f64 * s).collect();
        assert_eq!(back, values);
        let mut odd_values = values.clone();
        odd_values[3] = 0.1;
        let odd =
            SignedDistanceField::new(Vector3::zeros(), [s; 3], [10, 10, 10], odd_values).unwrap();
        assert!(wall_as_f32(&odd).is_none());
        // A wall held as scaled samples is stored as they are.
        let scaled =
            SignedDistanceField::scaled(Vector3::zeros(), [s; 3], [10, 10, 10], f.to_vec(), s)
                .unwrap();
        assert_eq!(*wall_as_f32(&scaled).unwrap(), *f);
        assert!(scaled.same_samples(&wall));
    }
}
