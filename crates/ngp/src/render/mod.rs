//! Ray marching through the occupancy grid, volume compositing (forward and backward), and
//! rendering whole images.

pub mod composite;
pub mod image;
pub mod march;

use crate::camera::Camera;
use crate::error::Result;
use image::{RenderOptions, RenderedImage, SceneView, render_image};

/// What evaluation needs from a renderer, whichever device runs it: one image per camera.
pub trait RenderBackend {
    fn render(&mut self, cam: &Camera, opts: &RenderOptions) -> Result<RenderedImage>;
}

impl RenderBackend for SceneView<'_> {
    fn render(&mut self, cam: &Camera, opts: &RenderOptions) -> Result<RenderedImage> {
        Ok(render_image(self, cam, opts))
    }
}
