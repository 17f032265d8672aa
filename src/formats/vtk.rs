//! VTK XML meshes for ParaView: the hexahedral lung mesh as an UnstructuredGrid (`.vtu`) and
//! its external surface as PolyData quads (`.vtp`).
//!
//! Convention:
//! * Point coordinates are in **LPS millimetres**, DICOM patient space (+x patient left,
//!   +y posterior, +z superior), the frame of the CT the mesh was built from, so a mesh
//!   loads on top of the CT in ParaView or 3D Slicer (Slicer shows RAS: it flips x and y
//!   of LPS files itself only for formats that say so; load the CT in LPS too).
//! * Hexahedra are `VTK_HEXAHEDRON` (type 12) in VTK corner order (the order of
//!   [`HexMesh::elements`]); surface quads are ordered so their right-hand normal points
//!   out of the mesh.
//! * Arrays carry their unit in their name: `displacement_mm` (point data, 3 components,
//!   LPS mm, current minus rest position), `material_class` (cell data, index into
//!   [`HexMesh::classes`]), `node_id` (surface point data: index of the node in the hex
//!   mesh), `group` (surface cell data, constraint group code of the face).
//! * Encoding: `version="1.0"`, little endian, `header_type="UInt64"`, every DataArray
//!   `format="binary"`: base64 of an 8-byte length header (the number of data bytes),
//!   encoded separately, followed by the base64 of the data, uncompressed. Binary costs
//!   4/3 of the raw size (a 96 000-hexahedron, 103 000-node mesh is 14.8 MB); ASCII would
//!   cost 2–3 × more and lose exactness unless printed with 9 or 17 digits.
//! * Points are Float64 (round trip exact); connectivity and offsets Int64; data arrays
//!   Float32, UInt8 or Int32 scalars, or Float32 3-vectors.
//!
//! The readers parse exactly this layout (what the writers produce) and refuse anything
//! else with an error naming the file and the problem.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::Vector3;

use crate::durable::write_atomic;
use crate::model::HexMesh;
use crate::{Error, Result};

/// VTK cell type code of an 8-node hexahedron.
pub const VTK_HEXAHEDRON: u8 = 12;

/// Millimetres per metre: the mesh works in SI, files in the CT's millimetres.
const MM_PER_M: f64 = 1000.0;

/// Values attached to each point or each cell of a mesh.
#[derive(Debug, Clone, PartialEq)]
pub enum DataArray {
    /// One f32 per item (Float32).
    ScalarsF32(Vec<f32>),
    /// One u8 per item (UInt8), e.g. a group code.
    ScalarsU8(Vec<u8>),
    /// One i32 per item (Int32), e.g. an index.
    ScalarsI32(Vec<i32>),
    /// Three f32 per item (Float32, 3 components), e.g. a displacement in LPS mm.
    VectorsF32(Vec<[f32; 3]>),
}

impl DataArray {
    /// Number of items (points or cells) the array describes.
    pub fn len(&self) -> usize {
        match self {
            DataArray::ScalarsF32(v) => v.len(),
            DataArray::ScalarsU8(v) => v.len(),
            DataArray::ScalarsI32(v) => v.len(),
            DataArray::VectorsF32(v) => v.len(),
        }
    }

    /// Whether the array describes no item.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn vtk_type(&self) -> (&'static str, usize) {
        match self {
            DataArray::ScalarsF32(_) => ("Float32", 1),
            DataArray::ScalarsU8(_) => ("UInt8", 1),
            DataArray::ScalarsI32(_) => ("Int32", 1),
            DataArray::VectorsF32(_) => ("Float32", 3),
        }
    }

    fn encode(&self, b64: &mut Base64Writer) {
        match self {
            DataArray::ScalarsF32(v) => v.iter().for_each(|x| b64.push(&x.to_le_bytes())),
            DataArray::ScalarsU8(v) => b64.push(v),
            DataArray::ScalarsI32(v) => v.iter().for_each(|x| b64.push(&x.to_le_bytes())),
            DataArray::VectorsF32(v) => v.iter().flatten().for_each(|x| b64.push(&x.to_le_bytes())),
        }
    }

    fn byte_len(&self) -> usize {
        match self {
            DataArray::ScalarsF32(v) => v.len() * 4,
            DataArray::ScalarsU8(v) => v.len(),
            DataArray::ScalarsI32(v) => v.len() * 4,
            DataArray::VectorsF32(v) => v.len() * 12,
        }
    }
}

