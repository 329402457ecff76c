// The occupancy grid's training update on the device, as ngp::occupancy::OccupancyGrid does
// it: draw the update's cells and positions (bit-identical to the CPU: the same PCG32 in
// 64-bit words, the same cell hash), then, once a density kernel has evaluated the field
// there, max-splat, decay, the cascade-0 mean, the bitfield and its OR-pooled cascades.
// Concatenated after u64.wgsl and pcg.wgsl.
//
// Layouts: density and `fresh` hold N_CELLS cells per cascade in Morton order; the bitfield
// holds one bit per cell, 32 cells per word, so its bytes are the CPU's Vec<u8> exactly.

const GRID_SIZE: u32 = 128u;
const N_CELLS: u32 = 2097152u; // 128³
const MIN_OPTICAL_THICKNESS: f32 = 0.01;
const DECAY: f32 = 0.95;
const MIN_CONE_STEPSIZE: f32 = 0.0016914559; // sqrt(3) / 1024, as the CPU's f32

struct OccParams {
    // PCG seed of this update: the CPU's `seed ^ (ema_step << 32)`.
    seed: vec2<u32>,
    n_uniform: u32,
    n_nonuniform: u32,
    // Updates so far (the CPU's ema_step), in the cell hash.
    ema_step: u32,
    n_cascades: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    // Cascade the pooling pass writes (1..n_cascades).
    level: u32,
    // The scene's box in ngp space: positions leave warped, w = (p − aabb_min) · inv_extent
    // (aabb sides are powers of two, so this is the CPU's division to the bit).
    aabb_min: vec3<f32>,
    inv_extent: f32,
    // A rebuild's draw: the first cell (cascade offset included; `n_uniform` cells from it)
    // and the octant of each cell its points fall in.
    first: u32,
    octant: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<storage, read_write> density: array<f32>;
@group(0) @binding(1) var<storage, read_write> fresh: array<atomic<u32>>;
@group(0) @binding(2) var<storage, read_write> bitfield: array<atomic<u32>>;
// Per sample: warped position (3 floats) and cell (including the cascade offset).
@group(0) @binding(3) var<storage, read_write> sample_pos: array<f32>;
@group(0) @binding(4) var<storage, read_write> sample_cell: array<u32>;
@group(0) @binding(5) var<storage, read> log_density: array<f32>;
// [0]: the cascade-0 sum (then the mean), [1..]: per-workgroup partial sums.
@group(0) @binding(6) var<storage, read_write> sums: array<f32>;
@group(0) @binding(7) var<uniform> p: OccParams;

// Every third bit of x, compacted (the CPU's morton3d_invert).
fn morton3d_invert(v: u32) -> u32 {
    var x = v & 0x49249249u;
    x = (x | (x >> 2u)) & 0xc30c30c3u;
    x = (x | (x >> 4u)) & 0x0f00f00fu;
    x = (x | (x >> 8u)) & 0xff0000ffu;
    x = (x | (x >> 16u)) & 0x0000ffffu;
    return x;
}

fn expand_bits(v: u32) -> u32 {
    var x = v & 0x3ffu;
    x = (x | (x << 16u)) & 0x030000ffu;
    x = (x | (x << 8u)) & 0x0300f00fu;
    x = (x | (x << 4u)) & 0x030c30c3u;
    x = (x | (x << 2u)) & 0x09249249u;
    return x;
}

fn morton3d(x: u32, y: u32, z: u32) -> u32 {
    return expand_bits(x) | (expand_bits(y) << 1u) | (expand_bits(z) << 2u);
}

// One draw of `generate_grid_samples_nerf_nonuniform`: sample i of a set of n (stream 1:
// all seen cells, threshold −0.01; stream 2: occupied cells).
fn draw(i: u32, n: u32, stream: u32, thresh: f32, out: u32) {
    var r = pcg_new(p.seed, i, stream);
    let nc = p.n_cascades;
    let level = u32(pcg_f32(&r) * f32(nc)) % nc;
    var idx = 0u;
    for (var j = 0u; j < 10u; j++) {
        idx = ((i + p.ema_step * n) * 56924617u + j * 19349663u + 96925573u) % N_CELLS;
        if (density[idx + level * N_CELLS] > thresh) {
            break;
        }
    }
    // The cell's corner and size in ngp space (cascade c spans 2^c around the centre).
    let s = f32(1u << level);
    let g = f32(GRID_SIZE);
    let cell = vec3<f32>(
        f32(morton3d_invert(idx)),
        f32(morton3d_invert(idx >> 1u)),
        f32(morton3d_invert(idx >> 2u)),
    );
    let o = (cell / g - 0.5) * s + 0.5;
    let vs = s / g;
    let q = vec3<f32>(o.x + vs * pcg_f32(&r), o.y + vs * pcg_f32(&r), o.z + vs * pcg_f32(&r));
    let w = (q - p.aabb_min) * p.inv_extent;
    sample_pos[3u * out] = w.x;
    sample_pos[3u * out + 1u] = w.y;
    sample_pos[3u * out + 2u] = w.z;
    sample_cell[out] = idx + level * N_CELLS;
}

@compute @workgroup_size(64)
fn sample_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x + gid.y * p.row_width;
    if (k < p.n_uniform) {
        draw(k, p.n_uniform, 1u, -0.01, k);
    } else if (k < p.n_uniform + p.n_nonuniform) {
        draw(k - p.n_uniform, p.n_nonuniform, 2u, MIN_OPTICAL_THICKNESS, k);
    }
}

