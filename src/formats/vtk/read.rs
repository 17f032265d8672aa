//! Reading the VTK XML pieces the writers produce: a minimal tag scanner, then checks of
//! every array against the piece's counts.

use std::path::Path;

use super::base64::base64_decode;
use super::{DataArray, Kind, VTK_HEXAHEDRON};
use crate::error::{IoContext, IoOp};
use crate::{Error, Result};

/// The file as UTF-8 text (XML).
pub(super) fn read_text(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).at(IoOp::Read, path)?;
    String::from_utf8(bytes).map_err(|_| Error::format(path, "not a text (XML) file"))
}

/// A parsed piece before its connectivity is cut into fixed-size cells.
pub(super) struct Piece<const N: usize> {
    pub points: Vec<[f64; 3]>,
    pub cells: Vec<[u32; N]>,
    pub point_data: Vec<(String, DataArray)>,
    pub cell_data: Vec<(String, DataArray)>,
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

/// Parses one piece of `kind`: scans the tags, then checks every array against the counts
/// the Piece announced and cuts the connectivity into cells of `N` corners.
pub(super) fn parse_piece<const N: usize>(text: &str, kind: Kind, what: &str) -> Result<Piece<N>> {
    let bad = |m: String| Error::format(what, m);
    let found = scan_piece(text, kind).map_err(bad)?;
    let n_points = found.n_points.ok_or_else(|| bad("no Piece".into()))?;
    let n_cells = found.n_cells.unwrap_or(0);
    let points = point_triples(found.points, n_points).map_err(bad)?;
    let connectivity = check_connectivity::<N>(found.connectivity, n_cells).map_err(bad)?;
    check_offsets::<N>(found.offsets, n_cells).map_err(bad)?;
    if kind == Kind::Unstructured {
        check_cell_types(found.types, n_cells).map_err(bad)?;
    }
    let cells = cells_of::<N>(&connectivity, n_points, n_cells).map_err(bad)?;
    check_data_lengths(&found.point_data, &found.cell_data, n_points, n_cells).map_err(bad)?;
    Ok(Piece {
        points,
        cells,
        point_data: found.point_data,
        cell_data: found.cell_data,
    })
}

/// What the tag scan of a file collects, before the arrays are checked against each other.
#[derive(Default)]
struct ScannedPiece {
    n_points: Option<usize>,
    n_cells: Option<usize>,
    points: Option<Raw>,
    connectivity: Option<Raw>,
    offsets: Option<Raw>,
    types: Option<Raw>,
    point_data: Vec<(String, DataArray)>,
    cell_data: Vec<(String, DataArray)>,
    seen_root: bool,
    /// The root names VTK's zlib compressor: arrays are in its block layout.
    zlib: bool,
}

/// Walks the tags in order (declarations and comments skipped), keeping the stack of open
/// elements so each DataArray is filed under its parent section.
fn scan_piece(text: &str, kind: Kind) -> std::result::Result<ScannedPiece, String> {
    let mut found = ScannedPiece::default();
    let mut stack: Vec<&str> = Vec::new();
    let mut pos = 0;
    while let Some(lt) = text[pos..].find('<').map(|i| pos + i) {
        let rest = &text[lt..];
        if rest.starts_with("<?") || rest.starts_with("<!--") {
            let end = if rest.starts_with("<?") { "?>" } else { "-->" };
            pos = lt
                + rest
                    .find(end)
                    .ok_or("unterminated XML declaration or comment")?
                + end.len();
            continue;
        }
        let gt = rest
            .find('>')
            .ok_or("unterminated XML tag (truncated file?)")?;
        let tag = parse_tag(&rest[1..gt])
            .ok_or_else(|| format!("malformed XML tag <{}>", &rest[1..gt]))?;
        pos = lt + gt + 1;
        if tag.closing {
            match stack.pop() {
                Some(open) if open == tag.name => continue,
                other => {
                    return Err(format!(
                        "</{}> closes <{}>",
                        tag.name,
                        other.unwrap_or("nothing")
                    ))
                }
            }
        }
        match tag.name {
            "VTKFile" => {
                found.zlib = check_root(&tag, kind)?;
                found.seen_root = true;
            }
            "Piece" => found.read_counts(&tag, kind)?,
            "DataArray" => {
                if !found.seen_root || found.n_points.is_none() {
                    return Err("DataArray outside a Piece".into());
                }
                let body_end = text[pos..]
                    .find('<')
                    .map(|i| pos + i)
                    .ok_or("DataArray has no end (truncated file?)")?;
                let body = if tag.empty { "" } else { &text[pos..body_end] };
                let parent = stack.last().copied().unwrap_or("");
                found.add_array(&tag, body, parent, kind)?;
            }
            _ => {}
        }
        if !tag.empty {
            stack.push(tag.name);
        }
    }
    if !found.seen_root {
        return Err("not a VTK XML file (no VTKFile element)".into());
    }
    if !stack.is_empty() {
        return Err(format!(
            "<{}> is never closed (truncated file?)",
            stack.join("><")
        ));
    }
    Ok(found)
}

/// The root must be this writer's: dataset type, little endian, UInt64 headers, zlib or no
/// compression; returns whether the arrays are zlib-compressed.
fn check_root(tag: &Tag, kind: Kind) -> std::result::Result<bool, String> {
    let expect = [
        ("type", kind.file_type()),
        ("byte_order", "LittleEndian"),
        ("header_type", "UInt64"),
    ];
    for (key, want) in expect {
        if tag.attr(key) != Some(want) {
            return Err(format!(
                "VTKFile {key}={:?}, expected {want:?} (only files written by \
                 lungmotion are read)",
                tag.attr(key).unwrap_or("")
            ));
        }
    }
    match tag.attr("compressor") {
        None => Ok(false),
        Some("vtkZLibDataCompressor") => Ok(true),
        Some(c) => Err(format!(
            "compressed data ({c}) is not supported (only vtkZLibDataCompressor)"
        )),
    }
}

impl ScannedPiece {
    /// Reads the point and cell counts of the (single) Piece; PolyData must hold quads only.
    fn read_counts(&mut self, tag: &Tag, kind: Kind) -> std::result::Result<(), String> {
        if self.n_points.is_some() {
            return Err("more than one Piece is not supported".into());
        }
        let count = |key: &str| -> std::result::Result<usize, String> {
            tag.attr(key)
                .and_then(|v| v.trim().parse().ok())
                .ok_or_else(|| format!("Piece has no valid {key}"))
        };
        self.n_points = Some(count("NumberOfPoints")?);
        self.n_cells = Some(match kind {
            Kind::Unstructured => count("NumberOfCells")?,
            Kind::Poly => {
                for other in ["NumberOfVerts", "NumberOfLines", "NumberOfStrips"] {
                    if tag.attr(other).is_some_and(|v| v.trim() != "0") {
                        return Err(format!("{other} is not 0: only quads are read"));
                    }
                }
                count("NumberOfPolys")?
            }
        });
        Ok(())
    }

