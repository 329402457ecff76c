//! Binary little-endian PLY, as instant-ngp's `save_mesh` lays a mesh out (position,
//! normal, uchar colour; triangles as a uchar-counted int list), written through
//! `ply-rs-bw` (the maintained fork of `ply-rs`) one element at a time, so that no second
//! copy of the mesh is made.

use super::Mesh;
use ngp::error::Result;
use ngp::util::write_atomic_with;
use ply_rs_bw::ply::{
    Addable, ElementDef, Encoding, Header, PropertyAccess, PropertyDef, PropertyType, ScalarType,
};
use ply_rs_bw::writer::Writer;
use std::io::{BufWriter, Write};
use std::path::Path;

/// One vertex or one face, as the writer asks for their properties by name.
#[derive(Default)]
struct Element {
    p: [f32; 3],
    n: [f32; 3],
    c: [u8; 3],
    face: [i32; 3],
}

impl PropertyAccess for Element {
    fn new() -> Self {
        Element::default()
    }
    fn get_float(&self, name: &str) -> Option<f32> {
        Some(match name {
            "x" => self.p[0],
            "y" => self.p[1],
            "z" => self.p[2],
            "nx" => self.n[0],
            "ny" => self.n[1],
            "nz" => self.n[2],
            _ => return None,
        })
    }
    fn get_uchar(&self, name: &str) -> Option<u8> {
        Some(match name {
            "red" => self.c[0],
            "green" => self.c[1],
            "blue" => self.c[2],
            _ => return None,
        })
    }
    fn get_list_int(&self, name: &str) -> Option<&[i32]> {
        (name == "vertex_indices").then_some(&self.face[..])
    }
}

fn header(mesh: &Mesh) -> Header {
    let mut h = Header::new();
    h.encoding = Encoding::BinaryLittleEndian;
    h.comments.push("written by stegongp mesh".into());
    let mut v = ElementDef::new("vertex".into());
    v.count = mesh.positions.len();
    for name in ["x", "y", "z", "nx", "ny", "nz"] {
        v.properties.add(PropertyDef::new(
            name.into(),
            PropertyType::Scalar(ScalarType::Float),
        ));
    }
    for name in ["red", "green", "blue"] {
        v.properties.add(PropertyDef::new(
            name.into(),
            PropertyType::Scalar(ScalarType::UChar),
        ));
    }
    h.elements.add(v);
    let mut f = ElementDef::new("face".into());
    f.count = mesh.triangles.len();
    f.properties.add(PropertyDef::new(
        "vertex_indices".into(),
        PropertyType::List(ScalarType::UChar, ScalarType::Int),
    ));
    h.elements.add(f);
    h
}

/// The mesh as PLY into `out`.
pub fn write_ply_to(out: &mut impl Write, mesh: &Mesh) -> std::io::Result<()> {
    check_indices(mesh)?;
    let h = header(mesh);
    let w = Writer::<Element>::new();
    w.write_header(out, &h)?;
    let (vdef, fdef) = (&h.elements["vertex"], &h.elements["face"]);
    let mut e = Element::default();
    for (i, &p) in mesh.positions.iter().enumerate() {
        e.p = p;
        e.n = mesh.normals[i];
        e.c = mesh.colours.get(i).copied().unwrap_or([200; 3]);
        w.write_little_endian_element(out, &e, vdef)?;
    }
    for t in &mesh.triangles {
        e.face = t.map(|v| v as i32);
        w.write_little_endian_element(out, &e, fdef)?;
    }
    Ok(())
}

/// PLY's `int` indices hold at most 2^31 − 1 vertices.
fn check_indices(mesh: &Mesh) -> std::io::Result<()> {
    if mesh.positions.len() > i32::MAX as usize {
        return Err(std::io::Error::other(format!(
            "{} vertices: more than a PLY int index reaches",
            mesh.positions.len()
        )));
    }
    Ok(())
}

/// Writes the mesh to `path` atomically (a temporary file renamed over it).
pub fn write_ply(path: &Path, mesh: &Mesh) -> Result<()> {
    write_atomic_with(path, |f| {
        let mut b = BufWriter::with_capacity(1 << 20, f);
        write_ply_to(&mut b, mesh)?;
        b.flush()
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::DefaultElement;

    pub(crate) fn tetrahedron() -> Mesh {
        Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
            ],
            normals: vec![
                [-0.577, -0.577, -0.577],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
            ],
            colours: vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [7, 8, 9]],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        }
    }

    #[test]
    fn a_written_mesh_parses_back_to_the_same_values() {
        let m = tetrahedron();
        let mut buf = Vec::new();
        write_ply_to(&mut buf, &m).unwrap();
        let head = String::from_utf8_lossy(&buf[..buf.len().min(400)]).into_owned();
        assert!(
            head.starts_with("ply\nformat binary_little_endian 1.0\n"),
            "{head}"
        );
        let ply = Parser::<DefaultElement>::new()
            .read_ply(&mut buf.as_slice())
            .unwrap();
        let v = &ply.payload["vertex"];
        assert_eq!(v.len(), 4);
        use ply_rs_bw::ply::Property::*;
        assert!(matches!(v[1]["x"], Float(x) if x == 1.0));
        assert!(matches!(v[3]["blue"], UChar(9)));
        assert!(matches!(v[0]["nz"], Float(z) if z == -0.577));
        let f = &ply.payload["face"];
        assert_eq!(f.len(), 4);
        assert!(matches!(&f[3]["vertex_indices"], ListInt(l) if l == &vec![1, 2, 3]));
    }
}
