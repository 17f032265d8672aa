//! Bridge to CalculiX (`ccx`), the independent FEM reference: writes a C3D8 deck from a
//! [`Scene`], runs `ccx` in a scratch directory and reads the nodal displacements back.
//!
//! The deck reproduces the scene exactly where the two codes can agree: gravity becomes
//! `*DLOAD GRAV` (its consistent nodal load on a rectangular brick is ρV/8 per corner, our
//! lumping), dead pressures become `*CLOAD` P·A/4 per corner (exactly our load, since CalculiX
//! pressure is a follower load under NLGEOM), follower pressures become `*DLOAD Pn`.
//! Everything is written in SI; CalculiX itself is unit-less.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::math::V3;
use crate::model::mesh::HEX_FACES;
use crate::model::{ContinuumLaw, HexMesh, Material, NodeConstraint};
use crate::simulation::Scene;
use crate::{Error, IoContext, IoOp, Result};

/// Environment variable naming the `ccx` executable, overriding the search of `PATH`.
pub const CCX_ENV: &str = "LUNGMOTION_CCX";

/// How to get CalculiX, for error messages shown when it is missing.
pub const CCX_INSTALL_HINT: &str = "install CalculiX (Debian/Ubuntu: `apt-get install -y \
     calculix-ccx`) or set LUNGMOTION_CCX to the path of the `ccx` executable";

/// 0-based corners of the C3D8 faces S1…S6 (CalculiX manual, 1-based: 1-2-3-4, 5-8-7-6,
/// 1-5-6-2, 2-6-7-3, 3-7-8-4, 4-8-5-1).
pub const C3D8_FACES: [[usize; 4]; 6] = [
    [0, 1, 2, 3],
    [4, 7, 6, 5],
    [0, 4, 5, 1],
    [1, 5, 6, 2],
    [2, 6, 7, 3],
    [3, 7, 4, 0],
];

/// The `ccx` executable: `$LUNGMOTION_CCX` if it names a file, else `ccx` found on `PATH`.
pub fn ccx_path() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(CCX_ENV) {
        let p = PathBuf::from(p);
        return p.is_file().then_some(p);
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join("ccx"))
        .find(|c| c.is_file())
}

/// The `ccx` executable, or an error saying how to install it.
pub fn require_ccx() -> Result<PathBuf> {
    ccx_path().ok_or_else(|| {
        let why = match std::env::var_os(CCX_ENV) {
            Some(p) => format!("{CCX_ENV}={} is not a file", Path::new(&p).display()),
            None => "`ccx` is not on PATH".to_string(),
        };
        Error::External(format!("CalculiX not found: {why}; {CCX_INSTALL_HINT}"))
    })
}

/// CalculiX hexahedron formulation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum ElementType {
    /// Trilinear, full 2×2×2 integration (locks in bending on coarse meshes).
    C3D8,
    /// Trilinear with incompatible modes (no shear locking; a cross-check of C3D8).
    C3D8I,
    /// Trilinear, reduced integration with hourglass control.
    C3D8R,
}

impl ElementType {
    /// The deck keyword.
    pub fn keyword(self) -> &'static str {
        match self {
            ElementType::C3D8 => "C3D8",
            ElementType::C3D8I => "C3D8I",
            ElementType::C3D8R => "C3D8R",
        }
    }
}

/// How the deck is written and `ccx` is run.
#[derive(Debug, Clone, Serialize)]
pub struct CalculixOptions {
    /// Geometrically non-linear step (`*STEP, NLGEOM`: St Venant–Kirchhoff with `*ELASTIC`).
    pub nlgeom: bool,
    /// Element formulation.
    pub element_type: ElementType,
    /// First load increment as a fraction of the step (`*STATIC` first field).
    pub initial_increment: f64,
    /// Smallest increment CalculiX may cut back to before giving up.
    pub min_increment: f64,
    /// Largest increment.
    pub max_increment: f64,
    /// Increment budget of the step (`INC=`).
    pub max_increments: usize,
    /// `OMP_NUM_THREADS` for `ccx`.
    pub threads: usize,
    /// Keep the scratch directory (its path goes into errors) instead of deleting it.
    pub keep_files: bool,
}

impl Default for CalculixOptions {
    fn default() -> Self {
        CalculixOptions {
            nlgeom: true,
            element_type: ElementType::C3D8,
            initial_increment: 0.1,
            min_increment: 1e-5,
            max_increment: 1.0,
            max_increments: 1000,
            threads: 2,
            keep_files: false,
        }
    }
}

impl CalculixOptions {
    /// Small-strain linear analysis (one increment).
    pub fn linear() -> Self {
        CalculixOptions {
            nlgeom: false,
            ..Default::default()
        }
    }
}

