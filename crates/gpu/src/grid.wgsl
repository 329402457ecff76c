// Multi-resolution hash-grid encoding, forward and backward, as the CPU's
// crates/ngp/src/encoding/grid.rs computes it: per (sample, level) the cell of `cell_of`, the 8
// corner entries of `level_corners` (index.wgsl, bit-identical to the CPU) and trilinear
// weights, formed with the same f32 operations in the same order.
//
// Concatenated after index.wgsl. The including module also declares, at binding 8,
//   grad: array<atomic<f32>> or array<atomic<u32>>
// and `fn grad_add(i: u32, v: f32)` adding v to grad[i] atomically (crates/gpu/src/grid.rs picks
// float atomics or a compare-and-swap loop when it builds the module).
//
// Layouts (all f32):
//   positions  3 per sample, sample s at [3s, 3s + 3), in [0, 1]^3
//   table      level l's entry e, feature f at (offset_l + e)·F + f (the grid block of the
//              parameter vector, as on the CPU)
//   enc, d_enc feature-major: feature l·F + f of sample s at (l·F + f)·ld + s, ld ≥ n (the
//              CPU's `enc`): consecutive invocations write consecutive words, and an MLP
//              reads one feature row of a tile of samples contiguously.

// The grid's own per-level geometry (GridLevel in grid.rs, 16 bytes).
struct GridLevel {
    scale: f32,
    // First entry of the level in the table, in entries.
    offset: u32,
    size: u32,
    _pad: u32,
}

struct GridParams {
    // First: a trainer whose sample count is known only on the device copies it here
    // (byte offset 0) instead of reading it back; invocations from n_samples to ld write
    // zero features and no gradient.
    n_samples: u32,
    ld: u32,
    // Invocations per dispatch row: dispatches wider than the device's workgroup limit fold
    // into y.
    row_width: u32,
    // copy_main: the leading dimension of the encodings it copies from.
    from_ld: u32,
}

// Features per level: 1, 2, 4 or 8 (grid.rs refuses others). A pipeline constant, so the
// feature loops have a fixed trip count after specialisation.
override N_FEATURES: u32 = 2u;
const MAX_FEATURES: u32 = 8u;

@group(0) @binding(0) var<storage, read> index_levels: array<LevelIndex>;
@group(0) @binding(1) var<storage, read> index_tables: array<u32>;
@group(0) @binding(2) var<storage, read> grid_levels: array<GridLevel>;
@group(0) @binding(3) var<uniform> params: GridParams;
@group(0) @binding(4) var<storage, read> positions: array<f32>;
// Forward only.
@group(0) @binding(5) var<storage, read> table: array<f32>;
@group(0) @binding(6) var<storage, read_write> enc: array<f32>;
// Backward only (and grad at binding 8).
@group(0) @binding(7) var<storage, read> d_enc: array<f32>;
// The table's fp16 copy (forward_half_main reads it, pack_half_main writes it): word w holds
// floats 2w and 2w + 1 of `table` (features f, f + 1 of an entry, F even), low half first.
@group(0) @binding(9) var<storage, read> table_half: array<u32>;
@group(0) @binding(10) var<storage, read_write> table_half_out: array<u32>;

struct Corners {
    entry: array<u32, 8>,
    weight: array<f32, 8>,
}

// ---- scale·x + 0.5 rounded once, as the CPU's `mul_add` ----

// WGSL's fma() need only be as accurate as a multiply and an add, and llvmpipe rounds
// twice; at a cell edge that puts a sample in the neighbouring cell (other entries read,
// and a fine level's output off by ~1e-4). So the one fma that chooses cells is computed
// exactly, in integers, unless the adapter's fma is fused (HARDWARE_FMA): llvmpipe's is not,
// so CI tests this path. The cost is some fifty integer operations per coordinate.

// 64-bit v >> r for 0 < r < 64, and whether any bit shifted out was set.
fn shr64_sticky(v: vec2<u32>, r: u32) -> vec3<u32> {
    if (r >= 32u) {
        let k = r - 32u;
        let lost = v.x != 0u || (v.y & ((1u << k) - 1u)) != 0u;
        return vec3<u32>(v.y >> k, 0u, select(0u, 1u, lost));
    }
    let lost = (v.x & ((1u << r) - 1u)) != 0u;
    return vec3<u32>((v.x >> r) | (v.y << (32u - r)), v.y >> r, select(0u, 1u, lost));
}

// Bit i of a 64-bit v, and whether any bit below it is set.
fn bit64(v: vec2<u32>, i: u32) -> u32 {
    if (i >= 32u) {
        return (v.y >> (i - 32u)) & 1u;
    }
    return (v.x >> i) & 1u;
}

fn any_below64(v: vec2<u32>, i: u32) -> bool {
    if (i >= 32u) {
        return v.x != 0u || (v.y & ((1u << (i - 32u)) - 1u)) != 0u;
    }
    return (v.x & ((1u << i) - 1u)) != 0u;
}

