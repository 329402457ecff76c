//! Vertex colours from the colour network, as instant-ngp's `compute_mesh_vertex_colors`
//! takes them: the whole network at the vertex, seen along the direction from the box's
//! centre out through it (no better direction is known for a surface point), through the
//! sigmoid.

use ngp::network::nerf::CHUNK;
use ngp::render::composite::sigmoid;
use ngp::render::image::SceneView;
use rayon::prelude::*;

/// The colour of each ngp-space position under `view`.
pub fn vertex_colours(view: &SceneView, positions: &[[f32; 3]]) -> Vec<[u8; 3]> {
    let mut out = vec![[0u8; 3]; positions.len()];
    out.par_chunks_mut(CHUNK * 8)
        .zip(positions.par_chunks(CHUNK * 8))
        .for_each_init(
            || {
                (
                    view.net.inference_workspace(),
                    Vec::with_capacity(CHUNK),
                    Vec::with_capacity(CHUNK),
                    vec![[0.0f32; 4]; CHUNK],
                )
            },
            |(ws, pos, dir, raw), (o, p)| {
                for (oc, pc) in o.chunks_mut(CHUNK).zip(p.chunks(CHUNK)) {
                    pos.clear();
                    dir.clear();
                    for &q in pc {
                        pos.push(view.marcher.warp(q));
                        dir.push(outward(q));
                    }
                    view.net.forward_with(
                        view.params,
                        view.grid_table(),
                        view.indices,
                        pos,
                        dir,
                        ws,
                        raw,
                    );
                    for (c, r) in oc.iter_mut().zip(raw.iter()) {
                        // instant-ngp's (unsigned char)clamp(c · 255, 0, 255).
                        *c = [0, 1, 2].map(|k| (sigmoid(r[k]) * 255.0).clamp(0.0, 255.0) as u8);
                    }
                }
            },
        );
    out
}

/// The unit direction from the box's centre (0.5, 0.5, 0.5 in ngp space) through `p`.
fn outward(p: [f32; 3]) -> [f32; 3] {
    let d = [p[0] - 0.5, p[1] - 0.5, p[2] - 0.5];
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if l > 0.0 {
        d.map(|v| v / l)
    } else {
        [0.0, 0.0, 1.0]
    }
}