/// A hexahedral mesh ready for a `.vtu` file (points in LPS mm).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VtuMesh {
    /// Point coordinates in LPS millimetres.
    pub points_lps_mm: Vec<[f64; 3]>,
    /// Eight point indices per hexahedron, VTK corner order.
    pub cells: Vec<[u32; 8]>,
    /// Named arrays with one item per point.
    pub point_data: Vec<(String, DataArray)>,
    /// Named arrays with one item per cell.
    pub cell_data: Vec<(String, DataArray)>,
}

/// A quad surface ready for a `.vtp` file (points in LPS mm).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VtpSurface {
    /// Point coordinates in LPS millimetres.
    pub points_lps_mm: Vec<[f64; 3]>,
    /// Four point indices per quad, counter-clockwise seen from outside.
    pub quads: Vec<[u32; 4]>,
    /// Named arrays with one item per point.
    pub point_data: Vec<(String, DataArray)>,
    /// Named arrays with one item per quad.
    pub cell_data: Vec<(String, DataArray)>,
}

/// Writes a hexahedral mesh as a VTK XML UnstructuredGrid (`.vtu`), atomically.
pub fn write_vtu(path: &Path, mesh: &VtuMesh) -> Result<()> {
    let cells: Vec<&[u32]> = mesh.cells.iter().map(|c| c.as_slice()).collect();
    let xml = piece_xml(
        path,
        Kind::Unstructured,
        &mesh.points_lps_mm,
        &cells,
        &mesh.point_data,
        &mesh.cell_data,
    )?;
    write_atomic(path, xml.as_bytes())
}

/// Writes a quad surface as VTK XML PolyData (`.vtp`), atomically.
pub fn write_vtp_surface(path: &Path, surface: &VtpSurface) -> Result<()> {
    let cells: Vec<&[u32]> = surface.quads.iter().map(|c| c.as_slice()).collect();
    let xml = piece_xml(
        path,
        Kind::Poly,
        &surface.points_lps_mm,
        &cells,
        &surface.point_data,
        &surface.cell_data,
    )?;
    write_atomic(path, xml.as_bytes())
}

/// Reads a `.vtu` written by [`write_vtu`].
pub fn read_vtu(path: &Path) -> Result<VtuMesh> {
    let text = read_text(path)?;
    let piece = parse_piece(&text, Kind::Unstructured, &path.display().to_string())?;
    Ok(VtuMesh {
        points_lps_mm: piece.points,
        cells: piece.cells,
        point_data: piece.point_data,
        cell_data: piece.cell_data,
    })
}

/// Reads a `.vtp` written by [`write_vtp_surface`].
pub fn read_vtp_surface(path: &Path) -> Result<VtpSurface> {
    let text = read_text(path)?;
    let piece = parse_piece(&text, Kind::Poly, &path.display().to_string())?;
    Ok(VtpSurface {
        points_lps_mm: piece.points,
        quads: piece.cells,
        point_data: piece.point_data,
        cell_data: piece.cell_data,
    })
}

/// The mesh at `positions_m` (metres, LPS) as a `.vtu` mesh in millimetres, with point data
/// `displacement_mm` (position − rest position) and cell data `material_class`.
pub fn vtu_from_hex_mesh(mesh: &HexMesh, positions_m: &[Vector3<f64>]) -> Result<VtuMesh> {
    check_positions(mesh, positions_m)?;
    let class = mesh.element_class.iter().map(|&c| c as i32).collect();
    Ok(VtuMesh {
        points_lps_mm: positions_m.iter().map(|p| (p * MM_PER_M).into()).collect(),
        cells: mesh.elements.clone(),
        point_data: vec![(
            "displacement_mm".into(),
            DataArray::VectorsF32(
                positions_m
                    .iter()
                    .zip(&mesh.rest_positions_m)
                    .map(|(p, r)| ((p - r) * MM_PER_M).map(|v| v as f32).into())
                    .collect(),
            ),
        )],
        cell_data: vec![("material_class".into(), DataArray::ScalarsI32(class))],
    })
}

