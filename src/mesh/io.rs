//! Mesh files: PLY (ASCII, binary little- and big-endian) through `ply-rs-bw`; OBJ in-house.
//!
//! Reading keeps only positions (any numeric type, converted to f64 mm) and faces (polygons are
//! fan-triangulated); other vertex and face properties (colours, normals, `quality`, …) are
//! ignored. Every index is checked against the vertex count and every coordinate for finiteness,
//! so what comes out is a well-formed [`TriMesh`] (topology is checked by [`super::validate`]).
//! Writing is atomic (temporary file + rename).

use std::fs::File;
use std::io::{self, BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use nalgebra::Point3;
use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{
    Addable, ElementDef, Encoding, Header, Ply, Property, PropertyAccess, PropertyAccessResult,
    PropertyDef, PropertyType, ScalarType,
};
use ply_rs_bw::writer::Writer;

use super::TriMesh;
use crate::util::atomic::write_atomic;

/// Why a mesh file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum MeshIoError {
    #[error("cannot open {path}: {cause}")]
    Open { path: PathBuf, cause: io::Error },
    #[error("cannot write {path}: {cause}")]
    Write { path: PathBuf, cause: io::Error },
    #[error("{path}: unknown mesh format '{ext}' (use .ply or .obj)")]
    UnknownFormat { path: PathBuf, ext: String },
    #[error("{path}: not a readable {format} file: {msg}")]
    Parse {
        path: PathBuf,
        format: &'static str,
        msg: String,
    },
    #[error("{path}: {msg}")]
    Content { path: PathBuf, msg: String },
    #[error(
        "{path}: face {face} refers to vertex {index}, but the file has {nverts} vertices \
         (indices 0..{nverts})"
    )]
    IndexOutOfRange {
        path: PathBuf,
        face: usize,
        index: i64,
        nverts: usize,
    },
    #[error("{path}: vertex {vertex} has a non-finite coordinate ({x}, {y}, {z})")]
    NonFinite {
        path: PathBuf,
        vertex: usize,
        x: f64,
        y: f64,
        z: f64,
    },
}

/// On-disk mesh formats glasscan writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshFormat {
    /// Binary little-endian PLY with double-precision positions.
    PlyBinary,
    /// ASCII PLY with double-precision positions.
    PlyAscii,
    /// Wavefront OBJ (positions and faces only).
    Obj,
}

impl MeshFormat {
    /// The format implied by a file name: `.ply` → binary PLY, `.obj` → OBJ.
    pub fn from_path(path: &Path) -> Result<Self, MeshIoError> {
        match extension(path).as_str() {
            "ply" => Ok(MeshFormat::PlyBinary),
            "obj" => Ok(MeshFormat::Obj),
            ext => Err(MeshIoError::UnknownFormat {
                path: path.into(),
                ext: ext.into(),
            }),
        }
    }
}

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

/// Reads a PLY or OBJ mesh (chosen by the file extension).
pub fn read_mesh(path: &Path) -> Result<TriMesh, MeshIoError> {
    read_mesh_with_quality(path).map(|(mesh, _)| mesh)
}

/// Reads a mesh and its per-vertex `quality` property, when it is a PLY file that has one (as
/// `reconstruct`'s result carries its confidence).
pub fn read_mesh_with_quality(path: &Path) -> Result<(TriMesh, Option<Vec<f64>>), MeshIoError> {
    let ((positions, polygons), quality) = match extension(path).as_str() {
        "ply" => read_ply(path)?,
        "obj" => (read_obj(path)?, None),
        ext => {
            return Err(MeshIoError::UnknownFormat {
                path: path.into(),
                ext: ext.into(),
            })
        }
    };
    Ok((assemble(path, positions, polygons)?, quality))
}

/// Writes `mesh` to `path` atomically in the format its extension implies.
pub fn write_mesh(path: &Path, mesh: &TriMesh) -> Result<(), MeshIoError> {
    write_mesh_as(path, mesh, MeshFormat::from_path(path)?)
}