/// Nodal displacements computed by CalculiX.
#[derive(Debug, Clone, Serialize)]
pub struct CalculixSolution {
    /// Displacement of every node of the scene (same order), metres.
    pub displacements_m: Vec<V3>,
    /// Wall time of the `ccx` process, seconds.
    pub wall_time_s: f64,
    /// Peak resident memory of `ccx` (VmHWM), MB, when `/proc` shows it.
    pub peak_memory_mb: Option<f64>,
    /// Load increments CalculiX reported (NLGEOM cuts the step into increments).
    pub increments: usize,
}

/// An element face: element, C3D8 face number 1…6, corners in our outward order.
type ElementFace = (u32, u8, [u32; 4]);

/// Locates the C3D8 face of each element that a quad lies on.
pub struct FaceLocator {
    // Keyed by the sorted corner nodes.
    faces: HashMap<[u32; 4], Vec<ElementFace>>,
}

impl FaceLocator {
    /// Indexes every face of every element of `elements`.
    pub fn new(elements: &[[u32; 8]]) -> Self {
        let mut faces: HashMap<[u32; 4], Vec<ElementFace>> = HashMap::new();
        for (e, corners) in elements.iter().enumerate() {
            for local in HEX_FACES {
                let outward = local.map(|c| corners[c]);
                let number = c3d8_face_number(local).expect("HEX_FACES are faces of a hexahedron");
                let mut key = outward;
                key.sort_unstable();
                faces
                    .entry(key)
                    .or_default()
                    .push((e as u32, number, outward));
            }
        }
        FaceLocator { faces }
    }

    /// The element (0-based) and C3D8 face number (1…6) for which `quad` is an outward face.
    ///
    /// An internal face belongs to two elements; the orientation of `quad` picks the one it
    /// points out of, so the pressure pushes the same way in both codes.
    pub fn locate(&self, quad: &[u32; 4]) -> Result<(u32, u8)> {
        let mut key = *quad;
        key.sort_unstable();
        let candidates = self.faces.get(&key).ok_or_else(|| {
            Error::InvalidModel(format!(
                "pressure face {quad:?} is not a face of any element"
            ))
        })?;
        candidates
            .iter()
            .find(|(_, _, outward)| same_cycle(outward, quad))
            .map(|&(e, s, _)| (e, s))
            .ok_or_else(|| {
                Error::InvalidModel(format!(
                    "pressure face {quad:?} is not ordered as an outward face of its element"
                ))
            })
    }
}

/// The C3D8 face number (1…6) whose corners are the set `local` (0-based element corners).
pub fn c3d8_face_number(local: [usize; 4]) -> Option<u8> {
    let mut key = local;
    key.sort_unstable();
    C3D8_FACES
        .iter()
        .position(|f| {
            let mut k = *f;
            k.sort_unstable();
            k == key
        })
        .map(|i| i as u8 + 1)
}

fn same_cycle(a: &[u32; 4], b: &[u32; 4]) -> bool {
    (0..4).any(|r| (0..4).all(|i| a[(i + r) % 4] == b[i]))
}

/// Writes the CalculiX input deck (`.inp` text) for `scene`.
///
/// Refuses what CalculiX cannot express faithfully: nodes sliding on implicit surfaces.
pub fn write_deck(scene: &Scene, options: &CalculixOptions) -> Result<String> {
    let mesh = &scene.mesh;
    // Numbers carry 13 significant digits: CalculiX reads at most 20 characters per field.
    let mut d = String::new();
    d.push_str("** lungmotion: mass-spring scene exported for CalculiX, SI units\n");
    write_nodes(&mut d, mesh);
    let material_count = write_element_sets(&mut d, mesh, options)?;
    let constraints = DeckConstraints::of(scene)?;
    write_transforms(&mut d, &constraints.transforms);
    let loads = DeckLoads::of(scene, options.nlgeom)?;
    write_step(&mut d, scene, options, material_count, &constraints, &loads);
    Ok(d)
}

/// `*NODE`: every node at rest, 1-based ids.
fn write_nodes(d: &mut String, mesh: &HexMesh) {
    d.push_str("*NODE, NSET=NALL\n");
    for (i, p) in mesh.rest_positions_m.iter().enumerate() {
        writeln!(d, "{}, {:.12e}, {:.12e}, {:.12e}", i + 1, p.x, p.y, p.z).unwrap();
    }
}

