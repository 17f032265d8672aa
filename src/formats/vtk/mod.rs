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
//!   mesh), `group` (surface cell data, constraint group code of the face). The lung
//!   meshes add point data `group` and cell data `lung`
//!   ([`lung_mesh_vtu`](crate::outputs::ingest_files::lung_mesh_vtu)).
//! * Encoding: `version="1.0"`, little endian, `header_type="UInt64"`,
//!   `compressor="vtkZLibDataCompressor"`, every DataArray `format="binary"`: VTK's
//!   compressed layout, a header of UInt64s (number of blocks, uncompressed block size
//!   32 KiB, uncompressed size of a partial last block or 0, each block's compressed size)
//!   base64-encoded on its own, followed by the base64 of the zlib streams of the blocks,
//!   deflated in parallel. Uncompressed, a 72 000-hexahedron lung mesh took 13.6 MB (binary
//!   is 4/3 of the raw size; ASCII would cost 2–3 × more and lose exactness unless printed
//!   with 9 or 17 digits); connectivity and coordinates on a lattice compress several-fold.
//!   The reader also takes the same layout uncompressed (files of earlier versions): the
//!   8-byte length header, then the data.
//! * Points are Float64 (round trip exact); connectivity and offsets Int64; data arrays
//!   Float32, UInt8 or Int32 scalars, or Float32 3-vectors.
//!
//! The readers parse exactly this layout (what the writers produce) and refuse anything
//! else with an error naming the file and the problem.

mod base64;
mod read;
mod write;

use std::path::Path;

use nalgebra::Vector3;

use crate::durable::write_atomic;
use crate::model::HexMesh;
use crate::{Error, Result};

use read::{parse_piece, read_text};
use write::piece_xml;

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

    fn encode(&self, out: &mut Vec<u8>) {
        match self {
            DataArray::ScalarsF32(v) => v.iter().for_each(|x| out.extend(x.to_le_bytes())),
            DataArray::ScalarsU8(v) => out.extend_from_slice(v),
            DataArray::ScalarsI32(v) => v.iter().for_each(|x| out.extend(x.to_le_bytes())),
            DataArray::VectorsF32(v) => {
                v.iter().flatten().for_each(|x| out.extend(x.to_le_bytes()))
            }
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
            return Err(Error::argument(
                "surface face groups",
                format!(
                    "{} face groups for {} external faces",
                    g.len(),
                    mesh.external_faces.len()
                ),
            ));
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
        return Err(Error::argument(
            "mesh positions",
            format!(
                "{} positions for a mesh of {} nodes",
                positions_m.len(),
                mesh.node_count()
            ),
        ));
    }
    if let Some(n) = positions_m
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(Error::argument(
            "mesh positions",
            format!("node {n} has a non-finite position"),
        ));
    }
    Ok(())
}

/// Which of the two VTK XML datasets a file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// `.vtu`: the hexahedral mesh.
    Unstructured,
    /// `.vtp`: the surface quads.
    Poly,
}

impl Kind {
    /// The VTKFile `type` and the dataset element's name.
    fn file_type(self) -> &'static str {
        match self {
            Kind::Unstructured => "UnstructuredGrid",
            Kind::Poly => "PolyData",
        }
    }

    /// The element holding connectivity and offsets.
    fn cell_section(self) -> &'static str {
        match self {
            Kind::Unstructured => "Cells",
            Kind::Poly => "Polys",
        }
    }
}