/// The external surface of the mesh at `positions_m` as quads in millimetres: only the
/// surface nodes are kept (point data `node_id` maps them back, `displacement_mm` as in
/// [`vtu_from_hex_mesh`]); `face_group`, one code per [`HexMesh::external_faces`] entry,
/// becomes cell data `group`.
pub fn surface_from_hex_mesh(
    mesh: &HexMesh,
    positions_m: &[Vector3<f64>],
    face_group: Option<&[u8]>,
) -> Result<VtpSurface> {
    check_positions(mesh, positions_m)?;
    if let Some(g) = face_group {
        if g.len() != mesh.external_faces.len() {
            return Err(Error::InvalidInput(format!(
                "{} face groups for {} external faces",
                g.len(),
                mesh.external_faces.len()
            )));
        }
    }
    let nodes = mesh.surface_nodes();
    let mut compact = vec![u32::MAX; mesh.node_count()];
    for (new, &old) in nodes.iter().enumerate() {
        compact[old as usize] = new as u32;
    }
    let quads = mesh
        .external_faces
        .iter()
        .map(|f| f.map(|n| compact[n as usize]))
        .collect();
    let mut cell_data = Vec::new();
    if let Some(g) = face_group {
        cell_data.push(("group".to_string(), DataArray::ScalarsU8(g.to_vec())));
    }
    Ok(VtpSurface {
        points_lps_mm: nodes
            .iter()
            .map(|&n| (positions_m[n as usize] * MM_PER_M).into())
            .collect(),
        quads,
        point_data: vec![
            (
                "node_id".into(),
                DataArray::ScalarsI32(nodes.iter().map(|&n| n as i32).collect()),
            ),
            (
                "displacement_mm".into(),
                DataArray::VectorsF32(
                    nodes
                        .iter()
                        .map(|&n| {
                            let d = positions_m[n as usize] - mesh.rest_positions_m[n as usize];
                            (d * MM_PER_M).map(|v| v as f32).into()
                        })
                        .collect(),
                ),
            ),
        ],
        cell_data,
    })
}

fn check_positions(mesh: &HexMesh, positions_m: &[Vector3<f64>]) -> Result<()> {
    if positions_m.len() != mesh.node_count() {
        return Err(Error::InvalidInput(format!(
            "{} positions for a mesh of {} nodes",
            positions_m.len(),
            mesh.node_count()
        )));
    }
    if let Some(n) = positions_m
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(Error::InvalidInput(format!(
            "node {n} has a non-finite position"
        )));
    }
    Ok(())
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Unstructured,
    Poly,
}

impl Kind {
    fn file_type(self) -> &'static str {
        match self {
            Kind::Unstructured => "UnstructuredGrid",
            Kind::Poly => "PolyData",
        }
    }

    fn cell_section(self) -> &'static str {
        match self {
            Kind::Unstructured => "Cells",
            Kind::Poly => "Polys",
        }
    }
}