// RN(s·x + 0.5) for normal s, x > 0 with s·x < 2^23 (every grid: resolutions stop at
// 2048 × the aabb scale): the product of the 24-bit significands is exact in 48 bits,
// placed as a fixed-point number with 40 fractional bits (what falls below goes to a sticky
// bit), 0.5 added, and the sum rounded to 24 significant bits, ties to even. Zero,
// subnormal, negative and out-of-range inputs (no grid position) take the builtin fma.
// True where the adapter's fma() rounds once (crates/gpu/src/fma.rs probes it on grid-like
// inputs against the CPU's mul_add): then the builtin is the exact value.
override HARDWARE_FMA: bool = false;

fn fma_half(s: f32, x: f32) -> f32 {
    if (HARDWARE_FMA) {
        return fma(s, x, 0.5);
    }
    let sb = bitcast<u32>(s);
    let xb = bitcast<u32>(x);
    let se = sb >> 23u;
    let xe = xb >> 23u;
    // The sign bits are in se, xe: a negative input fails the range test.
    let k = i32(se + xe) - 260;
    if (se == 0u || se >= 255u || xe == 0u || xe >= 255u || k > 15) {
        return fma(s, x, 0.5);
    }
    // s·x = m·2^(se + xe − 300), m < 2^48; in units of 2^-40, m·2^k.
    let m = mul_wide((sb & 0x7fffffu) | 0x800000u, (xb & 0x7fffffu) | 0x800000u);
    var n: vec2<u32>;
    var sticky = false;
    if (k >= 0) {
        let u = u32(k);
        n = vec2<u32>(m.x << u, select(m.y, (m.y << u) | (m.x >> (32u - u)), u > 0u));
    } else if (k > -64) {
        let r = shr64_sticky(m, u32(-k));
        n = r.xy;
        sticky = r.z != 0u;
    } else {
        sticky = true;
    }
    // + 0.5 = 2^39; the sum is ≥ 2^39 and < 2^64, so its leading bit h is in the high word.
    let sum = add64(n, vec2<u32>(0u, 1u << 7u));
    let h = 32u + firstLeadingBit(sum.y);
    let d = h - 23u;
    var kept: u32;
    if (d >= 32u) {
        kept = sum.y >> (d - 32u);
    } else {
        kept = (sum.x >> d) | (sum.y << (32u - d));
    }
    let half = bit64(sum, d - 1u) != 0u;
    let up = half && (sticky || any_below64(sum, d - 1u) || (kept & 1u) != 0u);
    // kept·2^(d − 40) with its leading bit at h − 40: biased exponent h − 40 + 127; a
    // carry out of the significand on rounding up moves into the exponent, as it should.
    return bitcast<f32>(((h + 87u) << 23u) + (kept & 0x7fffffu) + select(0u, 1u, up));
}

// Sample s on level l: the CPU's `cell_of` (fma(scale, x, 0.5), floor, (u32)(i32)) and
// `level_corners`' weights, wx·wy·wz multiplied in that order. The backward recomputes this
// rather than reading a cache from the forward: the same code on the same inputs gives the
// same entries, and a cache would cost 64 bytes per (sample, level) written and read
// again (256 MiB at 2^18 samples × 16 levels) against a few dozen integer operations per
// corner for every index but SipHash; tiny-cuda-nn recomputes too.
fn grid_corners(l: u32, s: u32) -> Corners {
    let gl = grid_levels[l];
    var cell: vec3<u32>;
    var frac: vec3<f32>;
    for (var d = 0u; d < 3u; d++) {
        let p = fma_half(gl.scale, positions[3u * s + d]);
        let fl = floor(p);
        cell[d] = u32(i32(fl));
        frac[d] = p - fl;
    }
    var out: Corners;
    out.entry = level_corners(index_levels[l], cell);
    let wx = array<f32, 2>(1.0 - frac.x, frac.x);
    let wy = array<f32, 2>(1.0 - frac.y, frac.y);
    let wz = array<f32, 2>(1.0 - frac.z, frac.z);
    for (var c = 0u; c < 8u; c++) {
        out.weight[c] = wx[c & 1u] * wy[(c >> 1u) & 1u] * wz[c >> 2u];
    }
    return out;
}

// One invocation per (sample, level), the level in z: a workgroup's level, and so its
// index kind's branch, is uniform.
fn sample_of(gid: vec3<u32>) -> u32 {
    return gid.x + gid.y * params.row_width;
}

// Sample s's features of level l into enc, feature-major at leading dimension params.ld.
// Padding samples (s >= params.n_samples) pass zeros: the MLP may run over whole tiles of
// ld.
fn store_encoding(l: u32, s: u32, acc: ptr<function, array<f32, MAX_FEATURES>>) {
    let ld = params.ld;
    let out = l * N_FEATURES * ld + s;
    for (var f = 0u; f < N_FEATURES; f++) {
        enc[out + f * ld] = (*acc)[f];
    }
}