/// Writes `mesh` to `path` (a .ply file) atomically, binary, with a float vertex property
/// `quality` (one value per vertex; MeshLab colours by it).
pub fn write_mesh_with_quality(
    path: &Path,
    mesh: &TriMesh,
    quality: &[f64],
) -> Result<(), MeshIoError> {
    assert_eq!(
        quality.len(),
        mesh.positions.len(),
        "one quality per vertex"
    );
    if MeshFormat::from_path(path)? == MeshFormat::Obj {
        return Err(MeshIoError::UnknownFormat {
            path: path.into(),
            ext: "obj (a per-vertex quality needs .ply)".into(),
        });
    }
    write_atomic(path, |w| {
        write_ply_quality(w, mesh, Encoding::BinaryLittleEndian, Some(quality))
    })
    .map_err(|cause| MeshIoError::Write {
        path: path.into(),
        cause,
    })
}

/// Writes `mesh` to `path` atomically in `format`.
pub fn write_mesh_as(path: &Path, mesh: &TriMesh, format: MeshFormat) -> Result<(), MeshIoError> {
    let result = write_atomic(path, |w| match format {
        MeshFormat::PlyBinary => write_ply(w, mesh, Encoding::BinaryLittleEndian),
        MeshFormat::PlyAscii => write_ply(w, mesh, Encoding::Ascii),
        MeshFormat::Obj => write_obj(w, mesh),
    });
    result.map_err(|cause| MeshIoError::Write {
        path: path.into(),
        cause,
    })
}

/// What a file reader returns: positions (mm) and polygons (vertex indices as written).
type RawMesh = (Vec<[f64; 3]>, Vec<Vec<i64>>);

/// Checks indices and coordinates and fan-triangulates the polygons.
fn assemble(
    path: &Path,
    positions: Vec<[f64; 3]>,
    polygons: Vec<Vec<i64>>,
) -> Result<TriMesh, MeshIoError> {
    let nverts = positions.len();
    if let Some((v, p)) = positions
        .iter()
        .enumerate()
        .find(|(_, p)| !p.iter().all(|c| c.is_finite()))
    {
        return Err(MeshIoError::NonFinite {
            path: path.into(),
            vertex: v,
            x: p[0],
            y: p[1],
            z: p[2],
        });
    }
    let mut faces = Vec::with_capacity(polygons.len());
    for (f, poly) in polygons.iter().enumerate() {
        if poly.len() < 3 {
            return Err(MeshIoError::Content {
                path: path.into(),
                msg: format!(
                    "face {f} has {} vertices; a face needs at least 3",
                    poly.len()
                ),
            });
        }
        if let Some(&bad) = poly.iter().find(|&&i| i < 0 || i as usize >= nverts) {
            return Err(MeshIoError::IndexOutOfRange {
                path: path.into(),
                face: f,
                index: bad,
                nverts,
            });
        }
        for k in 1..poly.len() - 1 {
            faces.push([poly[0] as u32, poly[k] as u32, poly[k + 1] as u32]);
        }
    }
    if faces.is_empty() {
        return Err(MeshIoError::Content {
            path: path.into(),
            msg: "the file holds no faces".into(),
        });
    }
    let positions = positions
        .into_iter()
        .map(|[x, y, z]| Point3::new(x, y, z))
        .collect();
    Ok(TriMesh::new(positions, faces))
}

// ---- PLY ----

/// One PLY vertex (x, y, z of any numeric type, and `quality` when present) or face (a
/// `vertex_indices`/`vertex_index` list of any integer type); everything else is ignored.
#[derive(Default)]
struct PlyVertex([f64; 3], u8, Option<f64>);

#[derive(Default)]
struct PlyFace(Vec<i64>);

fn scalar_f64(p: &Property) -> Option<f64> {
    Some(match *p {
        Property::Char(v) => v as f64,
        Property::UChar(v) => v as f64,
        Property::Short(v) => v as f64,
        Property::UShort(v) => v as f64,
        Property::Int(v) => v as f64,
        Property::UInt(v) => v as f64,
        Property::Float(v) => v as f64,
        Property::Double(v) => v,
        _ => return None,
    })
}