fn piece_xml(
    path: &Path,
    kind: Kind,
    points: &[[f64; 3]],
    cells: &[&[u32]],
    point_data: &[(String, DataArray)],
    cell_data: &[(String, DataArray)],
) -> Result<String> {
    let bad = |m: String| Error::InvalidInput(format!("{}: {m}", path.display()));
    if let Some(n) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(bad(format!("point {n} is not finite")));
    }
    for (c, corners) in cells.iter().enumerate() {
        if let Some(&n) = corners.iter().find(|&&n| n as usize >= points.len()) {
            return Err(bad(format!(
                "cell {c} refers to point {n}, but there are {} points",
                points.len()
            )));
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
                return Err(bad(format!(
                    "{what} data name {name:?} is empty or has XML special characters"
                )));
            }
            if arrays[..a].iter().any(|(n, _)| n == name) {
                return Err(bad(format!("{what} data {name:?} appears twice")));
            }
            if array.len() != count {
                return Err(bad(format!(
                    "{what} data {name:?} has {} items for {count} {what}s",
                    array.len()
                )));
            }
        }
    }

    let mut xml = String::with_capacity(
        64 * (points.len() + cells.len())
            + point_data
                .iter()
                .chain(cell_data)
                .map(|(_, a)| a.byte_len() * 4 / 3 + 200)
                .sum::<usize>(),
    );
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
                "    <Piece NumberOfPoints=\"{}\" NumberOfCells=\"{}\">",
                points.len(),
                cells.len()
            );
        }
        Kind::Poly => {
            let _ = writeln!(
                xml,
                "    <Piece NumberOfPoints=\"{}\" NumberOfVerts=\"0\" NumberOfLines=\"0\" \
                 NumberOfStrips=\"0\" NumberOfPolys=\"{}\">",
                points.len(),
                cells.len()
            );
        }
    }
    for (section, arrays) in [("PointData", point_data), ("CellData", cell_data)] {
        let _ = writeln!(xml, "      <{section}>");
        for (name, array) in arrays {
            let (ty, nc) = array.vtk_type();
            data_array(&mut xml, ty, name, nc, array.byte_len(), |b| {
                array.encode(b)
            });
        }
        let _ = writeln!(xml, "      </{section}>");
    }
    xml.push_str("      <Points>\n");
    data_array(&mut xml, "Float64", "Points", 3, points.len() * 24, |b| {
        points
            .iter()
            .flatten()
            .for_each(|v| b.push(&v.to_le_bytes()))
    });
    xml.push_str("      </Points>\n");
    let section = kind.cell_section();
    let _ = writeln!(xml, "      <{section}>");
    let n_corners = cells.iter().map(|c| c.len()).sum::<usize>();
    data_array(&mut xml, "Int64", "connectivity", 1, n_corners * 8, |b| {
        cells
            .iter()
            .flat_map(|c| c.iter())
            .for_each(|&n| b.push(&i64::from(n).to_le_bytes()))
    });
    data_array(&mut xml, "Int64", "offsets", 1, cells.len() * 8, |b| {
        let mut end = 0i64;
        for c in cells {
            end += c.len() as i64;
            b.push(&end.to_le_bytes());
        }
    });
    if kind == Kind::Unstructured {
        data_array(&mut xml, "UInt8", "types", 1, cells.len(), |b| {
            cells.iter().for_each(|_| b.push(&[VTK_HEXAHEDRON]))
        });
    }
    let _ = writeln!(xml, "      </{section}>");
    xml.push_str("    </Piece>\n");
    let _ = writeln!(xml, "  </{ft}>");
    xml.push_str("</VTKFile>\n");
    Ok(xml)
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

const BASE64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// Streams bytes into base64 text, so arrays are encoded without an intermediate buffer.
struct Base64Writer<'a> {
    out: &'a mut String,
    pending: [u8; 3],
    n_pending: usize,
}

impl<'a> Base64Writer<'a> {
    fn new(out: &'a mut String) -> Self {
        Base64Writer {
            out,
            pending: [0; 3],
            n_pending: 0,
        }
    }

    fn push(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.pending[self.n_pending] = b;
            self.n_pending += 1;
            if self.n_pending == 3 {
                self.emit();
            }
        }
    }

    fn emit(&mut self) {
        let [a, b, c] = self.pending;
        let chars = [
            a >> 2,
            ((a & 3) << 4) | (b >> 4),
            ((b & 15) << 2) | (c >> 6),
            c & 63,
        ];
        for (i, &s) in chars.iter().enumerate() {
            // A partial group keeps n+1 characters and pads the rest.
            if i <= self.n_pending {
                self.out.push(BASE64[s as usize] as char);
            } else {
                self.out.push('=');
            }
        }
        self.pending = [0; 3];
        self.n_pending = 0;
    }

    fn finish(mut self) {
        if self.n_pending > 0 {
            self.emit();
        }
    }
}

/// Decodes base64 text (padding allowed only at the end); `None` if it is not base64.
fn base64_decode(text: &[u8]) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(4) {
        return None;
    }
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let value = |c: u8| -> Option<u8> {
        match c {
            b'A'..=b'Z' => Some(c - b'A'),
            b'a'..=b'z' => Some(c - b'a' + 26),
            b'0'..=b'9' => Some(c - b'0' + 52),
            b'+' => Some(62),
            b'/' => Some(63),
            _ => None,
        }
    };
    let groups = text.len() / 4;
    for (g, quad) in text.chunks_exact(4).enumerate() {
        let pad = quad.iter().rev().take_while(|&&c| c == b'=').count();
        if pad > 2 || (pad > 0 && g + 1 != groups) {
            return None;
        }
        let mut v = [0u8; 4];
        for (i, &c) in quad[..4 - pad].iter().enumerate() {
            v[i] = value(c)?;
        }
        let bytes = [
            (v[0] << 2) | (v[1] >> 4),
            (v[1] << 4) | (v[2] >> 2),
            (v[2] << 6) | v[3],
        ];
        out.extend_from_slice(&bytes[..3 - pad]);
    }
    Some(out)
}