@compute @workgroup_size(128)
fn forward_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = sample_of(gid);
    let ld = params.ld;
    if (s >= ld) {
        return;
    }
    let l = gid.z;
    var acc: array<f32, MAX_FEATURES>;
    if (s < params.n_samples) {
        let k = grid_corners(l, s);
        let gl = grid_levels[l];
        for (var c = 0u; c < 8u; c++) {
            let e = k.entry[c];
            // An entry outside its level (an index failing LevelIndex::check, which the
            // CPU refuses with a panic) contributes nothing rather than another level's
            // features.
            if (e < gl.size) {
                let base = (gl.offset + e) * N_FEATURES;
                for (var f = 0u; f < N_FEATURES; f++) {
                    acc[f] = fma(k.weight[c], table[base + f], acc[f]);
                }
            }
        }
    }
    store_encoding(l, s, &acc);
}

// The encodings of samples whose forward already ran in a larger batch (a training step's
// compacted samples, each a marched one): sample s's columns copied from sample
// copy_from[s] of copy_enc, laid out with leading dimension params.from_ld. The same bits
// as forward_main over their positions, whatever table it read, since the parameters do
// not change between the two passes; padding samples get zeros as there.
@group(0) @binding(10) var<storage, read> copy_from: array<u32>;
@group(0) @binding(11) var<storage, read> copy_enc: array<f32>;

@compute @workgroup_size(128)
fn copy_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = sample_of(gid);
    let ld = params.ld;
    if (s >= ld) {
        return;
    }
    let l = gid.z;
    var acc: array<f32, MAX_FEATURES>;
    if (s < params.n_samples) {
        let from_ld = params.from_ld;
        let src = l * N_FEATURES * from_ld + copy_from[s];
        for (var f = 0u; f < N_FEATURES; f++) {
            acc[f] = copy_enc[src + f * from_ld];
        }
    }
    store_encoding(l, s, &acc);
}

// forward_main reading the fp16 copy, as tiny-cuda-nn's forward reads its fp16 parameters
// while Adam keeps the f32 master: half the bytes a corner, and the two features of a pair
// in one load. The same entries and weights; the features are the table's rounded to fp16.
@compute @workgroup_size(128)
fn forward_half_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = sample_of(gid);
    let ld = params.ld;
    if (s >= ld) {
        return;
    }
    let l = gid.z;
    var acc: array<f32, MAX_FEATURES>;
    if (s < params.n_samples) {
        let k = grid_corners(l, s);
        let gl = grid_levels[l];
        for (var c = 0u; c < 8u; c++) {
            let e = k.entry[c];
            if (e < gl.size) {
                let base = (gl.offset + e) * (N_FEATURES / 2u);
                for (var f = 0u; f < N_FEATURES; f += 2u) {
                    let v = unpack2x16float(table_half[base + f / 2u]);
                    acc[f] = fma(k.weight[c], v.x, acc[f]);
                    acc[f + 1u] = fma(k.weight[c], v.y, acc[f + 1u]);
                }
            }
        }
    }
    store_encoding(l, s, &acc);
}

// The fp16 copy of the table, one word (two floats) per invocation, params.n_samples words.
// Values past fp16's range (none a trained table holds) are clamped to it rather than left
// to pack2x16float, whose result there WGSL leaves undefined.
@compute @workgroup_size(128)
fn pack_half_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = sample_of(gid);
    if (w >= params.n_samples) {
        return;
    }
    let v = vec2<f32>(table[2u * w], table[2u * w + 1u]);
    table_half_out[w] = pack2x16float(clamp(v, vec2<f32>(-65504.0), vec2<f32>(65504.0)));
}

@compute @workgroup_size(128)
fn backward_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = sample_of(gid);
    let ld = params.ld;
    if (s >= params.n_samples || s >= ld) {
        return;
    }
    let l = gid.z;
    let row = l * N_FEATURES * ld + s;
    var g: array<f32, MAX_FEATURES>;
    var live = false;
    for (var f = 0u; f < N_FEATURES; f++) {
        g[f] = d_enc[row + f * ld];
        live = live || g[f] != 0.0;
    }
    // A sample whose features had no gradient (outside every ray's weight) skips the
    // index arithmetic.
    if (!live) {
        return;
    }
    let k = grid_corners(l, s);
    let gl = grid_levels[l];
    for (var c = 0u; c < 8u; c++) {
        let e = k.entry[c];
        if (e < gl.size) {
            let base = (gl.offset + e) * N_FEATURES;
            for (var f = 0u; f < N_FEATURES; f++) {
                grad_add(base + f, k.weight[c] * g[f]);
            }
        }
    }
}
