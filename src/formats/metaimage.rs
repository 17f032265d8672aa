//! MetaImage (`.mha`, header and data in one file), as ITK, elastix and 3D Slicer read it.
//!
//! Convention: MetaImage lives in LPS like DICOM (ITK's native frame), so nothing flips:
//! `Offset` is the LPS position of voxel (0, 0, 0) in mm, `ElementSpacing` the spacing,
//! `TransformMatrix` the three axis directions one after the other (i, then j, then k — the
//! columns of our direction matrix, as ITK's MetaImageIO reads them). Vector images (a
//! displacement field) store `ElementNumberOfChannels = 3` interleaved per voxel, components
//! in LPS millimetres. Data are little-endian float32, uncompressed.

use std::path::Path;

use crate::durable::write_atomic;
use crate::volume::VolumeGeometry;
use crate::{Error, IoContext, IoOp, Result};

/// Most channels per voxel read (a displacement field has 3, a tensor image 9).
const MAX_CHANNELS: usize = 16;
/// Longest header searched for ElementDataFile; ITK's headers are under a kilobyte.
const MAX_HEADER_BYTES: usize = 1 << 20;

/// Writes float32 voxels with `channels` components each (1 for a scalar image, 3 for a field).
pub fn write_mha(
    path: &Path,
    geometry: &VolumeGeometry,
    channels: usize,
    values: &[f32],
    description: &str,
) -> Result<()> {
    if values.len() != geometry.voxel_count() * channels {
        return Err(Error::Argument {
            what: "MetaImage values".into(),
            reason: format!(
                "{} values for {} voxels × {channels} channels",
                values.len(),
                geometry.voxel_count()
            ),
        });
    }
    let d = geometry.direction_lps;
    let join = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let mut header = String::new();
    header.push_str("ObjectType = Image\nNDims = 3\n");
    header.push_str(&format!("Comment = {}\n", description.replace('\n', " ")));
    header.push_str("BinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = False\n");
    header.push_str(&format!(
        "TransformMatrix = {}\n",
        join(&[d[0], d[1], d[2]].concat())
    ));
    header.push_str(&format!("Offset = {}\n", join(&geometry.origin_lps_mm)));
    header.push_str("CenterOfRotation = 0 0 0\nAnatomicalOrientation = RAI\n");
    header.push_str(&format!(
        "ElementSpacing = {}\n",
        join(&geometry.spacing_mm)
    ));
    header.push_str(&format!(
        "DimSize = {} {} {}\n",
        geometry.dims[0], geometry.dims[1], geometry.dims[2]
    ));
    if channels != 1 {
        header.push_str(&format!("ElementNumberOfChannels = {channels}\n"));
    }
    header.push_str("ElementType = MET_FLOAT\nElementDataFile = LOCAL\n");
    let mut bytes = header.into_bytes();
    bytes.reserve(values.len() * 4);
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    write_atomic(path, &bytes)
}