/// One element set per distinct material, in order of first appearance, each with its
/// `*MATERIAL` and `*SOLID SECTION`; returns how many sets there are.
fn write_element_sets(d: &mut String, mesh: &HexMesh, options: &CalculixOptions) -> Result<usize> {
    let mut materials: Vec<Material> = Vec::new();
    let mut group_of_class = Vec::with_capacity(mesh.classes.len());
    for c in &mesh.classes {
        let g = match materials.iter().position(|m| *m == c.material) {
            Some(g) => g,
            None => {
                materials.push(c.material);
                materials.len() - 1
            }
        };
        group_of_class.push(g);
    }
    for (g, m) in materials.iter().enumerate() {
        writeln!(
            d,
            "*ELEMENT, TYPE={}, ELSET=E{}",
            options.element_type.keyword(),
            g + 1
        )
        .unwrap();
        for (e, corners) in mesh.elements.iter().enumerate() {
            if group_of_class[mesh.element_class[e] as usize] != g {
                continue;
            }
            write!(d, "{}", e + 1).unwrap();
            for c in corners {
                write!(d, ", {}", c + 1).unwrap();
            }
            d.push('\n');
        }
        writeln!(d, "*MATERIAL, NAME=M{}", g + 1).unwrap();
        d.push_str(&material_card(m)?);
        writeln!(d, "*DENSITY\n{:.12e}", m.density_kg_per_m3).unwrap();
        writeln!(d, "*SOLID SECTION, ELSET=E{}, MATERIAL=M{}", g + 1, g + 1).unwrap();
    }
    Ok(materials.len())
}

/// The constitutive card of `m`: its volumetric or continuum-correction law when it names one
/// CalculiX has
/// (`*HYPERELASTIC, NEO HOOKE` with C₁₀ = G/2, D₁ = 2/K; `*HYPERFOAM, N=1` with μ₁ = G,
/// α₁ = 2, ν₁ = ν), else `*ELASTIC` (St Venant–Kirchhoff under NLGEOM). Debian's CalculiX
/// 2.20 stops with exit status 255 on `*HYPERFOAM` (seen on one cube), which `solve` reports.
pub fn material_card(m: &Material) -> Result<String> {
    let (g, k) = (m.shear_modulus_pa(), m.bulk_modulus_pa());
    Ok(match m.volumetric_law.or(m.continuum_correction) {
        None => format!(
            "*ELASTIC\n{:.12e}, {:.12e}\n",
            m.youngs_modulus_pa, m.poisson_ratio
        ),
        Some(ContinuumLaw::NeoHookean) => {
            format!(
                "*HYPERELASTIC, NEO HOOKE\n{:.12e}, {:.12e}\n",
                g / 2.0,
                2.0 / k
            )
        }
        Some(ContinuumLaw::Hyperfoam) => {
            format!(
                "*HYPERFOAM, N=1\n{:.12e}, 2., {:.12e}\n",
                g, m.poisson_ratio
            )
        }
        Some(law @ ContinuumLaw::LungBirzle) => {
            return Err(Error::argument(
                "CalculiX material",
                format!(
                    "{law:?} has no CalculiX card (its (Ī₁ − 3)³ and (J^(2/3) − 1)⁶ terms need a \
                     user material); compare with hyperfoam, its first two terms"
                ),
            ))
        }
    })
}

/// The scene's constraints as CalculiX boundary conditions: per node, the imposed DOFs
/// (1-based, in the node's frame) and values, and the local frames of nodes constrained
/// along a direction that is not a coordinate axis.
struct DeckConstraints {
    /// Each distinct local frame with the nodes that use it.
    transforms: Vec<([V3; 3], Vec<u32>)>,
    /// Index into `transforms` of each transformed node.
    frame_of_node: HashMap<u32, usize>,
    /// (node, DOF, imposed displacement).
    boundary: Vec<(u32, usize, f64)>,
}

impl DeckConstraints {
    /// Translates every constraint of `scene`; refuses nodes sliding on implicit surfaces.
    fn of(scene: &Scene) -> Result<Self> {
        let mesh = &scene.mesh;
        let mut transforms: Vec<([V3; 3], Vec<u32>)> = Vec::new();
        let mut frame_of_node: HashMap<u32, usize> = HashMap::new();
        let mut boundary: Vec<(u32, usize, f64)> = Vec::new();
        for &(node, c) in &scene.constraints.entries {
            let rest = mesh.rest_positions_m[node as usize];
            match c {
                NodeConstraint::Fixed { target_m } => {
                    let u = target_m - rest;
                    for i in 0..3 {
                        boundary.push((node, i + 1, u[i]));
                    }
                }
                NodeConstraint::Plane { point_m, normal } => {
                    // The node is projected onto the plane: its normal displacement is imposed.
                    let u = normal * (point_m - rest).dot(&normal);
                    match axis_of(&normal) {
                        Some(i) => boundary.push((node, i + 1, u[i])),
                        None => {
                            let f = frame_with_x(normal);
                            add_to_frame(&mut transforms, &mut frame_of_node, f, node);
                            boundary.push((node, 1, u.dot(&f[0])));
                        }
                    }
                }
                NodeConstraint::Line { point_m, direction } => {
                    let off = point_m - rest;
                    let u = off - direction * off.dot(&direction);
                    match axis_of(&direction) {
                        Some(i) => {
                            for j in (0..3).filter(|&j| j != i) {
                                boundary.push((node, j + 1, u[j]));
                            }
                        }
                        None => {
                            let f = frame_with_x(direction);
                            add_to_frame(&mut transforms, &mut frame_of_node, f, node);
                            boundary.push((node, 2, u.dot(&f[1])));
                            boundary.push((node, 3, u.dot(&f[2])));
                        }
                    }
                }
                NodeConstraint::Surface { field, .. } => {
                    return Err(Error::InvalidModel(format!(
                        "node {node} slides on implicit surface {field}; CalculiX has no \
                         equivalent constraint, so this scene cannot be exported"
                    )));
                }
            }
        }
        Ok(DeckConstraints {
            transforms,
            frame_of_node,
            boundary,
        })
    }
}

