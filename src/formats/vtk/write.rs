//! Writing one VTK XML piece: checks, then the XML with binary (base64) DataArrays.

use std::fmt::Write as _;
use std::path::Path;

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
        "<VTKFile type=\"{ft}\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">"
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
            .for_each(|v| b.push(&v.to_le_bytes()))
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
            .for_each(|&n| b.push(&i64::from(n).to_le_bytes()))
    });
    data_array(xml, "Int64", "offsets", 1, cells.len() * 8, |b| {
        let mut end = 0i64;
        for c in cells {
            end += c.len() as i64;
            b.push(&end.to_le_bytes());
        }
    });
    if kind == Kind::Unstructured {
        data_array(xml, "UInt8", "types", 1, cells.len(), |b| {
            cells.iter().for_each(|_| b.push(&[VTK_HEXAHEDRON]))
        });
    }
    let _ = writeln!(xml, "      </{section}>");
}

/// Appends one binary DataArray element: the length header and the data are base64-encoded
/// separately, as VTK's reader expects for uncompressed binary data.
fn data_array(
    xml: &mut String,
    ty: &str,
    name: &str,
    components: usize,
    byte_len: usize,
    fill: impl FnOnce(&mut Base64Writer),
) {
    let _ = write!(
        xml,
        "        <DataArray type=\"{ty}\" Name=\"{name}\" NumberOfComponents=\"{components}\" \
         format=\"binary\">\n          "
    );
    let mut header = Base64Writer::new(xml);
    header.push(&(byte_len as u64).to_le_bytes());
    header.finish();
    let mut data = Base64Writer::new(xml);
    fill(&mut data);
    data.finish();
    xml.push_str("\n        </DataArray>\n");
}