fn read_text(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path)
        .map_err(|e| Error::InvalidInput(format!("{}: cannot read: {e}", path.display())))?;
    String::from_utf8(bytes)
        .map_err(|_| Error::InvalidInput(format!("{}: not a text (XML) file", path.display())))
}

/// A parsed piece before its connectivity is cut into fixed-size cells.
struct Piece<const N: usize> {
    points: Vec<[f64; 3]>,
    cells: Vec<[u32; N]>,
    point_data: Vec<(String, DataArray)>,
    cell_data: Vec<(String, DataArray)>,
}

/// One XML tag: its name, attributes and whether it opens, closes or is empty.
struct Tag<'a> {
    name: &'a str,
    attrs: Vec<(&'a str, &'a str)>,
    closing: bool,
    empty: bool,
}

impl<'a> Tag<'a> {
    fn attr(&self, key: &str) -> Option<&'a str> {
        self.attrs.iter().find(|(k, _)| *k == key).map(|(_, v)| *v)
    }
}

fn parse_tag(inner: &str) -> Option<Tag<'_>> {
    let closing = inner.starts_with('/');
    let empty = inner.ends_with('/');
    let body = inner.trim_start_matches('/').trim_end_matches('/').trim();
    let name_end = body.find(char::is_whitespace).unwrap_or(body.len());
    let name = &body[..name_end];
    let mut rest = body[name_end..].trim_start();
    let mut attrs = Vec::new();
    while !rest.is_empty() {
        let eq = rest.find('=')?;
        let key = rest[..eq].trim();
        let after = rest[eq + 1..].trim_start();
        let quote = after.chars().next().filter(|&q| q == '"' || q == '\'')?;
        let close = after[1..].find(quote)? + 1;
        attrs.push((key, &after[1..close]));
        rest = after[close + 1..].trim_start();
    }
    (!name.is_empty()).then_some(Tag {
        name,
        attrs,
        closing,
        empty,
    })
}