/// `*NSET` and `*TRANSFORM` of each local frame.
fn write_transforms(d: &mut String, transforms: &[([V3; 3], Vec<u32>)]) {
    for (t, (frame, nodes)) in transforms.iter().enumerate() {
        writeln!(d, "*NSET, NSET=TR{}", t + 1).unwrap();
        write_id_list(d, nodes.iter().map(|n| n + 1));
        // CalculiX builds its local y from the second point's part orthogonal to local x.
        let (a, b) = (frame[0], frame[1]);
        writeln!(
            d,
            "*TRANSFORM, NSET=TR{}, TYPE=R\n{:.12e}, {:.12e}, {:.12e}, {:.12e}, {:.12e}, {:.12e}",
            t + 1,
            a.x,
            a.y,
            a.z,
            b.x,
            b.y,
            b.z
        )
        .unwrap();
    }
}

/// The scene's loads as CalculiX takes them: dead forces summed per node (CalculiX keeps
/// only the last value given for a node and DOF), follower pressures summed per element
/// face.
struct DeckLoads {
    /// Summed dead force per node, N.
    nodal: Vec<V3>,
    /// Whether a node carries a dead force (possibly summing to zero).
    has_nodal: Vec<bool>,
    /// Pressure per (element, C3D8 face), Pa, in order of first appearance.
    face_pressure: Vec<((u32, u8), f64)>,
}

impl DeckLoads {
    /// Sums the scene's point forces and pressures; under NLGEOM dead pressures become
    /// nodal forces P·A/4 per corner (CalculiX pressure follows the deformation).
    fn of(scene: &Scene, nlgeom: bool) -> Result<Self> {
        let mesh = &scene.mesh;
        let mut nodal = vec![V3::zeros(); mesh.node_count()];
        let mut has_nodal = vec![false; mesh.node_count()];
        for &(n, f) in &scene.loads.point_forces_n {
            nodal[n as usize] += f;
            has_nodal[n as usize] = true;
        }
        let locator = FaceLocator::new(&mesh.elements);
        let mut face_pressure: Vec<((u32, u8), f64)> = Vec::new();
        let mut face_slot: HashMap<(u32, u8), usize> = HashMap::new();
        for p in &scene.loads.pressures {
            for face in &p.faces {
                if p.follows_deformation || !nlgeom {
                    let key = locator.locate(face)?;
                    match face_slot.get(&key) {
                        Some(&s) => face_pressure[s].1 += p.pressure_pa,
                        None => {
                            face_slot.insert(key, face_pressure.len());
                            face_pressure.push((key, p.pressure_pa));
                        }
                    }
                } else {
                    let c = face.map(|i| mesh.rest_positions_m[i as usize]);
                    let area = 0.5 * (c[2] - c[0]).cross(&(c[3] - c[1]));
                    for &i in face {
                        nodal[i as usize] -= area * (p.pressure_pa / 4.0);
                        has_nodal[i as usize] = true;
                    }
                }
            }
        }
        Ok(DeckLoads {
            nodal,
            has_nodal,
            face_pressure,
        })
    }
}

/// The static step: `*STEP`, `*STATIC`, `*BOUNDARY`, `*DLOAD` (gravity on each of the
/// `material_count` element sets, face pressures), `*CLOAD` and the displacement print.
fn write_step(
    d: &mut String,
    scene: &Scene,
    options: &CalculixOptions,
    material_count: usize,
    constraints: &DeckConstraints,
    loads: &DeckLoads,
) {
    if options.nlgeom {
        writeln!(d, "*STEP, NLGEOM, INC={}", options.max_increments).unwrap();
    } else {
        writeln!(d, "*STEP, INC={}", options.max_increments).unwrap();
    }
    writeln!(
        d,
        "*STATIC\n{:e}, 1.0, {:e}, {:e}",
        options.initial_increment, options.min_increment, options.max_increment
    )
    .unwrap();
    if !constraints.boundary.is_empty() {
        d.push_str("*BOUNDARY\n");
        for (node, dof, value) in &constraints.boundary {
            writeln!(d, "{}, {dof}, {dof}, {value:.12e}", node + 1).unwrap();
        }
    }
    write_dloads(
        d,
        scene.loads.gravity_m_per_s2,
        material_count,
        &loads.face_pressure,
    );
    write_cloads(d, loads, constraints);
    d.push_str("*NODE PRINT, NSET=NALL, GLOBAL=YES\nU\n*END STEP\n");
}

