// Training's loss on each ray (ngp::train::loss::ray_loss), one invocation per ray:
// front-to-back compositing over the ray's random background, instant-ngp's Huber loss
// (δ 0.1, ÷ 5) against the pixel, the exact gradient back to every sample's raw outputs,
// and the reference's two density regularisers. A ray's samples are contiguous (compacted)
// and few (the transmittance stops it), so one invocation walks them twice, as the CPU does.

struct LossParams {
    n_rays: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    loss_norm: f32,
    pull_up: f32,
    // The scene's box in ngp space: a warped position q lies at aabb_min + q·(aabb_max − aabb_min).
    aabb_min: vec3<f32>,
    min_transmittance: f32,
    aabb_max: vec3<f32>,
    near_distance: f32,
    near_push_down: f32,
    // 1: the pull-up applies only while the occupancy grid's mean (grid_mean[0], written
    // on the device by the last update) is below mean_below, as instant-ngp's loss kernel
    // reads the mean it is given on the device; 0: always.
    mean_gate: u32,
    mean_below: f32,
    _pad2: u32,
}

// start, n, background rgb, the pixel's rgb.
struct Ray {
    start: u32,
    n: u32,
    bg: array<f32, 3>,
    pixel: array<f32, 3>,
}

@group(0) @binding(0) var<storage, read> rays: array<Ray>;
// Per sample: raw r, g, b, log-density.
@group(0) @binding(1) var<storage, read> raw: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> dt: array<f32>;
@group(0) @binding(3) var<storage, read> dist: array<f32>;
// Per sample: the warped position, x y z.
@group(0) @binding(4) var<storage, read> pos: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_raw: array<vec4<f32>>;
// Per ray: loss (mean over channels), samples used (bitcast).
@group(0) @binding(6) var<storage, read_write> ray_out: array<vec2<f32>>;
@group(0) @binding(7) var<uniform> p: LossParams;
@group(0) @binding(8) var<storage, read> grid_mean: array<f32>;

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

@compute @workgroup_size(64)
fn loss_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x + gid.y * p.row_width;
    if (r >= p.n_rays) {
        return;
    }
    var pull_up = p.pull_up;
    if (p.mean_gate != 0u && !(grid_mean[0] < p.mean_below)) {
        pull_up = 0.0;
    }
    let ray = rays[r];
    // A ray the compaction could not fit (compact.wgsl's SKIP) trains nothing; its
    // `(0, used)` stays as the compaction wrote it.
    if (ray.n == 0xffffffffu) {
        return;
    }
    let bg = vec3<f32>(ray.bg[0], ray.bg[1], ray.bg[2]);
    let pixel = vec3<f32>(ray.pixel[0], ray.pixel[1], ray.pixel[2]);
    // Forward: what the ray shows and where it stops.
    var acc = vec3<f32>(0.0);
    var tr = 1.0;
    var n_used = 0u;
    for (var j = 0u; j < ray.n; j++) {
        if (tr < p.min_transmittance) {
            break;
        }
        let s = raw[ray.start + j];
        let alpha = 1.0 - exp(-exp(s.w) * dt[ray.start + j]);
        let w = alpha * tr;
        acc += w * vec3<f32>(sigmoid(s.x), sigmoid(s.y), sigmoid(s.z));
        tr *= 1.0 - alpha;
        n_used = j + 1u;
    }
    let pred = acc + tr * bg;
    // Huber, δ = 0.1, divided by 5, per channel.
    let d = pred - pixel;
    var loss = 0.0;
    var g = vec3<f32>(0.0);
    for (var k = 0u; k < 3u; k++) {
        if (abs(d[k]) > 0.1) {
            loss += abs(d[k]) - 0.05;
            g[k] = sign(d[k]);
        } else {
            loss += 5.0 * d[k] * d[k];
            g[k] = d[k] / 0.1;
        }
    }
    let dl = g / 5.0 * p.loss_norm;
    // Backward: d pred / d(σ·dt) = T_after·c − (what is still to come, background included).
    var acc2 = vec3<f32>(0.0);
    var tr2 = 1.0;
    for (var j = 0u; j < ray.n; j++) {
        let i = ray.start + j;
        if (j >= n_used) {
            d_raw[i] = vec4<f32>(0.0);
            continue;
        }
        let s = raw[i];
        let alpha = 1.0 - exp(-exp(s.w) * dt[i]);
        let w = alpha * tr2;
        let col = vec3<f32>(sigmoid(s.x), sigmoid(s.y), sigmoid(s.z));
        acc2 += w * col;
        tr2 *= 1.0 - alpha;
        let suffix = pred - acc2;
        let dtau = dot(dl, tr2 * col - suffix);
        // The reference clamps the exponent of the density derivative to [−15, 15].
        var dd = dtau * dt[i] * exp(clamp(s.w, -15.0, 15.0));
        if (s.w < 0.0) {
            // Inside occupancy cascade 0, the unit cube of ngp space (Marcher::in_cascade0).
            let q = vec3<f32>(pos[3u * i], pos[3u * i + 1u], pos[3u * i + 2u]);
            let x = p.aabb_min + q * (p.aabb_max - p.aabb_min);
            if (all(x >= vec3<f32>(0.0)) && all(x <= vec3<f32>(1.0))) {
                dd -= pull_up;
            }
        }
        if (s.w > -10.0 && dist[i] < p.near_distance) {
            dd += p.near_push_down;
        }
        d_raw[i] = vec4<f32>(dl * w * col * (1.0 - col), dd);
    }
    ray_out[r] = vec2<f32>(loss / 5.0 / 3.0, bitcast<f32>(n_used));
}