fn parse_piece<const N: usize>(text: &str, kind: Kind, what: &str) -> Result<Piece<N>> {
    let bad = |m: String| Error::InvalidInput(format!("{what}: {m}"));
    let mut stack: Vec<&str> = Vec::new();
    let mut pos = 0;
    let mut n_points: Option<usize> = None;
    let mut n_cells: Option<usize> = None;
    let mut points = None;
    let mut connectivity = None;
    let mut offsets = None;
    let mut types = None;
    let mut point_data = Vec::new();
    let mut cell_data = Vec::new();
    let mut seen_root = false;
    while let Some(lt) = text[pos..].find('<').map(|i| pos + i) {
        let rest = &text[lt..];
        if rest.starts_with("<?") || rest.starts_with("<!--") {
            let end = if rest.starts_with("<?") { "?>" } else { "-->" };
            pos = lt
                + rest
                    .find(end)
                    .ok_or_else(|| bad("unterminated XML declaration or comment".into()))?
                + end.len();
            continue;
        }
        let gt = rest
            .find('>')
            .ok_or_else(|| bad("unterminated XML tag (truncated file?)".into()))?;
        let tag = parse_tag(&rest[1..gt])
            .ok_or_else(|| bad(format!("malformed XML tag <{}>", &rest[1..gt])))?;
        pos = lt + gt + 1;
        if tag.closing {
            match stack.pop() {
                Some(open) if open == tag.name => continue,
                other => {
                    return Err(bad(format!(
                        "</{}> closes <{}>",
                        tag.name,
                        other.unwrap_or("nothing")
                    )))
                }
            }
        }
        match tag.name {
            "VTKFile" => {
                let expect = [
                    ("type", kind.file_type()),
                    ("byte_order", "LittleEndian"),
                    ("header_type", "UInt64"),
                ];
                for (key, want) in expect {
                    if tag.attr(key) != Some(want) {
                        return Err(bad(format!(
                            "VTKFile {key}={:?}, expected {want:?} (only files written by \
                             lungmotion are read)",
                            tag.attr(key).unwrap_or("")
                        )));
                    }
                }
                if let Some(c) = tag.attr("compressor") {
                    return Err(bad(format!("compressed data ({c}) is not supported")));
                }
                seen_root = true;
            }
            "Piece" => {
                if n_points.is_some() {
                    return Err(bad("more than one Piece is not supported".into()));
                }
                let count = |key: &str| -> Result<usize> {
                    tag.attr(key)
                        .and_then(|v| v.trim().parse().ok())
                        .ok_or_else(|| bad(format!("Piece has no valid {key}")))
                };
                n_points = Some(count("NumberOfPoints")?);
                n_cells = Some(match kind {
                    Kind::Unstructured => count("NumberOfCells")?,
                    Kind::Poly => {
                        for other in ["NumberOfVerts", "NumberOfLines", "NumberOfStrips"] {
                            if tag.attr(other).is_some_and(|v| v.trim() != "0") {
                                return Err(bad(format!("{other} is not 0: only quads are read")));
                            }
                        }
                        count("NumberOfPolys")?
                    }
                });
            }
            "DataArray" => {
                if !seen_root || n_points.is_none() {
                    return Err(bad("DataArray outside a Piece".into()));
                }
                let body_end = text[pos..]
                    .find('<')
                    .map(|i| pos + i)
                    .ok_or_else(|| bad("DataArray has no end (truncated file?)".into()))?;
                let body = if tag.empty { "" } else { &text[pos..body_end] };
                let name = tag.attr("Name").unwrap_or("");
                let array = decode_array(&tag, body).map_err(|m| bad(format!("{name}: {m}")))?;
                let parent = stack.last().copied().unwrap_or("");
                let section = kind.cell_section();
                match (parent, name) {
                    ("Points", _) => points = Some(array),
                    (s, "connectivity") if s == section => connectivity = Some(array),
                    (s, "offsets") if s == section => offsets = Some(array),
                    (s, "types") if s == section && kind == Kind::Unstructured => {
                        types = Some(array)
                    }
                    ("PointData" | "CellData", _) => {
                        let data = array.into_data().map_err(|m| bad(format!("{name}: {m}")))?;
                        if parent == "PointData" {
                            point_data.push((name.to_string(), data));
                        } else {
                            cell_data.push((name.to_string(), data));
                        }
                    }
                    _ => return Err(bad(format!("unexpected DataArray {name:?} in <{parent}>"))),
                }
            }
            _ => {}
        }
        if !tag.empty {
            stack.push(tag.name);
        }
    }
    if !seen_root {
        return Err(bad("not a VTK XML file (no VTKFile element)".into()));
    }
    if !stack.is_empty() {
        return Err(bad(format!(
            "<{}> is never closed (truncated file?)",
            stack.join("><")
        )));
    }
    let n_points = n_points.ok_or_else(|| bad("no Piece".into()))?;
    let n_cells = n_cells.unwrap_or(0);

    let points = match points {
        Some(Raw::F64(v, 3)) if v.len() == 3 * n_points => v
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect::<Vec<_>>(),
        Some(_) => return Err(bad(format!("Points must be {n_points} Float64 triples"))),
        None => return Err(bad("no Points".into())),
    };
    let connectivity = match connectivity {
        Some(Raw::I64(v, 1)) if v.len() == N * n_cells => v,
        Some(_) => {
            return Err(bad(format!(
                "connectivity must be {} Int64 ({n_cells} cells of {N} corners)",
                N * n_cells
            )))
        }
        None => return Err(bad("no connectivity".into())),
    };
    match offsets {
        Some(Raw::I64(v, 1))
            if v.len() == n_cells
                && v.iter()
                    .enumerate()
                    .all(|(c, &o)| o == (N * (c + 1)) as i64) => {}
        Some(_) => {
            return Err(bad(format!(
                "offsets must be Int64 multiples of {N}: only cells of {N} corners are read"
            )))
        }
        None => return Err(bad("no offsets".into())),
    }
    if kind == Kind::Unstructured {
        match types {
            Some(Raw::U8(v, 1)) if v.len() == n_cells && v.iter().all(|&t| t == VTK_HEXAHEDRON) => {
            }
            Some(_) => {
                return Err(bad(format!(
                    "cell types must be {n_cells} UInt8 of value {VTK_HEXAHEDRON} (hexahedra)"
                )))
            }
            None => return Err(bad("no cell types".into())),
        }
    }
    let mut cells = Vec::with_capacity(n_cells);
    for (c, corners) in connectivity.chunks_exact(N).enumerate() {
        let mut cell = [0u32; N];
        for (slot, &n) in cell.iter_mut().zip(corners) {
            if n < 0 || n as usize >= n_points {
                return Err(bad(format!(
                    "cell {c} refers to point {n}, but there are {n_points} points"
                )));
            }
            *slot = n as u32;
        }
        cells.push(cell);
    }
    for (what_data, arrays, count) in [
        ("point", &point_data, n_points),
        ("cell", &cell_data, n_cells),
    ] {
        if let Some((name, a)) = arrays.iter().find(|(_, a)| a.len() != count) {
            return Err(bad(format!(
                "{what_data} data {name:?} has {} items for {count} {what_data}s",
                a.len()
            )));
        }
    }
    Ok(Piece {
        points,
        cells,
        point_data,
        cell_data,
    })
}