/// `*DLOAD`: gravity on each element set, then the face pressures; nothing without either.
fn write_dloads(d: &mut String, g: V3, material_count: usize, face_pressure: &[((u32, u8), f64)]) {
    let mut dload = String::new();
    if g != V3::zeros() {
        let dir = g / g.norm();
        for e in 0..material_count {
            writeln!(
                dload,
                "E{}, GRAV, {:.12e}, {:.12e}, {:.12e}, {:.12e}",
                e + 1,
                g.norm(),
                dir.x,
                dir.y,
                dir.z
            )
            .unwrap();
        }
    }
    for ((e, s), p) in face_pressure {
        writeln!(dload, "{}, P{s}, {p:.12e}", e + 1).unwrap();
    }
    if !dload.is_empty() {
        d.push_str("*DLOAD\n");
        d.push_str(&dload);
    }
}

/// `*CLOAD`: the dead nodal forces, in each transformed node's local frame.
fn write_cloads(d: &mut String, loads: &DeckLoads, constraints: &DeckConstraints) {
    if !loads.has_nodal.iter().any(|&h| h) {
        return;
    }
    d.push_str("*CLOAD\n");
    for (n, f) in loads.nodal.iter().enumerate() {
        if !loads.has_nodal[n] {
            continue;
        }
        // Loads on transformed nodes are read in the node's local frame.
        let local = match constraints.frame_of_node.get(&(n as u32)) {
            Some(&t) => {
                let fr = &constraints.transforms[t].0;
                V3::new(f.dot(&fr[0]), f.dot(&fr[1]), f.dot(&fr[2]))
            }
            None => *f,
        };
        // Components at round-off level of a rotated load would only be noise.
        let floor = 1e-14 * local.norm();
        for i in 0..3 {
            if local[i].abs() > floor {
                writeln!(d, "{}, {}, {:.12e}", n + 1, i + 1, local[i]).unwrap();
            }
        }
    }
}

/// Index of the coordinate axis `v` points along (either sign), if it does.
fn axis_of(v: &V3) -> Option<usize> {
    (0..3).find(|&i| v[i].abs() > 1.0 - 1e-12)
}

/// An orthonormal frame whose first axis is `x`, built the way CalculiX builds a rectangular
/// `*TRANSFORM` from it and the second vector returned.
fn frame_with_x(x: V3) -> [V3; 3] {
    let a = x.normalize();
    let helper = if a.x.abs() < 0.9 { V3::x() } else { V3::y() };
    let b = (helper - a * helper.dot(&a)).normalize();
    [a, b, a.cross(&b)]
}

fn add_to_frame(
    transforms: &mut Vec<([V3; 3], Vec<u32>)>,
    frame_of_node: &mut HashMap<u32, usize>,
    frame: [V3; 3],
    node: u32,
) {
    let t = match transforms
        .iter()
        .position(|(f, _)| (f[0] - frame[0]).norm() < 1e-12)
    {
        Some(t) => t,
        None => {
            transforms.push((frame, Vec::new()));
            transforms.len() - 1
        }
    };
    transforms[t].1.push(node);
    frame_of_node.insert(node, t);
}

/// Writes ids 8 to a line (CalculiX reads at most 16 per line and 132 characters).
fn write_id_list(d: &mut String, ids: impl Iterator<Item = u32>) {
    let ids: Vec<u32> = ids.collect();
    for chunk in ids.chunks(8) {
        let line: Vec<String> = chunk.iter().map(|i| i.to_string()).collect();
        writeln!(d, "{},", line.join(", ")).unwrap();
    }
}