/// Reads a float32 MetaImage written as [`write_mha`] writes it: geometry, channels, values.
pub fn read_mha(path: &Path) -> Result<(VolumeGeometry, usize, Vec<f32>)> {
    let bad = |m: String| Error::scan(path, m);
    let bytes = std::fs::read(path).at(IoOp::Read, path)?;
    let mut pos = 0;
    let mut fields = std::collections::HashMap::new();
    let searched = &bytes[..bytes.len().min(MAX_HEADER_BYTES)];
    loop {
        let end = searched[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| {
                bad(format!(
                    "header ends before ElementDataFile (searched {} bytes)",
                    searched.len()
                ))
            })?
            + pos;
        let line = String::from_utf8_lossy(&bytes[pos..end]).trim().to_string();
        pos = end + 1;
        let Some((k, v)) = line.split_once('=') else {
            return Err(bad(format!("header line '{line}' is not 'key = value'")));
        };
        let (k, v) = (k.trim().to_string(), v.trim().to_string());
        let last = k == "ElementDataFile";
        fields.insert(k, v);
        if last {
            break;
        }
    }
    let get = |k: &str| fields.get(k).ok_or_else(|| bad(format!("missing {k}")));
    let numbers = |k: &str, n: usize| -> Result<Vec<f64>> {
        let v: Vec<f64> = get(k)?
            .split_whitespace()
            .map(|x| {
                x.parse::<f64>()
                    .map_err(|_| bad(format!("{k}: '{x}' is not a number")))
            })
            .collect::<Result<_>>()?;
        if v.len() != n {
            return Err(bad(format!("{k} needs {n} numbers, has {}", v.len())));
        }
        Ok(v)
    };
    if get("NDims")? != "3"
        || get("ElementType")? != "MET_FLOAT"
        || get("ElementDataFile")? != "LOCAL"
    {
        return Err(bad(
            "only 3-D MET_FLOAT images with LOCAL data are read".into()
        ));
    }
    if fields.get("CompressedData").is_some_and(|v| v == "True")
        || fields
            .get("BinaryDataByteOrderMSB")
            .is_some_and(|v| v == "True")
    {
        return Err(bad("compressed or big-endian data are not read".into()));
    }
    let dims = whole_numbers(get("DimSize")?).map_err(|m| bad(format!("DimSize: {m}")))?;
    let t = numbers("TransformMatrix", 9)?;
    let geometry = VolumeGeometry {
        dims,
        spacing_mm: numbers("ElementSpacing", 3)?.try_into().unwrap(),
        origin_lps_mm: numbers("Offset", 3)?.try_into().unwrap(),
        direction_lps: [[t[0], t[1], t[2]], [t[3], t[4], t[5]], [t[6], t[7], t[8]]],
    };
    geometry.validate(&path.display().to_string())?;
    let channels = match fields.get("ElementNumberOfChannels") {
        Some(c) => c
            .parse::<usize>()
            .ok()
            .filter(|n| (1..=MAX_CHANNELS).contains(n))
            .ok_or_else(|| {
                bad(format!(
                    "ElementNumberOfChannels '{c}' is not a whole number from 1 to {MAX_CHANNELS}"
                ))
            })?,
        None => 1,
    };
    // validate() bounds the voxel count, MAX_CHANNELS the rest: no overflow.
    let expected = geometry.voxel_count() * channels * 4;
    let data = &bytes[pos..];
    if data.len() != expected {
        return Err(bad(format!(
            "{} data bytes where the header needs {expected} (truncated?)",
            data.len()
        )));
    }
    let values = data
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Ok((geometry, channels, values))
}

/// Three whole, non-negative numbers (`DimSize`); a fraction or a sign is an error, not
/// silently truncated.
fn whole_numbers(text: &str) -> std::result::Result<[usize; 3], String> {
    let parsed: Vec<usize> = text
        .split_whitespace()
        .map(|x| {
            x.parse::<usize>()
                .map_err(|_| format!("'{x}' is not a whole number of voxels"))
        })
        .collect::<std::result::Result<_, _>>()?;
    parsed
        .try_into()
        .map_err(|v: Vec<usize>| format!("needs 3 numbers, has {}", v.len()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vector_field_round_trips_with_an_oblique_geometry() {
        let (s, c) = (0.2f64.sin(), 0.2f64.cos());
        let g = VolumeGeometry {
            dims: [3, 4, 5],
            spacing_mm: [1.5, 2.0, 2.5],
            origin_lps_mm: [-10.0, 20.5, -300.25],
            direction_lps: [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]],
        };
        let values: Vec<f32> = (0..g.voxel_count() * 3)
            .map(|i| i as f32 * 0.25 - 7.0)
            .collect();
        let dir = std::env::temp_dir().join(format!("lm-mha-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("field.mha");
        write_mha(&path, &g, 3, &values, "displacement, LPS mm").unwrap();
        let (g2, ch, v2) = read_mha(&path).unwrap();
        assert_eq!(ch, 3);
        assert_eq!(v2, values);
        assert!(g2.same_grid(&g, 1e-9));
        let text = String::from_utf8_lossy(&std::fs::read(&path).unwrap()[..200]).to_string();
        assert!(text.contains("TransformMatrix = 0.98"), "{text}");
        // A truncated file is refused, naming the problem.
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 4]).unwrap();
        let e = read_mha(&path).unwrap_err().to_string();
        assert!(e.contains("truncated"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
