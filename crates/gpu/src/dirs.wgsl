// Per-sample view directions for the network: every compacted sample of ray r gets the
// ray's unit direction (what the CPU trainer's `w.dir.extend(repeat_n(ray.d, n))` does).
// The marching kernel writes positions, dt and distances only; one invocation per ray
// copies its direction over its `n` samples (at most MAX_SAMPLES_PER_RAY).

struct DirsParams {
    n_rays: u32,
    row_width: u32,
    _pad0: u32,
    _pad1: u32,
}

// struct GenRay (rays.rs), 16 words: o (0..3), t, d (4..7), hit, bg, pixel, target, image.
@group(0) @binding(0) var<storage, read> drawn: array<f32>;
// struct GpuRay (loss.rs), 8 words: start, n, bg, target.
@group(0) @binding(1) var<storage, read> rays: array<u32>;
@group(0) @binding(2) var<storage, read_write> dirs: array<f32>;
@group(0) @binding(3) var<uniform> p: DirsParams;

@compute @workgroup_size(64)
fn dirs_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x + gid.y * p.row_width;
    if (r >= p.n_rays) {
        return;
    }
    let start = rays[8u * r];
    let n = rays[8u * r + 1u];
    let d = vec3<f32>(drawn[16u * r + 4u], drawn[16u * r + 5u], drawn[16u * r + 6u]);
    for (var j = 0u; j < n; j++) {
        let s = 3u * (start + j);
        dirs[s] = d.x;
        dirs[s + 1u] = d.y;
        dirs[s + 2u] = d.z;
    }
}