fn list_i64(p: Property) -> Option<Vec<i64>> {
    fn conv<T: Into<i64>>(v: Vec<T>) -> Vec<i64> {
        v.into_iter().map(Into::into).collect()
    }
    Some(match p {
        Property::ListChar(v) => conv(v),
        Property::ListUChar(v) => conv(v),
        Property::ListShort(v) => conv(v),
        Property::ListUShort(v) => conv(v),
        Property::ListInt(v) => conv(v),
        Property::ListUInt(v) => conv(v),
        _ => return None,
    })
}

impl PropertyAccess for PlyVertex {
    fn new() -> Self {
        Self::default()
    }
    fn set_property(&mut self, key: &str, property: Property) -> PropertyAccessResult {
        let k = match key {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            "quality" => {
                self.2 = scalar_f64(&property);
                return PropertyAccessResult::Set;
            }
            _ => return PropertyAccessResult::Ignored,
        };
        match scalar_f64(&property) {
            Some(v) => {
                self.0[k] = v;
                self.1 |= 1 << k;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::UnsupportedType,
        }
    }
}

impl PropertyAccess for PlyFace {
    fn new() -> Self {
        Self::default()
    }
    fn set_property(&mut self, key: &str, property: Property) -> PropertyAccessResult {
        if key != "vertex_indices" && key != "vertex_index" {
            return PropertyAccessResult::Ignored;
        }
        match list_i64(property) {
            Some(v) => {
                self.0 = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::UnsupportedType,
        }
    }
}

/// Bytes a PLY element (vertex, face) takes once read, as the budget counts them.
const PLY_BYTES_PER_ELEMENT: u128 = 96;

fn read_ply(path: &Path) -> Result<(RawMesh, Option<Vec<f64>>), MeshIoError> {
    let file = File::open(path).map_err(|cause| MeshIoError::Open {
        path: path.into(),
        cause,
    })?;
    // ply-rs-bw's messages may span lines and end in its parser's debug dump ("String: …",
    // "Error: ParseError { … }"); keep ours to the one line that says what is wrong.
    let parse_err = |e: &dyn std::fmt::Display| {
        let text = e.to_string();
        let lines: Vec<&str> = text.split('\n').map(str::trim).collect();
        let msg = lines.join("; ");
        let cut = ["; String:", "; Error:"]
            .iter()
            .filter_map(|m| msg.find(m))
            .min()
            .filter(|&i| i > 0)
            .unwrap_or(msg.len());
        MeshIoError::Parse {
            path: path.into(),
            format: "PLY",
            msg: msg[..cut].to_string(),
        }
    };
    let mut reader = Reader::new(BufReader::new(file));
    let vparser = Parser::<PlyVertex>::new();
    let fparser = Parser::<PlyFace>::new();
    let header = vparser
        .read_header(&mut reader)
        .map_err(|e| parse_err(&e))?;
    let mut verts: Option<Vec<PlyVertex>> = None;
    let mut faces: Option<Vec<PlyFace>> = None;
    for (name, element) in &header.elements {
        // The reader sizes its lists from the header's counts: check them first.
        crate::util::budget::check(
            &format!("the header's {} '{name}' elements", element.count),
            element.count as u128,
            PLY_BYTES_PER_ELEMENT,
            "is the file damaged? a mesh of this size needs a larger machine",
        )
        .map_err(|e| parse_err(&e))?;
        match name.as_str() {
            "vertex" => {
                let read = (&mut reader, element, &header);
                verts = Some(read_counted(&vparser, read, "vertices", &parse_err)?);
            }
            "face" => {
                let read = (&mut reader, element, &header);
                faces = Some(read_counted(&fparser, read, "faces", &parse_err)?);
            }
            // Other elements (edges, materials, …) must still be read to reach later ones.
            _ => {
                Parser::<ply_rs_bw::ply::DefaultElement>::new()
                    .read_payload_for_element(&mut reader, element, &header)
                    .map_err(|e| parse_err(&e))?;
            }
        }
    }
    let verts = verts.ok_or_else(|| parse_err(&"no 'vertex' element"))?;
    let faces =
        faces.ok_or_else(|| parse_err(&"no 'face' element (a point cloud is not a mesh)"))?;
    if let Some(i) = verts.iter().position(|v| v.1 != 0b111) {
        return Err(parse_err(&format!(
            "vertex {i} lacks one of the properties x, y, z"
        )));
    }
    let quality: Option<Vec<f64>> = verts.iter().map(|v| v.2).collect();
    Ok((
        (
            verts.into_iter().map(|v| v.0).collect(),
            faces.into_iter().map(|f| f.0).collect(),
        ),
        quality,
    ))
}

/// The `element`'s items, read with `parser`, checked to be as many as the header promises
/// (`what`: their name in the message; `parse_err` makes the error).
fn read_counted<E: PropertyAccess, R: BufRead>(
    parser: &Parser<E>,
    (reader, element, header): (&mut Reader<R>, &ElementDef, &Header),
    what: &str,
    parse_err: &dyn Fn(&dyn std::fmt::Display) -> MeshIoError,
) -> Result<Vec<E>, MeshIoError> {
    let items = parser
        .read_payload_for_element(reader, element, header)
        .map_err(|e| parse_err(&e))?;
    if items.len() != element.count {
        return Err(parse_err(&format!(
            "the header promises {} {what} but the file holds {}",
            element.count,
            items.len()
        )));
    }
    Ok(items)
}

/// A PLY element glasscan writes: a vertex (x, y, z as doubles, a quality as float) or a
/// triangle.
enum PlyOut {
    Vertex([f64; 3], f32),
    Face([u32; 3]),
}

impl PropertyAccess for PlyOut {
    fn new() -> Self {
        PlyOut::Vertex([0.0; 3], 0.0)
    }
    fn get_double(&self, key: &str) -> Option<f64> {
        match (self, key) {
            (PlyOut::Vertex(p, _), "x") => Some(p[0]),
            (PlyOut::Vertex(p, _), "y") => Some(p[1]),
            (PlyOut::Vertex(p, _), "z") => Some(p[2]),
            _ => None,
        }
    }
    fn get_float(&self, key: &str) -> Option<f32> {
        match (self, key) {
            (PlyOut::Vertex(_, q), "quality") => Some(*q),
            _ => None,
        }
    }
    fn get_list_uint(&self, key: &str) -> Option<&[u32]> {
        match (self, key) {
            (PlyOut::Face(f), "vertex_indices") => Some(f),
            _ => None,
        }
    }
}

fn write_ply(w: &mut dyn Write, mesh: &TriMesh, encoding: Encoding) -> io::Result<()> {
    write_ply_quality(w, mesh, encoding, None)
}

/// [`write_ply`] with a float vertex property `quality` when given.
fn write_ply_quality(
    w: &mut dyn Write,
    mesh: &TriMesh,
    encoding: Encoding,
    quality: Option<&[f64]>,
) -> io::Result<()> {
    let mut ply = Ply::<PlyOut>::new();
    ply.header.encoding = encoding;
    ply.header
        .comments
        .push("written by glasscan; units: mm".into());
    let mut vertex = ElementDef::new("vertex".into());
    for k in ["x", "y", "z"] {
        vertex.properties.add(PropertyDef::new(
            k.into(),
            PropertyType::Scalar(ScalarType::Double),
        ));
    }
    if quality.is_some() {
        vertex.properties.add(PropertyDef::new(
            "quality".into(),
            PropertyType::Scalar(ScalarType::Float),
        ));
    }
    vertex.count = mesh.positions.len();
    ply.header.elements.add(vertex);
    let mut face = ElementDef::new("face".into());
    face.properties.add(PropertyDef::new(
        "vertex_indices".into(),
        PropertyType::List(ScalarType::UChar, ScalarType::UInt),
    ));
    face.count = mesh.faces.len();
    ply.header.elements.add(face);
    ply.payload.insert(
        "vertex".into(),
        mesh.positions
            .iter()
            .enumerate()
            .map(|(i, p)| PlyOut::Vertex([p.x, p.y, p.z], quality.map_or(0.0, |q| q[i] as f32)))
            .collect(),
    );
    ply.payload.insert(
        "face".into(),
        mesh.faces.iter().map(|&f| PlyOut::Face(f)).collect(),
    );
    Writer::new().write_ply_unchecked(&mut WriteAdapter(w), &ply)?;
    Ok(())
}

/// `ply-rs-bw` wants a sized `Write`; this forwards to a `dyn Write`.
struct WriteAdapter<'a>(&'a mut dyn Write);

impl Write for WriteAdapter<'_> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0.write(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.0.flush()
    }
}