/// A decoded DataArray with its component count.
enum Raw {
    F32(Vec<f32>, usize),
    F64(Vec<f64>, usize),
    U8(Vec<u8>, usize),
    I32(Vec<i32>, usize),
    I64(Vec<i64>, usize),
}

impl Raw {
    fn into_data(self) -> std::result::Result<DataArray, String> {
        match self {
            Raw::F32(v, 1) => Ok(DataArray::ScalarsF32(v)),
            Raw::F32(v, 3) => Ok(DataArray::VectorsF32(
                v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
            )),
            Raw::U8(v, 1) => Ok(DataArray::ScalarsU8(v)),
            Raw::I32(v, 1) => Ok(DataArray::ScalarsI32(v)),
            _ => Err(
                "data arrays must be Float32, UInt8 or Int32 scalars or Float32 3-vectors".into(),
            ),
        }
    }
}

fn decode_array(tag: &Tag, body: &str) -> std::result::Result<Raw, String> {
    if tag.attr("format") != Some("binary") {
        return Err(format!(
            "format {:?} is not supported (only \"binary\")",
            tag.attr("format").unwrap_or("")
        ));
    }
    let components: usize = tag
        .attr("NumberOfComponents")
        .unwrap_or("1")
        .trim()
        .parse()
        .ok()
        .filter(|&c| c == 1 || c == 3)
        .ok_or("NumberOfComponents must be 1 or 3")?;
    let b64: Vec<u8> = body.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
    // The 8-byte length header is its own base64 block of 12 characters.
    if b64.len() < 12 {
        return Err("binary data has no length header".into());
    }
    let header = base64_decode(&b64[..12]).ok_or("length header is not base64")?;
    let byte_len = u64::from_le_bytes(header[..8].try_into().map_err(|_| "short header")?);
    let data = base64_decode(&b64[12..]).ok_or("data are not base64")?;
    if data.len() as u64 != byte_len {
        return Err(format!(
            "header announces {byte_len} bytes but {} are encoded",
            data.len()
        ));
    }
    let ty = tag.attr("type").unwrap_or("");
    let size = match ty {
        "Float32" | "Int32" => 4,
        "Float64" | "Int64" => 8,
        "UInt8" => 1,
        other => return Err(format!("type {other:?} is not supported")),
    };
    if !data.len().is_multiple_of(size * components) {
        return Err(format!(
            "{} bytes is not a whole number of {ty} {components}-tuples",
            data.len()
        ));
    }
    Ok(match ty {
        "Float32" => Raw::F32(
            data.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            components,
        ),
        "Int32" => Raw::I32(
            data.chunks_exact(4)
                .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            components,
        ),
        "Float64" => Raw::F64(
            data.chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
                .collect(),
            components,
        ),
        "Int64" => Raw::I64(
            data.chunks_exact(8)
                .map(|c| i64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
                .collect(),
            components,
        ),
        _ => Raw::U8(data, components),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        let cases: [(&[u8], &str); 4] = [
            (b"", ""),
            (b"f", "Zg=="),
            (b"fo", "Zm8="),
            (b"foobar", "Zm9vYmFy"),
        ];
        for (raw, text) in cases {
            let mut s = String::new();
            let mut w = Base64Writer::new(&mut s);
            w.push(raw);
            w.finish();
            assert_eq!(s, text);
            assert_eq!(base64_decode(text.as_bytes()).unwrap(), raw);
        }
        assert!(base64_decode(b"Zg==Zg==").is_none());
        assert!(base64_decode(b"Z!==").is_none());
    }
}
