// The NeRF network after the hash grid (crates/ngp/src/network/nerf.rs on the device): SH of the
// view direction, density MLP (DIN → 64 → 16, output 0 the log-density), colour MLP on
// [16 density outputs, 16 SH] (32 → 64 → 64 → 16, outputs 0..3 raw rgb), bias-free, ReLU
// hidden layers, forward and backward.
//
// The Rust side (crates/gpu/src/mlp.rs) prepends the constants this file uses and does not
// declare (N_ENC grid features L·F, DIN density inputs = N_ENC padded to 16, the five
// matrices' offsets OFF_* in the parameter vector and T* in the transposed copy, NW weights
// of both MLPs, CH samples per weight-gradient chunk, RG_CHUNKS chunks per reduction group)
// and appends the functions it generates: the register-blocked layer products `mmF{R}`
// (forward, from the transposed weights) and `mmB{R}` (backward, from the weights as
// stored), their tile and device-memory writes, and one weight-gradient kernel per matrix
// (`wgrad_{m}`), each written out with constant indices so that every accumulator is a
// register (a dynamically indexed private array becomes device memory).
//
// Layouts (f32, feature-major like the CPU engine): enc and d_enc `[(l·F + f)·ld_enc + s]`;
// dirs `[3·s + c]`; out and d_out one vec4 per sample, [r, g, b, log-density]; the saved
// activations `acts[(row)·ld + s]` and per-layer output gradients `dys[(row)·ld + s]` with
// the row blocks below, read and written as vec4 of 4 samples (ld is a multiple of 4).
//
// How a tile of T = 128 samples goes through a layer: invocation lid is lane lid % 32 of row
// group g = lid / 32; the lane owns samples 4·lane .. 4·lane + 3 (one vec4 of the tile row),
// the group owns R consecutive output rows. Per input k it reads one vec4 of the tile
// (consecutive lanes, consecutive vec4: no bank conflict) and R / 4 vec4 of weights, the
// same address for the whole subgroup (a broadcast from the cache), for 4·R multiply-adds.
// The products stay in registers until every invocation has read the tile, then overwrite
// it in place: one 64 × 128 tile (32 KiB) carries the samples through every layer.
//
// Runtime checks: the module is compiled without naga's index clamping and loop bounding
// (crates/gpu/src/mlp.rs says why each index is in bounds).