// ---- OBJ ----

/// Reads the `v` and `f` statements of an OBJ file (f64, vertex order kept, 1-based or negative
/// relative indices, `v/vt/vn` forms); other statements (normals, texture coordinates, groups,
/// materials) are ignored. In-house because `tobj` reads positions as f32 and renumbers vertices.
fn read_obj(path: &Path) -> Result<RawMesh, MeshIoError> {
    let file = File::open(path).map_err(|cause| MeshIoError::Open {
        path: path.into(),
        cause,
    })?;
    let parse_err = |line: usize, msg: String| MeshIoError::Parse {
        path: path.into(),
        format: "OBJ",
        msg: format!("line {line}: {msg}"),
    };
    let mut positions: Vec<[f64; 3]> = Vec::new();
    let mut polygons = Vec::new();
    let mut face_lines = Vec::new();
    for (n, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|e| parse_err(n + 1, e.to_string()))?;
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let mut p = [0.0; 3];
                for c in &mut p {
                    let w = words
                        .next()
                        .ok_or_else(|| parse_err(n + 1, "a vertex needs x y z".into()))?;
                    *c = w
                        .parse()
                        .map_err(|_| parse_err(n + 1, format!("'{w}' is not a number")))?;
                }
                positions.push(p);
            }
            Some("f") => {
                let poly = words
                    .map(|w| {
                        let idx = w.split('/').next().unwrap_or_default();
                        let i: i64 = idx.parse().map_err(|_| {
                            parse_err(n + 1, format!("'{w}' is not a vertex index"))
                        })?;
                        // OBJ indices are 1-based; negative ones count back from the last vertex.
                        let converted = match i {
                            0 => -1,
                            i if i < 0 => positions.len() as i64 + i,
                            i => i - 1,
                        };
                        if converted < 0 {
                            return Err(parse_err(
                                n + 1,
                                format!(
                                    "vertex index {w}: OBJ indices start at 1 (or count back \
                                     from -1), and {} vertices precede this face",
                                    positions.len()
                                ),
                            ));
                        }
                        Ok(converted)
                    })
                    .collect::<Result<Vec<i64>, _>>()?;
                polygons.push(poly);
                face_lines.push(n + 1);
            }
            _ => {}
        }
    }
    // Indices past the end, quoted as written (1-based) with their line.
    for (poly, line) in polygons.iter().zip(&face_lines) {
        if let Some(&bad) = poly.iter().find(|&&i| i as usize >= positions.len()) {
            return Err(parse_err(
                *line,
                format!(
                    "vertex index {}: the file has {} vertices (OBJ indices 1..={})",
                    bad + 1,
                    positions.len(),
                    positions.len()
                ),
            ));
        }
    }
    Ok((positions, polygons))
}

fn write_obj(w: &mut dyn Write, mesh: &TriMesh) -> io::Result<()> {
    writeln!(w, "# written by glasscan; units: mm")?;
    for p in &mesh.positions {
        writeln!(w, "v {} {} {}", p.x, p.y, p.z)?;
    }
    for f in &mesh.faces {
        writeln!(w, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1)?;
    }
    Ok(())
}
