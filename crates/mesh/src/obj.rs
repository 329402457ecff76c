//! Wavefront OBJ as instant-ngp writes it: `v x y z r g b` (colours in [0, 1], the common
//! extension that MeshLab, Blender and trimesh read), one `vn` a vertex, and faces that
//! name each vertex's normal (`f a//a b//b c//c`, 1-based).

use super::Mesh;
use ngp::error::Result;
use ngp::util::write_atomic_with;
use std::io::{BufWriter, Write};
use std::path::Path;

pub fn write_obj_to(out: &mut impl Write, mesh: &Mesh) -> std::io::Result<()> {
    writeln!(out, "# written by stegongp mesh")?;
    for (i, p) in mesh.positions.iter().enumerate() {
        let c = mesh.colours.get(i).copied().unwrap_or([200; 3]);
        // The shortest decimals that read back to the same float.
        writeln!(
            out,
            "v {} {} {} {:.4} {:.4} {:.4}",
            p[0],
            p[1],
            p[2],
            c[0] as f32 / 255.0,
            c[1] as f32 / 255.0,
            c[2] as f32 / 255.0
        )?;
    }
    for n in &mesh.normals {
        writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
    }
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|v| v as u64 + 1);
        writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}")?;
    }
    Ok(())
}

/// Writes the mesh to `path` atomically (a temporary file renamed over it).
pub fn write_obj(path: &Path, mesh: &Mesh) -> Result<()> {
    write_atomic_with(path, |f| {
        let mut b = BufWriter::with_capacity(1 << 20, f);
        write_obj_to(&mut b, mesh)?;
        b.flush()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_lines_name_every_vertex_normal_and_face() {
        let m = crate::ply::tests::tetrahedron();
        let mut buf = Vec::new();
        write_obj_to(&mut buf, &m).unwrap();
        let s = String::from_utf8(buf).unwrap();
        let count = |p: &str| s.lines().filter(|l| l.starts_with(p)).count();
        assert_eq!((count("v "), count("vn "), count("f ")), (4, 4, 4));
        assert!(s.contains("\nv 1 0 0 0.0000 1.0000 0.0000\n"), "{s}");
        assert!(s.contains("\nf 2//2 3//3 4//4\n"), "{s}");
    }
}
