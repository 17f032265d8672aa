//! Writing one VTK XML piece: checks, then the XML with binary (base64) DataArrays.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use flate2::write::ZlibEncoder;
use flate2::Compression;
use rayon::prelude::*;

use super::base64::Base64Writer;
use super::{DataArray, Kind, VTK_HEXAHEDRON};
use crate::{Error, Result};

/// The XML of one piece: points, cells of any corner count and named point/cell arrays.
pub(super) fn piece_xml(
    path: &Path,
    kind: Kind,
    points: &[[f64; 3]],
    cells: &[&[u32]],
    point_data: &[(String, DataArray)],
    cell_data: &[(String, DataArray)],
) -> Result<String> {
    check_piece(points, cells, point_data, cell_data).map_err(|m| Error::format(path, m))?;
    let mut xml = String::with_capacity(
        64 * (points.len() + cells.len())
            + point_data
                .iter()
                .chain(cell_data)
                .map(|(_, a)| a.byte_len() * 4 / 3 + 200)
                .sum::<usize>(),
    );
    let ft = kind.file_type();
    open_piece(&mut xml, kind, points.len(), cells.len());
    write_data_sections(&mut xml, point_data, cell_data);
    write_points(&mut xml, points);
    write_cells(&mut xml, kind, cells);
    xml.push_str("    </Piece>\n");
    let _ = writeln!(xml, "  </{ft}>");
    xml.push_str("</VTKFile>\n");
    Ok(xml)
}

/// Refuses what ParaView would misread: non-finite points, cells naming missing points, and
/// array names that are empty, repeated, break the XML, or arrays of the wrong length.
fn check_piece(
    points: &[[f64; 3]],
    cells: &[&[u32]],
    point_data: &[(String, DataArray)],
    cell_data: &[(String, DataArray)],
) -> std::result::Result<(), String> {
    if let Some(n) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(format!("point {n} is not finite"));
    }
    for (c, corners) in cells.iter().enumerate() {
        if let Some(&n) = corners.iter().find(|&&n| n as usize >= points.len()) {
            return Err(format!(
                "cell {c} refers to point {n}, but there are {} points",
                points.len()
            ));
        }
    }
    for (what, arrays, count) in [
        ("point", point_data, points.len()),
        ("cell", cell_data, cells.len()),
    ] {
        for (a, (name, array)) in arrays.iter().enumerate() {
            if name.is_empty()
                || name
                    .chars()
                    .any(|c| matches!(c, '"' | '<' | '>' | '&' | '\'') || c.is_control())
            {
                return Err(format!(
                    "{what} data name {name:?} is empty or has XML special characters"
                ));
            }
            if arrays[..a].iter().any(|(n, _)| n == name) {
                return Err(format!("{what} data {name:?} appears twice"));
            }
            if array.len() != count {
                return Err(format!(
                    "{what} data {name:?} has {} items for {count} {what}s",
                    array.len()
                ));
            }
        }
    }
    Ok(())
}

/// The XML declaration, the VTKFile and dataset elements and the Piece element with its
/// counts (PolyData counts every cell kind; only polys are written).
fn open_piece(xml: &mut String, kind: Kind, n_points: usize, n_cells: usize) {
    let ft = kind.file_type();
    xml.push_str("<?xml version=\"1.0\"?>\n");
    xml.push_str("<!-- lungmotion: points in LPS millimetres (DICOM patient space) -->\n");
    let _ = writeln!(
        xml,
        "<VTKFile type=\"{ft}\" version=\"1.0\" byte_order=\"LittleEndian\" \
         header_type=\"UInt64\" compressor=\"vtkZLibDataCompressor\">"
    );
    let _ = writeln!(xml, "  <{ft}>");
    match kind {
        Kind::Unstructured => {
            let _ = writeln!(
                xml,
                "    <Piece NumberOfPoints=\"{n_points}\" NumberOfCells=\"{n_cells}\">",
            );
        }
        Kind::Poly => {
            let _ = writeln!(
                xml,
                "    <Piece NumberOfPoints=\"{n_points}\" NumberOfVerts=\"0\" NumberOfLines=\"0\" \
                 NumberOfStrips=\"0\" NumberOfPolys=\"{n_cells}\">",
            );
        }
    }
}