/// Reads the displacements of the last `*NODE PRINT` block of a `.dat` file.
///
/// Returns the step time of that block and the displacement of every node (1-based ids
/// 1…`node_count`); fails if a node is missing or a value is unreadable.
pub fn parse_dat_displacements(dat: &str, node_count: usize) -> Result<(f64, Vec<V3>)> {
    const HEADER: &str = "displacements (vx,vy,vz) for set";
    let start = dat
        .rfind(HEADER)
        .ok_or_else(|| Error::External("no displacement block in the CalculiX .dat file".into()))?;
    let mut lines = dat[start..].lines();
    let header = lines.next().unwrap_or_default();
    let time: f64 = header
        .rsplit("time")
        .next()
        .and_then(|t| t.trim().parse().ok())
        .ok_or_else(|| Error::External(format!("unreadable .dat block header: {header:?}")))?;
    let mut u = vec![V3::repeat(f64::NAN); node_count];
    let mut seen = 0usize;
    for line in lines {
        let line = line.trim();
        if line.is_empty() {
            if seen > 0 {
                break;
            }
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        let parsed = (fields.len() == 4)
            .then(|| {
                let id: usize = fields[0].parse().ok()?;
                let v: Vec<f64> = fields[1..]
                    .iter()
                    .map(|f| f.parse::<f64>().ok())
                    .collect::<Option<_>>()?;
                Some((id, V3::new(v[0], v[1], v[2])))
            })
            .flatten();
        let (id, v) = match parsed {
            Some(x) => x,
            None if seen > 0 => break,
            None => {
                return Err(Error::External(format!("unreadable .dat line: {line:?}")));
            }
        };
        if id == 0 || id > node_count {
            return Err(Error::External(format!(
                ".dat lists node {id}, but the scene has {node_count} nodes"
            )));
        }
        if u[id - 1].x.is_nan() {
            seen += 1;
        }
        u[id - 1] = v;
    }
    if let Some(n) = u.iter().position(|v| !v.iter().all(|x| x.is_finite())) {
        return Err(Error::External(format!(
            "CalculiX reported no finite displacement for node {} ({seen} of {node_count} read)",
            n + 1
        )));
    }
    Ok((time, u))
}

static RUN_COUNTER: AtomicUsize = AtomicUsize::new(0);

/// Runs CalculiX on `scene` and returns the displacement of every node, with the run's wall
/// time, peak memory (polled from `/proc` while it runs) and increment count.
///
/// Fails with the tail of ccx's output when it exits with an error, prints `*ERROR`, or stops
/// before the end of the step (no converged solution at full load).
pub fn solve(scene: &Scene, options: &CalculixOptions) -> Result<CalculixSolution> {
    let ccx = require_ccx()?;
    let deck = write_deck(scene, options)?;
    let dir = std::env::temp_dir().join(format!(
        "lungmotion-ccx-{}-{}-{}",
        std::process::id(),
        RUN_COUNTER.fetch_add(1, Ordering::Relaxed),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0)
    ));
    std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
    let result = run_in(&ccx, &dir, &deck, scene.node_count(), options);
    if options.keep_files {
        result.map_err(|e| match e {
            Error::External(m) => Error::External(format!("{m} (files kept in {})", dir.display())),
            e => e,
        })
    } else {
        let _ = std::fs::remove_dir_all(&dir);
        result
    }
}

