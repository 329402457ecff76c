//! Where a mesh's coordinates are written: the training data's frame, undoing the loader's
//! scale and offset. instant-ngp's `save_mesh` writes `(p − offset) / scale` and keeps ngp's
//! axis order (its x, y, z are the data's y, z, x); [`Axes::Dataset`] also undoes that
//! cycle, so that the mesh lies over the cameras of `transforms.json`.

use super::Mesh;
use ngp::error::{Error, Result};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Axes {
    /// As instant-ngp writes a mesh: scale and offset undone, ngp's axis order.
    #[default]
    InstantNgp,
    /// The dataset's own frame (`transforms.json`'s axes).
    Dataset,
}

impl ngp::choice::Choice for Axes {
    const ALL: &'static [Self] = &[Axes::InstantNgp, Axes::Dataset];
    fn name(self) -> &'static str {
        match self {
            Axes::InstantNgp => "instant-ngp",
            Axes::Dataset => "dataset",
        }
    }
    fn help(self) -> &'static str {
        match self {
            Axes::InstantNgp => {
                "as instant-ngp writes a mesh: the data's scale and offset undone, ngp's axis order (the data's y, z, x)"
            }
            Axes::Dataset => "the dataset's own axes, over the cameras of transforms.json",
        }
    }
}

impl std::fmt::Display for Axes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(ngp::choice::Choice::name(*self))
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// The loader's `scale` and `offset` (ngp = data · scale + offset).
    pub scale: f32,
    pub offset: [f32; 3],
    pub axes: Axes,
}

impl Frame {
    pub fn new(scale: f32, offset: [f32; 3], axes: Axes) -> Result<Self> {
        if !(scale.is_finite() && scale > 0.0 && offset.iter().all(|v| v.is_finite())) {
            return Err(Error::Config(format!(
                "the model's dataset scale {scale} and offset {offset:?} do not map back to \
                 the data's frame"
            )));
        }
        Ok(Frame {
            scale,
            offset,
            axes,
        })
    }

    /// An ngp-space position in the output frame.
    pub fn position(&self, p: [f32; 3]) -> [f32; 3] {
        let (s, o) = (self.scale, self.offset);
        match self.axes {
            Axes::InstantNgp => [0, 1, 2].map(|d| (p[d] - o[d]) / s),
            // ngp (x, y, z) = data (y, z, x) · scale + offset (offset in the data's order).
            Axes::Dataset => [(p[2] - o[0]) / s, (p[0] - o[1]) / s, (p[1] - o[2]) / s],
        }
    }

    /// The ngp-space position of an output-frame position (a `--box` corner).
    pub fn to_ngp(&self, q: [f32; 3]) -> [f32; 3] {
        let (s, o) = (self.scale, self.offset);
        match self.axes {
            Axes::InstantNgp => [0, 1, 2].map(|d| q[d] * s + o[d]),
            Axes::Dataset => [q[1] * s + o[1], q[2] * s + o[2], q[0] * s + o[0]],
        }
    }

    pub fn direction(&self, n: [f32; 3]) -> [f32; 3] {
        match self.axes {
            Axes::InstantNgp => n,
            Axes::Dataset => [n[2], n[0], n[1]],
        }
    }

    /// Moves an ngp-space mesh into this frame (a rotation and a positive scale: the
    /// triangles keep their winding).
    pub fn apply(&self, mesh: &mut Mesh) {
        for p in &mut mesh.positions {
            *p = self.position(*p);
        }
        for n in &mut mesh.normals {
            *n = self.direction(*n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_match_the_loader() {
        use ngp::camera::nerf_to_ngp;
        let (s, o) = (0.33, [0.5, 0.4, 0.3]);
        let t = [1.0, -2.0, 0.25];
        // The loader's image of a camera at data position t.
        let m = nerf_to_ngp(
            &[
                [1.0, 0.0, 0.0, t[0]],
                [0.0, 1.0, 0.0, t[1]],
                [0.0, 0.0, 1.0, t[2]],
            ],
            s,
            o,
        );
        let ngp = [m[0][3], m[1][3], m[2][3]];
        let f = Frame::new(s, o, Axes::Dataset).unwrap();
        let back = f.position(ngp);
        for d in 0..3 {
            assert!((back[d] - t[d]).abs() < 1e-5, "{back:?} vs {t:?}");
        }
        for axes in [Axes::InstantNgp, Axes::Dataset] {
            let f = Frame::new(s, o, axes).unwrap();
            let q = f.to_ngp(f.position(ngp));
            assert!((0..3).all(|d| (q[d] - ngp[d]).abs() < 1e-5));
        }
        assert!(Frame::new(0.0, o, Axes::Dataset).is_err());
        assert!(Frame::new(f32::NAN, o, Axes::Dataset).is_err());
    }
}