// OccupancyGrid::points_in_cell_octant over cells first..first + n_uniform, as a rebuild
// draws them: sample k is cell c = first + k, drawn with Pcg32::new(seed, c) (seed is the
// round's `seed + round`, not mixed with the update count), x then y then z, uniform in the
// cell's octant `octant` (bit d: the upper half along axis d); warped like the others.
@compute @workgroup_size(64)
fn cell_points_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x + gid.y * p.row_width;
    if (k >= p.n_uniform) {
        return;
    }
    let c = p.first + k;
    var r = pcg_new(p.seed, c, 0u);
    let level = c / N_CELLS;
    let idx = c % N_CELLS;
    let s = f32(1u << level);
    let g = f32(GRID_SIZE);
    let cell = vec3<f32>(
        f32(morton3d_invert(idx)),
        f32(morton3d_invert(idx >> 1u)),
        f32(morton3d_invert(idx >> 2u)),
    );
    let o = (cell / g - 0.5) * s + 0.5;
    let vs = s / g;
    let lo = 0.5 * vec3<f32>(f32(p.octant & 1u), f32((p.octant >> 1u) & 1u), f32((p.octant >> 2u) & 1u));
    // Every product here is by a power of two (exact), so a fused multiply-add rounds as
    // the CPU's separate operations do.
    let x = o.x + vs * (lo.x + 0.5 * pcg_f32(&r));
    let y = o.y + vs * (lo.y + 0.5 * pcg_f32(&r));
    let z = o.z + vs * (lo.z + 0.5 * pcg_f32(&r));
    let w = (vec3<f32>(x, y, z) - p.aabb_min) * p.inv_extent;
    sample_pos[3u * k] = w.x;
    sample_pos[3u * k + 1u] = w.y;
    sample_pos[3u * k + 2u] = w.z;
}

// OccupancyGrid::splat_max after cell_points_main: sample k raises cell first + k to its
// optical thickness (one sample a cell per pass, so no atomics), no decay; culled cells
// (−1) stay culled.
@compute @workgroup_size(64)
fn splat_max_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x + gid.y * p.row_width;
    if (k >= p.n_uniform) {
        return;
    }
    let c = p.first + k;
    let t = exp(log_density[k]) * MIN_CONE_STEPSIZE;
    let d = density[c];
    if (d >= 0.0 && t > d) {
        density[c] = t;
    }
}

