// The NeRF network after the hash grid (crates/ngp/src/network/nerf.rs on the device): SH of the
// view direction, density MLP (DIN → 64 → 16, output 0 the log-density), colour MLP on
// [16 density outputs, 16 SH] (32 → 64 → 64 → 16, outputs 0..3 raw rgb), bias-free, ReLU
// hidden layers, forward and backward.
//
// The Rust side (crates/gpu/src/mlp.rs) prepends the constants this file uses and does not
// declare: T (samples per tile), SB = T / 8 (samples per invocation), N_ENC (grid features
// L·F), DIN (density inputs, N_ENC padded to 16), OFF_D0, OFF_D1, OFF_C0, OFF_C1, OFF_C2
// (the five weight matrices' offsets in the parameter vector), NW (weights of both MLPs),
// CH (samples per weight-gradient chunk).
//
// Layouts (all f32, feature-major like the CPU engine): enc and d_enc `[(l·F + f)·ld_enc + s]`;
// dirs `[3·s + c]`; out and d_out one vec4 per sample, [r, g, b, log-density]; the saved
// activations `acts[(row)·ld + s]` and per-layer output gradients `dys[(row)·ld + s]` with
// the row blocks below.

struct MlpParams {
    n: u32,
    ld_enc: u32,
    ld: u32,
    // forward: keep the activations backward needs in `acts`.
    store: u32,
    // Tiles per dispatch row: dispatches past 65535 workgroups fold into y.
    tiles_x: u32,
    n_chunks: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<storage, read> weights: array<f32>;
@group(0) @binding(1) var<storage, read> enc: array<f32>;
@group(0) @binding(2) var<storage, read> dirs: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> dens_out: array<f32>;
@group(0) @binding(5) var<storage, read_write> acts: array<f32>;
@group(0) @binding(6) var<storage, read_write> dys: array<f32>;
@group(0) @binding(7) var<storage, read> d_out: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> d_enc: array<f32>;
@group(0) @binding(9) var<storage, read_write> partials: array<f32>;
@group(0) @binding(10) var<storage, read_write> grad: array<f32>;
@group(0) @binding(11) var<uniform> p: MlpParams;

const WIDTH: u32 = 64u;
const DOUT: u32 = 16u;
const WG: u32 = 128u;

// Rows of `acts`: density hidden, colour input [density outputs, SH], colour hidden 1 and 2.
const A_DH: u32 = 0u;
const A_CIN: u32 = 64u;
const A_H1: u32 = 96u;
const A_H2: u32 = 160u;
// Rows of `dys` (dL/d(layer output), after the ReLU mask): density hidden, density outputs,
// colour hidden 1 and 2, rgb.
const G_DH: u32 = 0u;
const G_DOUT: u32 = 64u;
const G_H1: u32 = 80u;
const G_H2: u32 = 144u;
const G_RGB: u32 = 208u;

// One layer's weights, 64 × 64 at most (DIN ≤ 64), stored so that the 16 output rows an
// invocation group reads for one input are consecutive (no bank conflicts): M[k·64 + r].
var<workgroup> wsh: array<f32, 4096>;
// Two activation tiles of 64 rows × T samples, X at 0 and Y at TILE: each layer reads one and
// writes the other, so a tile goes through every layer without leaving the workgroup.
const TILE: u32 = 64u * T;
const X: u32 = 0u;
const Y: u32 = TILE;
var<workgroup> act: array<f32, 2u * TILE>;

fn tile_start(wid: vec3<u32>) -> u32 {
    return (wid.x + wid.y * p.tiles_x) * T;
}

// Forward weights: M[k·64 + r] = W[r][k] (W row-major rows × cols at `off`).
fn load_w_forward(off: u32, rows: u32, cols: u32, lid: u32) {
    for (var e = lid; e < rows * cols; e += WG) {
        wsh[(e % cols) * WIDTH + e / cols] = weights[off + e];
    }
}

// Backward weights (the transposed product): M[o·64 + i] = W[o][i].
fn load_w_backward(off: u32, rows: u32, cols: u32, lid: u32) {
    for (var e = lid; e < rows * cols; e += WG) {
        wsh[(e / cols) * WIDTH + e % cols] = weights[off + e];
    }
}

// dst[r][s] = act(Σ_{k < n_k} M[k·64 + r] · src[k][s]) for r < n_out (≤ 64), all T samples
// of the tile. Invocation lid owns rows rb + 16·g (g < 4) and samples sb + 8·j (j < SB):
// per input k, SB tile reads and 4 weight reads feed 4·SB multiply-adds, the four rows as
// one vec4 so that every index into the accumulators is a constant (dynamically indexed
// private arrays become memory, or gathers on a SIMD software adapter). Rows past n_out
// are computed from stale weights and dropped.
fn layer(src: u32, dst: u32, n_k: u32, n_out: u32, relu: bool, lid: u32) {
    let rb = lid % 16u;
    let sb = lid / 16u;
    var acc: array<vec4<f32>, SB>;
    for (var k = 0u; k < n_k; k++) {
        let m = k * WIDTH + rb;
        let w = vec4<f32>(wsh[m], wsh[m + 16u], wsh[m + 32u], wsh[m + 48u]);
        for (var j = 0u; j < SB; j++) {
            acc[j] = fma(w, vec4<f32>(act[src + k * T + sb + 8u * j]), acc[j]);
        }
    }
    for (var j = 0u; j < SB; j++) {
        var v = acc[j];
        if (relu) {
            v = max(v, vec4<f32>(0.0));
        }
        let o = dst + sb + 8u * j;
        for (var g = 0u; g < 4u; g++) {
            if (rb + 16u * g < n_out) {
                act[o + (rb + 16u * g) * T] = v[g];
            }
        }
    }
}

// The same for n_out ≤ 16 (the MLPs' output layers): one row per invocation.
fn layer16(src: u32, dst: u32, n_k: u32, n_out: u32, lid: u32) {
    let rb = lid % 16u;
    let sb = lid / 16u;
    var acc: array<f32, SB>;
    for (var k = 0u; k < n_k; k++) {
        let w = wsh[k * WIDTH + rb];
        for (var j = 0u; j < SB; j++) {
            acc[j] = fma(w, act[src + k * T + sb + 8u * j], acc[j]);
        }
    }
    if (rb < n_out) {
        for (var j = 0u; j < SB; j++) {
            act[dst + rb * T + sb + 8u * j] = acc[j];
        }
    }
}

// enc rows into tile X; rows N_ENC..DIN (the MLP's padding inputs) and samples past n are 0.
fn load_enc(s0: u32, lid: u32) {
    for (var e = lid; e < DIN * T; e += WG) {
        let r = e / T;
        let s = s0 + e % T;
        var v = 0.0;
        if (r < N_ENC && s < p.n) {
            v = enc[r * p.ld_enc + s];
        }
        act[X + e] = v;
    }
}

// `rows` rows of a tile to acts[(row0 + r)·ld + s].
fn store_acts(tile: u32, rows: u32, row0: u32, s0: u32, lid: u32) {
    for (var e = lid; e < rows * T; e += WG) {
        let s = s0 + e % T;
        if (s < p.n) {
            acts[(row0 + e / T) * p.ld + s] = act[tile + e];
        }
    }
}

// tcnn's SH constants (crates/ngp/src/encoding/sh.rs).
const C0: f32 = 0.28209479177387814;
const C1: f32 = 0.48860251190291987;
const C2: f32 = 1.0925484305920792;
const C3: f32 = 0.94617469575755997;
const C4: f32 = 0.31539156525251999;
const C5: f32 = 0.54627421529603959;
const C6: f32 = 0.59004358992664352;
const C7: f32 = 2.8906114426405538;
const C8: f32 = 0.45704579946446572;
const C9: f32 = 0.3731763325901154;
const C10: f32 = 1.4453057213202769;

// The 16 degree-4 SH coefficients of the direction the reference's encoder sees: instant-ngp
// feeds (d + 1) / 2 and the encoder maps it back with x·2 − 1 (`reference_direction`).
fn sh4(d: vec3<f32>) -> array<f32, 16> {
    let u = ((d + vec3<f32>(1.0)) * 0.5) * 2.0 - vec3<f32>(1.0);
    let x = u.x;
    let y = u.y;
    let z = u.z;
    let xy = x * y;
    let xz = x * z;
    let yz = y * z;
    let x2 = x * x;
    let y2 = y * y;
    let z2 = z * z;
    return array<f32, 16>(
        C0,
        -C1 * y,
        C1 * z,
        -C1 * x,
        C2 * xy,
        -C2 * yz,
        C3 * z2 - C4,
        -C2 * xz,
        C5 * x2 - C5 * y2,
        C6 * y * (-3.0 * x2 + y2),
        C7 * xy * z,
        C8 * y * (1.0 - 5.0 * z2),
        C9 * z * (5.0 * z2 - 3.0),
        C8 * x * (1.0 - 5.0 * z2),
        C10 * z * (x2 - y2),
        C6 * x * (-x2 + 3.0 * y2),
    );
}

// The density MLP's hidden layer of the tile into Y (enc and weights loaded here).
fn density_hidden(s0: u32, lid: u32) {
    load_enc(s0, lid);
    load_w_forward(OFF_D0, WIDTH, DIN, lid);
    workgroupBarrier();
    layer(X, Y, DIN, WIDTH, true, lid);
    workgroupBarrier();
}

// Forward of a tile of samples through both MLPs: out[s] = [r, g, b, log-density] raw; with
// p.store, the activations backward needs go to `acts`.
@compute @workgroup_size(128)
fn forward_main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let s0 = tile_start(wid);
    if (s0 >= p.n) {
        return;
    }
    let store = p.store != 0u;
    density_hidden(s0, lid);
    if (store) {
        store_acts(Y, WIDTH, A_DH, s0, lid);
    }
    load_w_forward(OFF_D1, DOUT, WIDTH, lid);
    workgroupBarrier();
    // Density outputs into X rows 0..16 (linear), SH into rows 16..32: the colour input.
    layer16(Y, X, WIDTH, DOUT, lid);
    if (lid < T) {
        var v = array<f32, 16>();
        let s = s0 + lid;
        if (s < p.n) {
            v = sh4(vec3<f32>(dirs[3u * s], dirs[3u * s + 1u], dirs[3u * s + 2u]));
        }
        for (var k = 0u; k < 16u; k++) {
            act[X + (DOUT + k) * T + lid] = v[k];
        }
    }
    workgroupBarrier();
    // Invocation lid < T writes sample lid's output at the end; the log-density is
    // overwritten in the tile before then, so it keeps it.
    var log_density = 0.0;
    if (lid < T) {
        log_density = act[X + lid];
    }
    if (store) {
        store_acts(X, DOUT + 16u, A_CIN, s0, lid);
    }
    load_w_forward(OFF_C0, WIDTH, DOUT + 16u, lid);
    workgroupBarrier();
    layer(X, Y, DOUT + 16u, WIDTH, true, lid);
    workgroupBarrier();
    if (store) {
        store_acts(Y, WIDTH, A_H1, s0, lid);
    }
    load_w_forward(OFF_C1, WIDTH, WIDTH, lid);
    workgroupBarrier();
    layer(Y, X, WIDTH, WIDTH, true, lid);
    workgroupBarrier();
    if (store) {
        store_acts(X, WIDTH, A_H2, s0, lid);
    }
    // Only the 3 used rows of the padded 16 × 64 output matrix.
    load_w_forward(OFF_C2, 3u, WIDTH, lid);
    workgroupBarrier();
    layer16(X, Y, WIDTH, 3u, lid);
    workgroupBarrier();
    let s = s0 + lid;
    if (lid < T && s < p.n) {
        out[s] = vec4<f32>(act[Y + lid], act[Y + T + lid], act[Y + 2u * T + lid], log_density);
    }
}