struct MlpParams {
    n: u32,
    ld_enc: u32,
    ld: u32,
    // forward: keep the activations backward needs in `acts`.
    store: u32,
    // Tiles per dispatch row: dispatches past 65535 workgroups fold into y.
    tiles_x: u32,
    // reduce_main: 0 sums each group of RG_CHUNKS chunks into the group's first chunk,
    // 1 sums the groups' first chunks into grad. The chunks are ⌈n / CH⌉ (n_chunks()):
    // n may be copied in on the device.
    stage: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<storage, read> weights4: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> enc: array<f32>;
@group(0) @binding(2) var<storage, read> dirs: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> dens_out: array<f32>;
@group(0) @binding(5) var<storage, read_write> acts4: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> dys4: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> d_out: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> d_enc: array<f32>;
@group(0) @binding(9) var<storage, read_write> partials: array<f32>;
@group(0) @binding(10) var<storage, read_write> grad: array<f32>;
@group(0) @binding(11) var<uniform> p: MlpParams;
// The forward's weights, transposed (input-major: W[r][k] at T* + k·rows + r) by
// transpose_main before each forward, so that a row group's R rows of one input are R / 4
// consecutive vec4.
@group(0) @binding(12) var<storage, read> wt4: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read_write> wt_out: array<f32>;

const WIDTH: u32 = 64u;
const DOUT: u32 = 16u;
const WG: u32 = 128u;
const T: u32 = 128u;
const LANES: u32 = 32u;

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

// 64 rows × 32 lanes × vec4 (4 samples): row r of lane l at tile[r·32 + l].
var<workgroup> tile: array<vec4<f32>, 2048>;

fn tile_start(wid: vec3<u32>) -> u32 {
    return (wid.x + wid.y * p.tiles_x) * T;
}

// Index of the vec4 holding samples sl..sl+3 of `row` in acts or dys (sl and ld are
// multiples of 4).
fn at4(row: u32, sl: u32) -> u32 {
    return (row * p.ld + sl) / 4u;
}

// The lane's 4 samples of one enc row (0 past n).
fn enc4(r: u32, sl: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    let b = r * p.ld_enc + sl;
    if (sl < p.n) { v.x = enc[b]; }
    if (sl + 1u < p.n) { v.y = enc[b + 1u]; }
    if (sl + 2u < p.n) { v.z = enc[b + 2u]; }
    if (sl + 3u < p.n) { v.w = enc[b + 3u]; }
    return v;
}

// enc rows into the tile; rows N_ENC..DIN (the MLP's padding inputs) and samples past n
// are 0.
fn load_enc(g: u32, lane: u32, sl: u32) {
    for (var r = g; r < DIN; r += 4u) {
        var v = vec4<f32>(0.0);
        if (r < N_ENC) {
            v = enc4(r, sl);
        }
        tile[r * LANES + lane] = v;
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

// Sample s0 + lid's SH into tile rows DOUT..DOUT+16 (0 past n): invocation lid writes
// component lid % 4 of lane lid / 4's vec4, consecutive words for consecutive invocations.
fn write_sh(s0: u32, lid: u32) {
    var v = array<f32, 16>();
    let s = s0 + lid;
    if (s < p.n) {
        v = sh4(vec3<f32>(dirs[3u * s], dirs[3u * s + 1u], dirs[3u * s + 2u]));
    }
    let l = lid / 4u;
    let c = lid % 4u;
    for (var k = 0u; k < 16u; k++) {
        tile[(DOUT + k) * LANES + l][c] = v[k];
    }
}

// The density MLP's hidden layer of the tile, left in the tile (rows 0..64), and kept in
// acts when asked.
fn density_hidden(g: u32, lane: u32, sl: u32, s0: u32, store: bool) {
    load_enc(g, lane, sl);
    workgroupBarrier();
    let h = relu16(mmF16((TD0 + 16u * g) / 4u, 16u, DIN, lane));
    workgroupBarrier();
    put16(h, 16u * g, lane);
    if (store && sl < p.n) {
        keep16(h, A_DH + 16u * g, sl);
    }
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
    let g = lid / LANES;
    let lane = lid % LANES;
    let sl = s0 + 4u * lane;
    let live = sl < p.n;
    let store = p.store != 0u;
    density_hidden(g, lane, sl, s0, store);
    // Density outputs (linear) into rows 0..16, SH into rows 16..32: the colour input.
    let d = mmF4((TD1 + 4u * g) / 4u, 4u, WIDTH, lane);
    workgroupBarrier();
    put4(d, 4u * g, lane);
    write_sh(s0, lid);
    if (store && live) {
        keep4(d, A_CIN + 4u * g, sl);
    }
    workgroupBarrier();
    // Row 0, the log-density, is overwritten by the next layer.
    let log_density = tile[lane];
    if (store && live) {
        for (var r = DOUT + g; r < DOUT + 16u; r += 4u) {
            acts4[at4(A_CIN + r, sl)] = tile[r * LANES + lane];
        }
    }
    let h1 = relu16(mmF16((TC0 + 16u * g) / 4u, 16u, DOUT + 16u, lane));
    workgroupBarrier();
    put16(h1, 16u * g, lane);
    if (store && live) {
        keep16(h1, A_H1 + 16u * g, sl);
    }
    workgroupBarrier();
    let h2 = relu16(mmF16((TC1 + 16u * g) / 4u, 16u, WIDTH, lane));
    workgroupBarrier();
    put16(h2, 16u * g, lane);
    if (store && live) {
        keep16(h2, A_H2 + 16u * g, sl);
    }
    workgroupBarrier();
    // The colour output's 3 used rows (of the 16 stored): group 0 alone.
    if (g == 0u && live) {
        let rgb = mmF4(TC2 / 4u, 4u, WIDTH, lane);
        for (var c = 0u; c < 4u; c++) {
            if (sl + c < p.n) {
                out[sl + c] = vec4<f32>(rgb[0][c], rgb[1][c], rgb[2][c], log_density[c]);
            }
        }
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
    let g = lid / LANES;
    let lane = lid % LANES;
    let sl = s0 + 4u * lane;
    density_hidden(g, lane, sl, s0, false);
    if (g == 0u && sl < p.n) {
        let d = mmF4(TD1 / 4u, 4u, WIDTH, lane);
        for (var c = 0u; c < 4u; c++) {
            if (sl + c < p.n) {
                dens_out[sl + c] = d[0][c];
            }
        }
    }
}

// Backward of a tile through both MLPs down to d_enc, after forward_main with p.store on the
// same samples; every layer's output gradient goes to `dys` for the weight gradients. The
// backward products read W[o][i] for one output o and R consecutive inputs i: R / 4
// consecutive vec4 of the weights as stored.
@compute @workgroup_size(128)
fn backward_main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let s0 = tile_start(wid);
    if (s0 >= p.n) {
        return;
    }
    let g = lid / LANES;
    let lane = lid % LANES;
    let sl = s0 + 4u * lane;
    let live = sl < p.n;
    // d rgb into rows 0..3 (0 past n, so padding samples stay zero all the way down), the
    // log-density's gradient kept for the density outputs.
    var d_log_density = vec4<f32>(0.0);
    if (g == 0u) {
        var rows = array<vec4<f32>, 3>();
        for (var c = 0u; c < 4u; c++) {
            if (sl + c < p.n) {
                let v = d_out[sl + c];
                rows[0][c] = v.x;
                rows[1][c] = v.y;
                rows[2][c] = v.z;
                d_log_density[c] = v.w;
            }
        }
        tile[lane] = rows[0];
        tile[LANES + lane] = rows[1];
        tile[2u * LANES + lane] = rows[2];
        if (live) {
            dys4[at4(G_RGB, sl)] = rows[0];
            dys4[at4(G_RGB + 1u, sl)] = rows[1];
            dys4[at4(G_RGB + 2u, sl)] = rows[2];
        }
    }
    workgroupBarrier();
    // Colour output → hidden 2 (W 16 × 64, 3 used outputs).
    let h2 = mask16(mmB16((OFF_C2 + 16u * g) / 4u, 16u, 3u, lane), A_H2 + 16u * g, sl);
    workgroupBarrier();
    put16(h2, 16u * g, lane);
    if (live) {
        dy16(h2, G_H2 + 16u * g, sl);
    }
    workgroupBarrier();
    // Hidden 2 → hidden 1 (W 64 × 64).
    let h1 = mask16(mmB16((OFF_C1 + 16u * g) / 4u, 16u, WIDTH, lane), A_H1 + 16u * g, sl);
    workgroupBarrier();
    put16(h1, 16u * g, lane);
    if (live) {
        dy16(h1, G_H1 + 16u * g, sl);
    }
    workgroupBarrier();
    // Hidden 1 → the density-output half of the colour input (W 64 × 32; SH is fixed). The
    // log-density reaches density output 0 directly as well; the density outputs are
    // linear: no mask.
    var d = mmB4((OFF_C0 + 4u * g) / 4u, (DOUT + 16u) / 4u, WIDTH, lane);
    if (g == 0u) {
        d[0] += d_log_density;
    }
    workgroupBarrier();
    put4(d, 4u * g, lane);
    if (live) {
        dy4(d, G_DOUT + 4u * g, sl);
    }
    workgroupBarrier();
    // Density outputs → density hidden (W 16 × 64).
    let h = mask16(mmB16((OFF_D1 + 16u * g) / 4u, 16u, DOUT, lane), A_DH + 16u * g, sl);
    workgroupBarrier();
    put16(h, 16u * g, lane);
    if (live) {
        dy16(h, G_DH + 16u * g, sl);
    }
    workgroupBarrier();
    // Density hidden → the encoding (W 64 × DIN), straight to d_enc.
    if (live) {
        d_enc_rows(mmBD((OFF_D0 + RD * g) / 4u, DIN / 4u, WIDTH, lane), RD * g, sl);
    }
}

// One sample's d_enc of one row, 4 samples at a time (ld_enc need not be a multiple of 4).
fn d_enc4(row: u32, sl: u32, v: vec4<f32>) {
    if (row < N_ENC) {
        let b = row * p.ld_enc + sl;
        d_enc[b] = v.x;
        if (sl + 1u < p.n) { d_enc[b + 1u] = v.y; }
        if (sl + 2u < p.n) { d_enc[b + 2u] = v.z; }
        if (sl + 3u < p.n) { d_enc[b + 3u] = v.w; }
    }
}

// Weight-gradient staging: ST samples of the rows of dY and X, row-major with a stride of
// ST + 1 words so that the consecutive samples of a row written by consecutive invocations,
// and the same sample of distinct rows read by them, fall in distinct banks.
const ST: u32 = 32u;
const SP: u32 = 33u;
var<workgroup> shy: array<f32, 2112>;
var<workgroup> shx: array<f32, 2112>;

// Rows `row0 ..< row0 + rows` of a saved buffer (acts or dys, `from_dys`), samples
// b ..< b + ST, into `sh` rows 0..rows, 0 past `end`: one vec4 per invocation.
fn stage_saved(from_dys: bool, row0: u32, rows: u32, b: u32, end: u32, lid: u32, to_y: bool) {
    for (var e = lid; e < rows * (ST / 4u); e += WG) {
        let r = e / (ST / 4u);
        let q = e % (ST / 4u);
        let s = b + 4u * q;
        var v = vec4<f32>(0.0);
        if (s < end) {
            if (from_dys) {
                v = dys4[at4(row0 + r, s)];
            } else {
                v = acts4[at4(row0 + r, s)];
            }
            if (s + 1u >= end) { v.y = 0.0; }
            if (s + 2u >= end) { v.z = 0.0; }
            if (s + 3u >= end) { v.w = 0.0; }
        }
        let o = r * SP + 4u * q;
        if (to_y) {
            shy[o] = v.x;
            shy[o + 1u] = v.y;
            shy[o + 2u] = v.z;
            shy[o + 3u] = v.w;
        } else {
            shx[o] = v.x;
            shx[o + 1u] = v.y;
            shx[o + 2u] = v.z;
            shx[o + 3u] = v.w;
        }
    }
}

// The encoding's rows (DIN, 0 past N_ENC and past `end`) into shx.
fn stage_enc(b: u32, end: u32, lid: u32) {
    for (var e = lid; e < DIN * ST; e += WG) {
        let r = e / ST;
        let s = b + e % ST;
        var v = 0.0;
        if (r < N_ENC && s < end) {
            v = enc[r * p.ld_enc + s];
        }
        shx[r * SP + e % ST] = v;
    }
}

// Forward weights transposed into wt_out: W[r][k] (row-major rows × cols at OFF_*) to
// T* + k·rows + r.
@compute @workgroup_size(128)
fn transpose_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= NW) {
        return;
    }
    var off = OFF_D0;
    var rows = WIDTH;
    var cols = DIN;
    if (e >= OFF_C2 - OFF_D0) {
        off = OFF_C2; rows = DOUT; cols = WIDTH;
    } else if (e >= OFF_C1 - OFF_D0) {
        off = OFF_C1; rows = WIDTH; cols = WIDTH;
    } else if (e >= OFF_C0 - OFF_D0) {
        off = OFF_C0; rows = WIDTH; cols = DOUT + 16u;
    } else if (e >= OFF_D1 - OFF_D0) {
        off = OFF_D1; rows = DOUT; cols = WIDTH;
    }
    let i = e - (off - OFF_D0);
    let r = i / cols;
    let k = i % cols;
    let w = off + i;
    wt_out[off - OFF_D0 + k * rows + r] = weights4[w / 4u][w % 4u];
}

fn n_chunks() -> u32 {
    return (p.n + CH - 1u) / CH;
}

// Stage 0: partials[g·RG_CHUNKS·NW + e] = Σ of the group's chunks (in order); stage 1:
// grad[OFF_D0 + e] += Σ of the groups' sums (in order). The same sum on every run and every
// adapter (no atomics).
@compute @workgroup_size(128)
fn reduce_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= NW) {
        return;
    }
    var sum = 0.0;
    if (p.stage == 0u) {
        let first = gid.y * RG_CHUNKS;
        let last = min(first + RG_CHUNKS, n_chunks());
        for (var c = first; c < last; c++) {
            sum += partials[c * NW + e];
        }
        partials[first * NW + e] = sum;
    } else {
        for (var c = 0u; c < n_chunks(); c += RG_CHUNKS) {
            sum += partials[c * NW + e];
        }
        grad[OFF_D0 + e] += sum;
    }
}