fn run_in(
    ccx: &Path,
    dir: &Path,
    deck: &str,
    node_count: usize,
    options: &CalculixOptions,
) -> Result<CalculixSolution> {
    let deck_path = dir.join("job.inp");
    std::fs::write(&deck_path, deck).at(IoOp::Write, &deck_path)?;
    // Output goes to files, not pipes: nobody reads a pipe while we poll, and a full one
    // would stall ccx.
    let stdout_path = dir.join("ccx.stdout");
    let stderr_path = dir.join("ccx.stderr");
    let start = Instant::now();
    let mut child = Command::new(ccx)
        .arg("-i")
        .arg("job")
        .current_dir(dir)
        .env("OMP_NUM_THREADS", options.threads.max(1).to_string())
        .stdout(Stdio::from(
            File::create(&stdout_path).at(IoOp::Create, &stdout_path)?,
        ))
        .stderr(Stdio::from(
            File::create(&stderr_path).at(IoOp::Create, &stderr_path)?,
        ))
        .spawn()
        .map_err(|e| Error::External(format!("cannot run {}: {e}", ccx.display())))?;
    let status_path = format!("/proc/{}/status", child.id());
    let mut peak_kb: Option<f64> = None;
    let status = loop {
        if let Some(s) = child
            .try_wait()
            .map_err(|e| Error::External(format!("waiting for {}: {e}", ccx.display())))?
        {
            break s;
        }
        if let Some(kb) = std::fs::read_to_string(&status_path)
            .ok()
            .as_deref()
            .and_then(vm_hwm_kb)
        {
            peak_kb = Some(peak_kb.map_or(kb, |p: f64| p.max(kb)));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let wall_time_s = start.elapsed().as_secs_f64();
    let stdout = std::fs::read_to_string(&stdout_path).unwrap_or_default();
    let stderr = std::fs::read_to_string(&stderr_path).unwrap_or_default();
    let fail = |why: &str| {
        Error::External(format!(
            "CalculiX {why}\n--- ccx stdout (tail) ---\n{}\n--- ccx stderr (tail) ---\n{}",
            tail(&stdout, 30),
            tail(&stderr, 30)
        ))
    };
    if !status.success() {
        return Err(fail(&format!("exited with {status}")));
    }
    if let Some(line) = stdout
        .lines()
        .chain(stderr.lines())
        .find(|l| l.contains("*ERROR"))
    {
        return Err(fail(&format!("reported an error: {}", line.trim())));
    }
    let dat = std::fs::read_to_string(dir.join("job.dat"))
        .map_err(|e| fail(&format!("wrote no readable job.dat ({e})")))?;
    let (time, displacements_m) = parse_dat_displacements(&dat, node_count)
        .map_err(|e| fail(&format!("output unusable: {e}")))?;
    if (time - 1.0).abs() > 1e-6 {
        return Err(fail(&format!(
            "stopped at step time {time} before reaching full load (1.0): not converged"
        )));
    }
    Ok(CalculixSolution {
        displacements_m,
        wall_time_s,
        peak_memory_mb: peak_kb.map(|kb| kb / 1024.0),
        increments: increment_count(&stdout),
    })
}

/// Converged load increments in ccx's standard output: each increment's first attempt
/// prints one `increment N attempt 1` line.
fn increment_count(stdout: &str) -> usize {
    stdout
        .lines()
        .filter(|l| l.trim_start().starts_with("increment") && l.contains("attempt 1"))
        .count()
}

/// The `VmHWM` (peak resident set) line of a `/proc/<pid>/status` text, kB.
fn vm_hwm_kb(status: &str) -> Option<f64> {
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

fn tail(s: &str, n: usize) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{ConstraintSet, Loads, SurfacePressure, VoxelGrid};

    fn unit_block() -> Scene {
        let gm = VoxelGrid::filled_box([1, 1, 1], [1.0; 3], V3::zeros())
            .to_mesh(Material::new(1000.0, 0.3, 2.0).unwrap())
            .unwrap();
        let n = gm.mesh.node_count();
        Scene::new(gm.mesh, ConstraintSet::new(n), Loads::default()).unwrap()
    }

    #[test]
    fn every_hex_face_maps_to_a_distinct_c3d8_face() {
        let mut seen: Vec<u8> = HEX_FACES
            .iter()
            .map(|f| c3d8_face_number(*f).unwrap())
            .collect();
        seen.sort_unstable();
        assert_eq!(seen, vec![1, 2, 3, 4, 5, 6]);
    }

    #[test]
    fn faces_of_a_unit_cube_get_their_c3d8_numbers() {
        let scene = unit_block();
        let mesh = &scene.mesh;
        let loc = FaceLocator::new(&mesh.elements);
        // Outward normal direction of each C3D8 face of a VTK-ordered brick.
        let want = [
            (V3::new(0.0, 0.0, -1.0), 1),
            (V3::new(0.0, 0.0, 1.0), 2),
            (V3::new(0.0, -1.0, 0.0), 3),
            (V3::new(1.0, 0.0, 0.0), 4),
            (V3::new(0.0, 1.0, 0.0), 5),
            (V3::new(-1.0, 0.0, 0.0), 6),
        ];
        assert_eq!(mesh.external_faces.len(), 6);
        for f in &mesh.external_faces {
            let c = f.map(|i| mesh.rest_positions_m[i as usize]);
            let n = (c[2] - c[0]).cross(&(c[3] - c[1])).normalize();
            let (e, s) = loc.locate(f).unwrap();
            assert_eq!(e, 0);
            let expect = want.iter().find(|(d, _)| (d - n).norm() < 1e-12).unwrap().1;
            assert_eq!(s, expect, "face {f:?} with normal {n:?}");
            // A reversed quad points into the element: refused, not silently flipped.
            let rev = [f[3], f[2], f[1], f[0]];
            assert!(loc.locate(&rev).is_err());
        }
    }

    #[test]
    fn internal_face_goes_to_the_element_it_points_out_of() {
        let gm = VoxelGrid::filled_box([2, 1, 1], [1.0; 3], V3::zeros())
            .to_mesh(Material::new(1000.0, 0.3, 2.0).unwrap())
            .unwrap();
        let loc = FaceLocator::new(&gm.mesh.elements);
        // The x = 1 face: +x face (S4) of element 0, −x face (S6) of element 1.
        let e0 = gm.mesh.elements[0];
        let plus_x = HEX_FACES[5].map(|c| e0[c]);
        assert_eq!(loc.locate(&plus_x).unwrap(), (0, 4));
        let rev = [plus_x[3], plus_x[2], plus_x[1], plus_x[0]];
        assert_eq!(loc.locate(&rev).unwrap(), (1, 6));
    }

    #[test]
    fn deck_holds_boundaries_loads_and_transforms() {
        let mut scene = unit_block();
        let mut cs = ConstraintSet::new(8);
        cs.fix(0, V3::new(0.0, 0.0, 0.5)).unwrap();
        cs.set(
            1,
            NodeConstraint::Plane {
                point_m: V3::zeros(),
                normal: V3::y(),
            },
        )
        .unwrap();
        cs.set(
            2,
            NodeConstraint::Plane {
                point_m: V3::zeros(),
                normal: V3::new(1.0, 1.0, 0.0),
            },
        )
        .unwrap();
        let face = scene.mesh.external_faces[0];
        let loads = Loads {
            gravity_m_per_s2: V3::new(0.0, 0.0, -9.81),
            point_forces_n: vec![(2, V3::new(1.0, 1.0, 0.0))],
            pressures: vec![SurfacePressure {
                faces: vec![face],
                pressure_pa: 3.0,
                follows_deformation: true,
            }],
        };
        scene = Scene::new(scene.mesh, cs, loads).unwrap();
        let deck = write_deck(&scene, &CalculixOptions::default()).unwrap();
        assert!(deck.contains("*ELEMENT, TYPE=C3D8, ELSET=E1\n1, 1, 2, 3, 4, 5, 6, 7, 8\n"));
        assert!(deck.contains("*STEP, NLGEOM"));
        assert!(deck.contains("1, 3, 3, 5.000000000000e-1"));
        assert!(deck.contains("2, 2, 2, 0.000000000000e0"));
        assert!(deck.contains("*TRANSFORM, NSET=TR1, TYPE=R"));
        // Node 3 sits at (1, 1, 0): its distance to the plane x + y = 0 is √2.
        assert!(deck.contains("3, 1, 1, -1.414213562373"), "{deck}");
        // The load on the transformed node is given along its local x (the plane normal).
        assert!(deck.contains("3, 1, 1.414213562373"), "{deck}");
        assert!(
            !deck.contains("3, 2, "),
            "round-off components are dropped: {deck}"
        );
        assert!(deck.contains("E1, GRAV, 9.81"));
        assert!(deck.contains(", P"));
        let linear = write_deck(&scene, &CalculixOptions::linear()).unwrap();
        assert!(!linear.contains("NLGEOM"));
    }

    #[test]
    fn refuses_surface_constraints() {
        let scene = unit_block();
        let mut cs = ConstraintSet::new(8);
        let sdf = crate::model::SignedDistanceField::from_fn(
            V3::repeat(-2.0),
            V3::repeat(2.0),
            0.5,
            |p| p.norm() - 1.0,
        )
        .unwrap();
        let field = cs.add_surface(sdf);
        cs.set(3, NodeConstraint::surface(field, 0.0)).unwrap();
        let scene = Scene::new(scene.mesh, cs, Loads::default()).unwrap();
        let err = write_deck(&scene, &CalculixOptions::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains("implicit surface"), "{err}");
    }

    #[test]
    fn dead_pressure_under_nlgeom_becomes_nodal_forces() {
        let scene = unit_block();
        let face = scene.mesh.external_faces[0];
        let loads = Loads {
            pressures: vec![SurfacePressure {
                faces: vec![face],
                pressure_pa: 4.0,
                follows_deformation: false,
            }],
            ..Default::default()
        };
        let scene = Scene::new(scene.mesh, ConstraintSet::new(8), loads).unwrap();
        let deck = write_deck(&scene, &CalculixOptions::default()).unwrap();
        assert!(deck.contains("*CLOAD"));
        assert!(!deck.contains(", P"));
        let deck = write_deck(&scene, &CalculixOptions::linear()).unwrap();
        assert!(!deck.contains("*CLOAD"));
        assert!(deck.contains(", P"));
    }

    #[test]
    fn parses_the_last_increment() {
        let dat = "\n displacements (vx,vy,vz) for set NALL and time  0.5000000E+00\n\n\
                   \x20        1  1.000000E+00  0.000000E+00  0.000000E+00\n\
                   \x20        2  0.000000E+00  2.000000E+00  0.000000E+00\n\n\
                   \x20displacements (vx,vy,vz) for set NALL and time  0.1000000E+01\n\n\
                   \x20        1  2.000000E+00  0.000000E+00  0.000000E+00\n\
                   \x20        2  0.000000E+00  4.000000E+00 -1.500000E-03\n\n";
        let (t, u) = parse_dat_displacements(dat, 2).unwrap();
        assert_eq!(t, 1.0);
        assert_eq!(u[1], V3::new(0.0, 4.0, -1.5e-3));
        assert!(parse_dat_displacements(dat, 3).is_err());
        assert!(parse_dat_displacements("nothing", 1).is_err());
    }

    #[test]
    fn peak_memory_is_read_from_proc_status() {
        let status = "Name:\tccx\nVmPeak:\t  900 kB\nVmHWM:\t  123456 kB\nVmRSS:\t 1 kB\n";
        assert_eq!(vm_hwm_kb(status), Some(123456.0));
        assert_eq!(vm_hwm_kb("Name:\tccx\n"), None);
    }

    #[test]
    fn increments_are_counted_once_per_converged_increment() {
        let stdout = " STEP 1\n\n increment 1 attempt 1 \n increment size= 1.0e-01\n \
                      iteration 1\n increment 2 attempt 1 \n increment 2 attempt 2 \n \
                      increment 3 attempt 1 \n Job finished\n";
        assert_eq!(increment_count(stdout), 3);
        assert_eq!(increment_count(""), 0);
    }
}
