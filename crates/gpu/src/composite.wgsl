// Rendering's compositing on the device (ngp::render::composite::composite and the wave loop
// of render_image): each ray keeps its running colour, depth and transmittance across
// waves of samples; `composite_main` folds one wave in, `finish_main` puts the background
// behind what is left and writes the pixel. Sigmoid colours, σ = exp(raw), front to back.

struct CompositeParams {
    n_rays: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    min_transmittance: f32,
    _pad: u32,
    background: vec4<f32>,
}

// Per ray: Σ w·c (rgb) and Σ w·t (depth, unnormalised); transmittance.
@group(0) @binding(0) var<storage, read_write> acc: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> trans: array<f32>;
// Per ray: this wave's samples, start and count in the sample buffers.
@group(0) @binding(2) var<storage, read> wave: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> raw: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> dt: array<f32>;
@group(0) @binding(5) var<storage, read> dist: array<f32>;
// Per ray: final rgb and opacity; depth (normalised by opacity).
@group(0) @binding(6) var<storage, read_write> pixel_rgba: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> pixel_depth: array<f32>;
@group(0) @binding(8) var<uniform> p: CompositeParams;

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

@compute @workgroup_size(64)
fn composite_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x + gid.y * p.row_width;
    if (r >= p.n_rays) {
        return;
    }
    let w = wave[r];
    var tr = trans[r];
    var a = acc[r];
    for (var j = 0u; j < w.y; j++) {
        if (tr < p.min_transmittance) {
            break;
        }
        let i = w.x + j;
        let s = raw[i];
        let alpha = 1.0 - exp(-exp(s.w) * dt[i]);
        let weight = alpha * tr;
        a += vec4<f32>(weight * vec3<f32>(sigmoid(s.x), sigmoid(s.y), sigmoid(s.z)), weight * dist[i]);
        tr *= 1.0 - alpha;
    }
    acc[r] = a;
    trans[r] = tr;
}

@compute @workgroup_size(64)
fn finish_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x + gid.y * p.row_width;
    if (r >= p.n_rays) {
        return;
    }
    let tr = trans[r];
    let a = acc[r];
    let opacity = 1.0 - tr;
    pixel_rgba[r] = vec4<f32>(a.xyz + tr * p.background.xyz, opacity);
    pixel_depth[r] = select(0.0, a.w / opacity, opacity > 0.0);
}