// Each sample raises its cell's fresh maximum. Optical thicknesses are ≥ 0, where float
// order is the order of the bit patterns, so an integer atomicMax takes the float maximum.
@compute @workgroup_size(64)
fn splat_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x + gid.y * p.row_width;
    if (k >= p.n_uniform + p.n_nonuniform) {
        return;
    }
    let t = exp(log_density[k]) * MIN_CONE_STEPSIZE;
    // NaN never wins a comparison on the CPU; here it would, as a large pattern.
    if (t > 0.0) {
        atomicMax(&fresh[sample_cell[k]], bitcast<u32>(t));
    }
}

// Decay every seen cell towards its fresh maximum; culled cells (−1) stay culled.
@compute @workgroup_size(256)
fn decay_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * p.row_width;
    if (i >= N_CELLS * p.n_cascades) {
        return;
    }
    let f = bitcast<f32>(atomicExchange(&fresh[i], 0u));
    let d = density[i];
    if (d >= 0.0) {
        density[i] = max(d * DECAY, f);
    }
}

var<workgroup> partial: array<f32, 256>;

// Cascade 0's cells clamped at 0, summed per workgroup of 256 (a fixed tree: deterministic).
@compute @workgroup_size(256)
fn sum_main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
) {
    let i = gid.x;
    partial[li] = max(density[i], 0.0);
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if (li < s) {
            partial[li] += partial[li + s];
        }
        workgroupBarrier();
    }
    if (li == 0u) {
        sums[1u + wg.x] = partial[0];
    }
}

// The 8192 partial sums, by one workgroup, into the mean.
@compute @workgroup_size(256)
fn mean_main(@builtin(local_invocation_index) li: u32) {
    var acc = 0.0;
    for (var k = li; k < N_CELLS / 256u; k += 256u) {
        acc += sums[1u + k];
    }
    partial[li] = acc;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if (li < s) {
            partial[li] += partial[li + s];
        }
        workgroupBarrier();
    }
    if (li == 0u) {
        sums[0] = partial[0] / f32(N_CELLS);
    }
}

// One word (32 cells) of every cascade's own bits, thresholded at min(0.01, mean).
@compute @workgroup_size(256)
fn bits_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = gid.x + gid.y * p.row_width;
    if (w >= N_CELLS / 32u * p.n_cascades) {
        return;
    }
    let thresh = min(MIN_OPTICAL_THICKNESS, sums[0]);
    var bits = 0u;
    for (var j = 0u; j < 32u; j++) {
        if (density[32u * w + j] > thresh) {
            bits |= 1u << j;
        }
    }
    atomicStore(&bitfield[w], bits);
}

// Cascade `level` ORs in its finer neighbour pooled 2×2×2: each byte of 8 fine cells sets
// one bit of the coarse cell that covers them (cascade c − 1 fills the middle eighth of c).
@compute @workgroup_size(256)
fn pool_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * p.row_width;
    if (i >= N_CELLS / 64u) {
        return;
    }
    let per_mip = N_CELLS / 32u; // words per cascade
    let fine = (p.level - 1u) * per_mip;
    var bits = 0u;
    for (var j = 0u; j < 8u; j++) {
        let byte_index = i * 8u + j;
        let word = atomicLoad(&bitfield[fine + byte_index / 4u]);
        if (((word >> (8u * (byte_index % 4u))) & 0xffu) != 0u) {
            bits |= 1u << j;
        }
    }
    if (bits == 0u) {
        return;
    }
    let q = GRID_SIZE / 8u;
    let m = morton3d(morton3d_invert(i) + q, morton3d_invert(i >> 1u) + q, morton3d_invert(i >> 2u) + q);
    atomicOr(&bitfield[p.level * per_mip + m / 4u], bits << (8u * (m % 4u)));
}
