// Compaction of a training batch to the samples that reach the loss (instant-ngp's
// `compute_loss_kernel_train_nerf` trains on the same set). A ray's samples reach the loss
// until its transmittance falls below the threshold, and that depends on the densities
// alone: the density network ran over every marched sample, and this kernel walks each
// ray's log-densities as the loss does (ngp::train::loss::ray_loss), counts its leading
// samples the transmittance reaches, reserves that many slots with one atomic add, and
// copies each one's position, step, distance and marched index there, with the ray's
// direction (what the CPU trainer's `w.dir.extend(repeat_n(ray.d, n))` gives its samples)
// and compacted range. The colour network, the loss and the backward then run on the
// compacted samples only. A ray whose slots would end past the capacity trains nothing
// and is counted; its compacted range is marked SKIP, so that the loss leaves the
// `(0, used)` written here.

struct CompactParams {
    n_rays: u32,
    row_width: u32,
    capacity: u32,
    min_transmittance: f32,
}

const SKIP: u32 = 0xffffffffu;

// struct GpuRay (loss.rs), 8 words: start, n, bg, target.
@group(0) @binding(0) var<storage, read> rays: array<u32>;
@group(0) @binding(1) var<storage, read> log_density: array<f32>;
@group(0) @binding(2) var<storage, read> dt: array<f32>;
@group(0) @binding(3) var<storage, read> dist: array<f32>;
@group(0) @binding(4) var<storage, read> pos: array<f32>;
// struct GenRay (rays.rs), 16 words: o (0..3), t, d (4..7), hit, bg, pixel, target, image.
@group(0) @binding(5) var<storage, read> drawn: array<f32>;
// Per ray: the compacted range (a GpuRay whose start and n index the compacted samples).
@group(0) @binding(6) var<storage, read_write> rays_c: array<u32>;
// Per ray: loss (written by the loss), samples used (bitcast).
@group(0) @binding(7) var<storage, read_write> ray_out: array<vec2<f32>>;
@group(0) @binding(8) var<storage, read_write> pos_c: array<f32>;
@group(0) @binding(9) var<storage, read_write> dirs_c: array<f32>;
@group(0) @binding(10) var<storage, read_write> dt_c: array<f32>;
@group(0) @binding(11) var<storage, read_write> dist_c: array<f32>;
// [0]: slots asked for, [1]: samples written, [2]: rays that did not fit, [3]: unused.
@group(0) @binding(12) var<storage, read_write> counters: array<atomic<u32>, 4>;
@group(0) @binding(13) var<uniform> p: CompactParams;
// Each compacted sample's marched index: the training pass copies its grid encoding from
// the marched pass's instead of computing it again (grid.wgsl, copy_main).
@group(0) @binding(14) var<storage, read_write> from_c: array<u32>;

@compute @workgroup_size(64)
fn compact_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x + gid.y * p.row_width;
    if (r >= p.n_rays) {
        return;
    }
    let start = rays[8u * r];
    let n = rays[8u * r + 1u];
    // The loss's forward loop, on the densities alone.
    var tr = 1.0;
    var used = 0u;
    for (var j = 0u; j < n; j++) {
        if (tr < p.min_transmittance) {
            break;
        }
        let alpha = 1.0 - exp(-exp(log_density[start + j]) * dt[start + j]);
        tr *= 1.0 - alpha;
        used = j + 1u;
    }
    ray_out[r] = vec2<f32>(0.0, bitcast<f32>(used));
    for (var k = 2u; k < 8u; k++) {
        rays_c[8u * r + k] = rays[8u * r + k];
    }
    rays_c[8u * r] = 0u;
    rays_c[8u * r + 1u] = 0u;
    if (used == 0u) {
        return;
    }
    let base = atomicAdd(&counters[0], used);
    // The second test catches the counter's wrap-around.
    if (base + used > p.capacity || base + used < base) {
        atomicAdd(&counters[2], 1u);
        rays_c[8u * r + 1u] = SKIP;
        return;
    }
    atomicAdd(&counters[1], used);
    let d = vec3<f32>(drawn[16u * r + 4u], drawn[16u * r + 5u], drawn[16u * r + 6u]);
    rays_c[8u * r] = base;
    rays_c[8u * r + 1u] = used;
    for (var j = 0u; j < used; j++) {
        let s = start + j;
        let c = base + j;
        pos_c[3u * c] = pos[3u * s];
        pos_c[3u * c + 1u] = pos[3u * s + 1u];
        pos_c[3u * c + 2u] = pos[3u * s + 2u];
        dirs_c[3u * c] = d.x;
        dirs_c[3u * c + 1u] = d.y;
        dirs_c[3u * c + 2u] = d.z;
        dt_c[c] = dt[s];
        dist_c[c] = dist[s];
        from_c[c] = s;
    }
}