// Density only (NerfNetwork::density): the hidden layer, then output row 0.
@compute @workgroup_size(128)
fn density_main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let s0 = tile_start(wid);
    if (s0 >= p.n) {
        return;
    }
    density_hidden(s0, lid);
    load_w_forward(OFF_D1, 1u, WIDTH, lid);
    workgroupBarrier();
    layer16(Y, X, WIDTH, 1u, lid);
    workgroupBarrier();
    let s = s0 + lid;
    if (lid < T && s < p.n) {
        dens_out[s] = act[X + lid];
    }
}

// Zeroes the gradient rows of a tile where the ReLU below was off (saved activation ≤ 0,
// as the CPU's mask), and saves them in dys for the weight gradients.
fn mask_and_store(tile: u32, rows: u32, act_row0: u32, dy_row0: u32, s0: u32, lid: u32) {
    for (var e = lid; e < rows * T; e += WG) {
        let r = e / T;
        let s = s0 + e % T;
        if (s < p.n) {
            var v = act[tile + e];
            if (acts[(act_row0 + r) * p.ld + s] <= 0.0) {
                v = 0.0;
            }
            act[tile + e] = v;
            dys[(dy_row0 + r) * p.ld + s] = v;
        }
    }
}

// Backward of a tile through both MLPs down to d_enc, after forward_main with p.store on the
// same samples; every layer's output gradient goes to `dys` for wgrad_main.
@compute @workgroup_size(128)
fn backward_main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let s0 = tile_start(wid);
    if (s0 >= p.n) {
        return;
    }
    // d rgb into X rows 0..3 (zero past n, so padding samples stay zero all the way down).
    if (lid < T) {
        let s = s0 + lid;
        var g = vec4<f32>(0.0);
        if (s < p.n) {
            g = d_out[s];
            dys[G_RGB * p.ld + s] = g.x;
            dys[(G_RGB + 1u) * p.ld + s] = g.y;
            dys[(G_RGB + 2u) * p.ld + s] = g.z;
        }
        act[X + lid] = g.x;
        act[X + T + lid] = g.y;
        act[X + 2u * T + lid] = g.z;
    }
    load_w_backward(OFF_C2, 3u, WIDTH, lid);
    workgroupBarrier();
    layer(X, Y, 3u, WIDTH, false, lid);
    workgroupBarrier();
    mask_and_store(Y, WIDTH, A_H2, G_H2, s0, lid);
    load_w_backward(OFF_C1, WIDTH, WIDTH, lid);
    workgroupBarrier();
    layer(Y, X, WIDTH, WIDTH, false, lid);
    workgroupBarrier();
    mask_and_store(X, WIDTH, A_H1, G_H1, s0, lid);
    // Only the density-output half of the colour input needs a gradient (SH is fixed).
    load_w_backward(OFF_C0, WIDTH, DOUT + 16u, lid);
    workgroupBarrier();
    layer16(X, Y, WIDTH, DOUT, lid);
    workgroupBarrier();
    // The log-density reaches density output 0 directly as well as through the colour MLP.
    // The density outputs are linear: no mask.
    for (var e = lid; e < DOUT * T; e += WG) {
        let s = s0 + e % T;
        if (s < p.n) {
            var v = act[Y + e];
            if (e < T) {
                v += d_out[s].w;
            }
            act[Y + e] = v;
            dys[(G_DOUT + e / T) * p.ld + s] = v;
        }
    }
    load_w_backward(OFF_D1, DOUT, WIDTH, lid);
    workgroupBarrier();
    layer(Y, X, DOUT, WIDTH, false, lid);
    workgroupBarrier();
    mask_and_store(X, WIDTH, A_DH, G_DH, s0, lid);
    load_w_backward(OFF_D0, WIDTH, DIN, lid);
    workgroupBarrier();
    layer(X, Y, WIDTH, N_ENC, false, lid);
    workgroupBarrier();
    for (var e = lid; e < N_ENC * T; e += WG) {
        let s = s0 + e % T;
        if (s < p.n) {
            d_enc[(e / T) * p.ld_enc + s] = act[Y + e];
        }
    }
}

