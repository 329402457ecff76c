// Compaction of a training batch to the samples that reach the loss (instant-ngp's
// `compute_loss_kernel_train_nerf` writes the same compacted set): the loss kernel ran on
// the inference outputs of every marched sample and wrote, per ray, how many of its leading
// samples the transmittance reached (`ray_out[r].y`) and their raw-output gradient
// (`d_raw`, zero past them). One invocation per ray reserves that many slots with one
// atomic add and copies each used sample's position, direction and gradient there, so the
// training pass (grid, network forward keeping activations, backward) runs on exactly those.
// A ray whose slots would end past the capacity trains nothing and is counted.

struct CompactParams {
    n_rays: u32,
    row_width: u32,
    capacity: u32,
    _pad: u32,
}

// struct GpuRay (loss.rs), 8 words: start, n, bg, target.
@group(0) @binding(0) var<storage, read> rays: array<u32>;
// Per ray: loss, samples used (bitcast).
@group(0) @binding(1) var<storage, read> ray_out: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read> pos: array<f32>;
@group(0) @binding(3) var<storage, read> dirs: array<f32>;
@group(0) @binding(4) var<storage, read> d_raw: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> pos_c: array<f32>;
@group(0) @binding(6) var<storage, read_write> dirs_c: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_raw_c: array<vec4<f32>>;
// [0]: slots asked for, [1]: samples written, [2]: rays that did not fit, [3]: unused.
@group(0) @binding(8) var<storage, read_write> counters: array<atomic<u32>, 4>;
@group(0) @binding(9) var<uniform> p: CompactParams;

@compute @workgroup_size(64)
fn compact_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x + gid.y * p.row_width;
    if (r >= p.n_rays) {
        return;
    }
    let used = bitcast<u32>(ray_out[r].y);
    if (used == 0u) {
        return;
    }
    let start = rays[8u * r];
    let base = atomicAdd(&counters[0], used);
    // The second test catches the counter's wrap-around.
    if (base + used > p.capacity || base + used < base) {
        atomicAdd(&counters[2], 1u);
        return;
    }
    atomicAdd(&counters[1], used);
    for (var j = 0u; j < used; j++) {
        let s = start + j;
        let c = base + j;
        pos_c[3u * c] = pos[3u * s];
        pos_c[3u * c + 1u] = pos[3u * s + 1u];
        pos_c[3u * c + 2u] = pos[3u * s + 2u];
        dirs_c[3u * c] = dirs[3u * s];
        dirs_c[3u * c + 1u] = dirs[3u * s + 1u];
        dirs_c[3u * c + 2u] = dirs[3u * s + 2u];
        d_raw_c[c] = d_raw[s];
    }
}