    /// Decodes one DataArray and files it by its parent element and name.
    fn add_array(
        &mut self,
        tag: &Tag,
        body: &str,
        parent: &str,
        kind: Kind,
    ) -> std::result::Result<(), String> {
        let name = tag.attr("Name").unwrap_or("");
        let array = decode_array(tag, body, self.zlib).map_err(|m| format!("{name}: {m}"))?;
        let section = kind.cell_section();
        match (parent, name) {
            ("Points", _) => self.points = Some(array),
            (s, "connectivity") if s == section => self.connectivity = Some(array),
            (s, "offsets") if s == section => self.offsets = Some(array),
            (s, "types") if s == section && kind == Kind::Unstructured => self.types = Some(array),
            ("PointData" | "CellData", _) => {
                let data = array.into_data().map_err(|m| format!("{name}: {m}"))?;
                if parent == "PointData" {
                    self.point_data.push((name.to_string(), data));
                } else {
                    self.cell_data.push((name.to_string(), data));
                }
            }
            _ => return Err(format!("unexpected DataArray {name:?} in <{parent}>")),
        }
        Ok(())
    }
}

/// The Points array as `n_points` Float64 triples.
fn point_triples(
    points: Option<Raw>,
    n_points: usize,
) -> std::result::Result<Vec<[f64; 3]>, String> {
    match points {
        Some(Raw::F64(v, 3)) if v.len() == 3 * n_points => Ok(v
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect::<Vec<_>>()),
        Some(_) => Err(format!("Points must be {n_points} Float64 triples")),
        None => Err("no Points".into()),
    }
}

/// The connectivity as `N` Int64 corners per cell.
fn check_connectivity<const N: usize>(
    connectivity: Option<Raw>,
    n_cells: usize,
) -> std::result::Result<Vec<i64>, String> {
    match connectivity {
        Some(Raw::I64(v, 1)) if v.len() == N * n_cells => Ok(v),
        Some(_) => Err(format!(
            "connectivity must be {} Int64 ({n_cells} cells of {N} corners)",
            N * n_cells
        )),
        None => Err("no connectivity".into()),
    }
}

/// Offsets must be the multiples of `N`: every cell has `N` corners.
fn check_offsets<const N: usize>(
    offsets: Option<Raw>,
    n_cells: usize,
) -> std::result::Result<(), String> {
    match offsets {
        Some(Raw::I64(v, 1))
            if v.len() == n_cells
                && v.iter()
                    .enumerate()
                    .all(|(c, &o)| o == (N * (c + 1)) as i64) =>
        {
            Ok(())
        }
        Some(_) => Err(format!(
            "offsets must be Int64 multiples of {N}: only cells of {N} corners are read"
        )),
        None => Err("no offsets".into()),
    }
}

/// Every cell of an UnstructuredGrid must be a hexahedron.
fn check_cell_types(types: Option<Raw>, n_cells: usize) -> std::result::Result<(), String> {
    match types {
        Some(Raw::U8(v, 1)) if v.len() == n_cells && v.iter().all(|&t| t == VTK_HEXAHEDRON) => {
            Ok(())
        }
        Some(_) => Err(format!(
            "cell types must be {n_cells} UInt8 of value {VTK_HEXAHEDRON} (hexahedra)"
        )),
        None => Err("no cell types".into()),
    }
}

/// Cuts the connectivity into cells, refusing corners outside the points.
fn cells_of<const N: usize>(
    connectivity: &[i64],
    n_points: usize,
    n_cells: usize,
) -> std::result::Result<Vec<[u32; N]>, String> {
    let mut cells = Vec::with_capacity(n_cells);
    for (c, corners) in connectivity.chunks_exact(N).enumerate() {
        let mut cell = [0u32; N];
        for (slot, &n) in cell.iter_mut().zip(corners) {
            if n < 0 || n as usize >= n_points {
                return Err(format!(
                    "cell {c} refers to point {n}, but there are {n_points} points"
                ));
            }
            *slot = n as u32;
        }
        cells.push(cell);
    }
    Ok(cells)
}

/// Every data array must have one item per point (or cell).
fn check_data_lengths(
    point_data: &[(String, DataArray)],
    cell_data: &[(String, DataArray)],
    n_points: usize,
    n_cells: usize,
) -> std::result::Result<(), String> {
    for (what_data, arrays, count) in [
        ("point", point_data, n_points),
        ("cell", cell_data, n_cells),
    ] {
        if let Some((name, a)) = arrays.iter().find(|(_, a)| a.len() != count) {
            return Err(format!(
                "{what_data} data {name:?} has {} items for {count} {what_data}s",
                a.len()
            ));
        }
    }
    Ok(())
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

fn decode_array(tag: &Tag, body: &str, zlib: bool) -> std::result::Result<Raw, String> {
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
    let data = if zlib {
        inflate_blocks(&b64)?
    } else {
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
        data
    };
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

/// Largest uncompressed array accepted from a compressed file, bytes: a hostile header cannot
/// make the reader allocate more (a 2 mm POPI mesh's connectivity is about 40 MB).
const MAX_INFLATED_BYTES: u64 = 1 << 31;

/// VTK's zlib layout: a base64 header of UInt64s (blocks, block size, partial last block
/// size, compressed sizes) and the base64 of the concatenated zlib streams.
fn inflate_blocks(b64: &[u8]) -> std::result::Result<Vec<u8>, String> {
    use std::io::Read as _;
    // The first three UInt64s (24 bytes) are one 32-character base64 group.
    if b64.len() < 32 {
        return Err("compressed data have no block header".into());
    }
    let head = base64_decode(&b64[..32]).ok_or("block header is not base64")?;
    let word =
        |b: &[u8], i: usize| u64::from_le_bytes(b[8 * i..8 * i + 8].try_into().unwrap_or([0; 8]));
    let (blocks, block_size, last) = (word(&head, 0), word(&head, 1), word(&head, 2));
    let total = match (blocks, last) {
        (0, _) => Some(0),
        (n, 0) => n.checked_mul(block_size),
        (n, l) => (n - 1)
            .checked_mul(block_size)
            .and_then(|t| t.checked_add(l)),
    }
    .filter(|&t| t <= MAX_INFLATED_BYTES && last <= block_size)
    .ok_or_else(|| {
        format!(
            "block header ({blocks} blocks of {block_size} bytes, last {last}) is not plausible"
        )
    })?;
    let header_bytes = 8 * (3 + blocks as usize);
    let header_chars = header_bytes.div_ceil(3) * 4;
    if b64.len() < header_chars {
        return Err(format!(
            "block header announces {blocks} blocks but is cut short"
        ));
    }
    let header = base64_decode(&b64[..header_chars]).ok_or("block header is not base64")?;
    let compressed = base64_decode(&b64[header_chars..]).ok_or("compressed data are not base64")?;
    let mut out = Vec::with_capacity(total as usize);
    let mut at = 0usize;
    for i in 0..blocks as usize {
        let size = word(&header, 3 + i) as usize;
        let chunk = compressed
            .get(at..at.saturating_add(size))
            .ok_or_else(|| format!("block {i} runs past the end of the compressed data"))?;
        at += size;
        let want = if i + 1 == blocks as usize && last != 0 {
            last
        } else {
            block_size
        };
        let before = out.len();
        flate2::read::ZlibDecoder::new(chunk)
            .take(want + 1)
            .read_to_end(&mut out)
            .map_err(|e| format!("block {i} is not a zlib stream: {e}"))?;
        if (out.len() - before) as u64 != want {
            return Err(format!(
                "block {i} inflates to {} bytes, the header says {want}",
                out.len() - before
            ));
        }
    }
    if at != compressed.len() {
        return Err(format!(
            "{} bytes of compressed data follow the last block",
            compressed.len() - at
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write as _;

    fn b64(bytes: &[u8]) -> String {
        let mut s = String::new();
        let mut w = super::super::base64::Base64Writer::new(&mut s);
        w.push(bytes);
        w.finish();
        s
    }

    fn words(w: &[u64]) -> Vec<u8> {
        w.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn zlib(bytes: &[u8]) -> Vec<u8> {
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        z.write_all(bytes).unwrap();
        z.finish().unwrap()
    }

    #[test]
    fn uncompressed_and_zlib_layouts_give_the_same_bytes() {
        let raw: Vec<u8> = (0..100u8).collect();
        let plain = format!("{}{}", b64(&words(&[100])), b64(&raw));
        // Two blocks of 64 bytes, the last one partial (36 bytes).
        let (a, b) = (zlib(&raw[..64]), zlib(&raw[64..]));
        let header = words(&[2, 64, 36, a.len() as u64, b.len() as u64]);
        let packed = format!("{}{}", b64(&header), b64(&[a, b].concat()));
        assert_eq!(inflate_blocks(packed.as_bytes()).unwrap(), raw);
        let plain: Vec<u8> = plain.bytes().collect();
        let data = base64_decode(&plain[12..]).unwrap();
        assert_eq!(data, raw);
    }

    #[test]
    fn hostile_or_inconsistent_block_headers_are_refused_by_what_is_wrong() {
        let block = zlib(&[7u8; 64]);
        let case = |header: &[u64], data: &[u8]| {
            let text = format!("{}{}", b64(&words(header)), b64(data));
            inflate_blocks(text.as_bytes()).unwrap_err()
        };
        let e = case(&[u64::MAX / 2, 1 << 20, 0], &block);
        assert!(e.contains("not plausible"), "{e}");
        let e = case(&[1, 64, 0, block.len() as u64 + 5], &block);
        assert!(e.contains("runs past the end"), "{e}");
        let e = case(&[1, 128, 0, block.len() as u64], &block);
        assert!(
            e.contains("inflates to 64 bytes, the header says 128"),
            "{e}"
        );
        let e = case(&[1, 32, 0, block.len() as u64], &block);
        assert!(e.contains("the header says 32"), "{e}");
        let e = case(&[1, 64, 0, 3], &block);
        assert!(
            e.contains("not a zlib stream") || e.contains("inflates"),
            "{e}"
        );
    }
}