/// The PointData and CellData sections, one DataArray per named array.
fn write_data_sections(
    xml: &mut String,
    point_data: &[(String, DataArray)],
    cell_data: &[(String, DataArray)],
) {
    for (section, arrays) in [("PointData", point_data), ("CellData", cell_data)] {
        let _ = writeln!(xml, "      <{section}>");
        for (name, array) in arrays {
            let (ty, nc) = array.vtk_type();
            data_array(xml, ty, name, nc, array.byte_len(), |b| array.encode(b));
        }
        let _ = writeln!(xml, "      </{section}>");
    }
}

/// The Points section: Float64 triples, so coordinates round-trip exactly.
fn write_points(xml: &mut String, points: &[[f64; 3]]) {
    xml.push_str("      <Points>\n");
    data_array(xml, "Float64", "Points", 3, points.len() * 24, |b| {
        points
            .iter()
            .flatten()
            .for_each(|v| b.extend(v.to_le_bytes()))
    });
    xml.push_str("      </Points>\n");
}

/// The Cells (or Polys) section: Int64 connectivity and offsets, and for an
/// UnstructuredGrid the cell types (all hexahedra).
fn write_cells(xml: &mut String, kind: Kind, cells: &[&[u32]]) {
    let section = kind.cell_section();
    let _ = writeln!(xml, "      <{section}>");
    let n_corners = cells.iter().map(|c| c.len()).sum::<usize>();
    data_array(xml, "Int64", "connectivity", 1, n_corners * 8, |b| {
        cells
            .iter()
            .flat_map(|c| c.iter())
            .for_each(|&n| b.extend(i64::from(n).to_le_bytes()))
    });
    data_array(xml, "Int64", "offsets", 1, cells.len() * 8, |b| {
        let mut end = 0i64;
        for c in cells {
            end += c.len() as i64;
            b.extend(end.to_le_bytes());
        }
    });
    if kind == Kind::Unstructured {
        data_array(xml, "UInt8", "types", 1, cells.len(), |b| {
            b.resize(cells.len(), VTK_HEXAHEDRON)
        });
    }
    let _ = writeln!(xml, "      </{section}>");
}

/// Uncompressed bytes per zlib block (VTK's own default).
pub(super) const ZLIB_BLOCK_BYTES: usize = 1 << 15;

/// Appends one binary DataArray element in VTK's zlib layout: the header (block count,
/// block size, partial last block size, compressed sizes) and the concatenated zlib streams,
/// each base64-encoded on its own as VTK's reader expects.
fn data_array(
    xml: &mut String,
    ty: &str,
    name: &str,
    components: usize,
    byte_len: usize,
    fill: impl FnOnce(&mut Vec<u8>),
) {
    let _ = write!(
        xml,
        "        <DataArray type=\"{ty}\" Name=\"{name}\" NumberOfComponents=\"{components}\" \
         format=\"binary\">\n          "
    );
    let mut raw = Vec::with_capacity(byte_len);
    fill(&mut raw);
    debug_assert_eq!(raw.len(), byte_len);
    let blocks: Vec<Vec<u8>> = raw
        .par_chunks(ZLIB_BLOCK_BYTES)
        .map(|block| {
            let mut z = ZlibEncoder::new(Vec::with_capacity(block.len() / 2), Compression::new(6));
            // Writing into a Vec cannot fail.
            let _ = z.write_all(block);
            z.finish().unwrap_or_default()
        })
        .collect();
    let mut header = Base64Writer::new(xml);
    header.push(&(blocks.len() as u64).to_le_bytes());
    header.push(&(ZLIB_BLOCK_BYTES as u64).to_le_bytes());
    header.push(&((raw.len() % ZLIB_BLOCK_BYTES) as u64).to_le_bytes());
    for b in &blocks {
        header.push(&(b.len() as u64).to_le_bytes());
    }
    header.finish();
    let mut data = Base64Writer::new(xml);
    blocks.iter().for_each(|b| data.push(b));
    data.finish();
    xml.push_str("\n        </DataArray>\n");
}