// Sub-tile of the weight-gradient product: 32 samples of dY (rows) and of X (columns), both
// sample-major in wsh so that the rows (columns) an invocation group reads are consecutive.
const ST: u32 = 32u;
const WG_X: u32 = 64u * ST;

// Per (chunk of CH samples, matrix): partial dW[o][i] = Σ_s dY[o][s] · X[i][s] over the
// chunk, written to partials[chunk·NW + (matrix offset − OFF_D0) + o·cols + i]; reduce_main
// sums the chunks in order. Matrices (wid.y): 0 density input, 1 density output, 2 colour
// input, 3 colour hidden, 4 colour output (3 used rows of 16; the padded rows get 0).
@compute @workgroup_size(128)
fn wgrad_main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let chunk = wid.x;
    // (offset, rows, cols, rows with a gradient, cols with an input, dY row, X row,
    // X from enc).
    var off = OFF_D0;
    var rows = WIDTH;
    var cols = DIN;
    var rows_used = WIDTH;
    var cols_used = N_ENC;
    var dy_row = G_DH;
    var x_row = 0u;
    var from_enc = true;
    switch wid.y {
        case 1u: {
            off = OFF_D1; rows = DOUT; cols = WIDTH; rows_used = DOUT; cols_used = WIDTH;
            dy_row = G_DOUT; x_row = A_DH; from_enc = false;
        }
        case 2u: {
            off = OFF_C0; rows = WIDTH; cols = DOUT + 16u; rows_used = WIDTH;
            cols_used = DOUT + 16u; dy_row = G_H1; x_row = A_CIN; from_enc = false;
        }
        case 3u: {
            off = OFF_C1; rows = WIDTH; cols = WIDTH; rows_used = WIDTH; cols_used = WIDTH;
            dy_row = G_H2; x_row = A_H1; from_enc = false;
        }
        case 4u: {
            off = OFF_C2; rows = DOUT; cols = WIDTH; rows_used = 3u; cols_used = WIDTH;
            dy_row = G_RGB; x_row = A_H2; from_enc = false;
        }
        default: {}
    }
    // Invocation lid owns rows rb + 16·g (g < 4, one vec4) and columns cb + 8·c (c < 8).
    let rb = lid % 16u;
    let cb = lid / 16u;
    var acc: array<vec4<f32>, 8>;
    let begin = chunk * CH;
    let end = min(begin + CH, p.n);
    for (var b = begin; b < end; b += ST) {
        for (var e = lid; e < WIDTH * ST; e += WG) {
            let r = e / ST;
            let s = e % ST;
            let gs = b + s;
            var dy = 0.0;
            var x = 0.0;
            if (gs < end) {
                if (r < rows_used) {
                    dy = dys[(dy_row + r) * p.ld + gs];
                }
                if (r < cols_used) {
                    if (from_enc) {
                        x = enc[r * p.ld_enc + gs];
                    } else {
                        x = acts[(x_row + r) * p.ld + gs];
                    }
                }
            }
            wsh[s * WIDTH + r] = dy;
            wsh[WG_X + s * WIDTH + r] = x;
        }
        workgroupBarrier();
        for (var s = 0u; s < ST; s++) {
            let m = s * WIDTH + rb;
            let dy = vec4<f32>(wsh[m], wsh[m + 16u], wsh[m + 32u], wsh[m + 48u]);
            for (var c = 0u; c < 8u; c++) {
                acc[c] = fma(dy, vec4<f32>(wsh[WG_X + s * WIDTH + cb + 8u * c]), acc[c]);
            }
        }
        workgroupBarrier();
    }
    let base = chunk * NW + off - OFF_D0;
    for (var c = 0u; c < 8u; c++) {
        let i = cb + 8u * c;
        for (var g = 0u; g < 4u; g++) {
            let r = rb + 16u * g;
            if (r < rows && i < cols) {
                partials[base + r * cols + i] = acc[c][g];
            }
        }
    }
}

// grad[OFF_D0 + e] += Σ_chunk partials[chunk·NW + e], the chunks in order: the sum is the same
// on every run and every adapter (no atomics).
@compute @workgroup_size(128)
fn reduce_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= NW) {
        return;
    }
    var sum = 0.0;
    for (var c = 0u; c < p.n_chunks; c++) {
        sum += partials[c * NW + e];
    }
    grad[OFF_D0 + e] += sum;
}
