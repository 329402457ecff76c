// Training rays on the device, as ngp::train::trainer::train_rays draws and marches them:
// `gen_main` draws ray i of a batch (image, pixel, random background from Pcg32::new(seed, i),
// the same draws in the same order as the CPU, bit-identical through u64.wgsl), the camera
// ray through the pixel's centre, its target pixel on that background and where marching
// starts; `march_main` marches it through the occupancy bitfield (Marcher::march) and writes
// its samples compactly. Concatenated after u64.wgsl and pcg.wgsl.
//
// Compaction (instant-ngp's scheme): a ray marches twice in one invocation, first counting
// its samples, then, after reserving that many slots with one atomicAdd on a batch counter,
// writing them. A ray whose slots would end past the batch's sample budget takes none
// (n = 0): once one ray overflows every later reservation does too, so the rays that fit
// own exactly the samples [0, used) with no holes. Which rays those are depends on the
// order the invocations reach the counter (not deterministic where the budget binds); a
// ray's own samples do not.

const GRID_SIZE: f32 = 128.0;
const N_CELLS: u32 = 2097152u; // 128³
const MIN_CONE_STEPSIZE: f32 = 0.0016914559; // sqrt(3) / 1024, as the CPU's f32
// Iterations of one marching pass at most: a GPU invocation must end (a hung one loses
// the device). The CPU's loop always ends because every iteration moves t forward through
// a finite box; this bound is far above what a ray through a 128-wide box of cascades takes
// (samples ≤ 1024 plus one skip per cell crossed).
const MAX_ITERATIONS: u32 = 65536u;

struct RayParams {
    seed: vec2<u32>,
    n_rays: u32,
    n_images: u32,
    aabb_min: vec3<f32>,
    cone_angle: f32,
    aabb_max: vec3<f32>,
    // 1 / the box's side (a power of two: w = (p − aabb_min)·inv_extent is the CPU's division).
    inv_extent: f32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    sample_budget: u32,
    max_per_ray: u32,
    max_cascade: u32,
    // Stepping-space constants, computed on the host with the CPU's own f32 operations:
    // l = ln(1 + cone_angle), a and b the steps where steps stop being MIN and start being
    // MAX_CONE_STEPSIZE, at = exp(a·l), bt = exp(b·l).
    step_l: f32,
    step_a: f32,
    step_b: f32,
    step_at: f32,
    step_bt: f32,
    max_step: f32,
    _pad0: u32,
    _pad1: u32,
}

// A camera (ngp::camera::Camera) and where its frame's image lies in `images`.
struct Cam {
    // Row-major 3×4: columns right, down, forward, position.
    c2w: array<vec4<f32>, 3>,
    // fx, fy, cx, cy.
    intr: vec4<f32>,
    // OpenCV k1, k2, p1, p2.
    dist: vec4<f32>,
    width: u32,
    height: u32,
    // First word of the frame's pixels in `images`.
    offset: u32,
    // Bit 0: pixels are f16 linear premultiplied RGBA (2 words), else RGBA8 sRGB straight
    // alpha (1 word, r in the low byte). Bit 1: the camera has lens distortion.
    flags: u32,
}

// One drawn ray: what marching needs, and what the tests compare with the CPU.
struct GenRay {
    o: vec3<f32>,
    // Where marching starts (advance_n_steps(tmin, cone_angle, u)).
    t: f32,
    d: vec3<f32>,
    // 1 when the ray meets the box.
    hit: u32,
    bg: vec3<f32>,
    // y·width + x.
    pixel: u32,
    target_rgb: vec3<f32>,
    image: u32,
}

// The loss kernel's ray (gpu::loss::GpuRay): samples start..start + n.
struct OutRay {
    start: u32,
    n: u32,
    bg: array<f32, 3>,
    target_rgb: array<f32, 3>,
}

@group(0) @binding(0) var<storage, read> cams: array<Cam>;
@group(0) @binding(1) var<storage, read> images: array<u32>;
// srgb_to_linear(i / 255) for every 8-bit code: the CPU's SRGB8_TO_LINEAR table.
@group(0) @binding(2) var<storage, read> lut: array<f32, 256>;
@group(0) @binding(3) var<storage, read_write> gen: array<GenRay>;
@group(0) @binding(4) var<storage, read> gen_in: array<GenRay>;
@group(0) @binding(5) var<storage, read> bitfield: array<u32>;
@group(0) @binding(6) var<storage, read_write> rays_out: array<OutRay>;
// Per sample: warped position (x y z), dt, distance along the ray.
@group(0) @binding(7) var<storage, read_write> pos: array<f32>;
@group(0) @binding(8) var<storage, read_write> dts: array<f32>;
@group(0) @binding(9) var<storage, read_write> dists: array<f32>;
// [0]: slots asked for (past the budget too), [1]: samples written, [2]: rays with samples,
// [3]: rays with samples that did not fit the budget (they train nothing this step).
@group(0) @binding(10) var<storage, read_write> counters: array<atomic<u32>, 4>;
@group(0) @binding(11) var<uniform> p: RayParams;

// floor(a·b / c) for a 64-bit a·b (the CPU's usize i·n_images / n_rays), by long division.
fn mul_div(a: u32, b: u32, c: u32) -> u32 {
    let prod = mul_wide(a, b);
    if (prod.y == 0u) {
        return prod.x / c;
    }
    var rem = 0u;
    var q = 0u;
    for (var k = 63i; k >= 0; k--) {
        let bit = select((prod.x >> u32(k)) & 1u, (prod.y >> u32(k - 32)) & 1u, k >= 32);
        // rem < c ≤ 2^32 − 1, so rem·2 + bit fits in 33 bits: track the carry.
        let carry = rem >> 31u;
        rem = (rem << 1u) | bit;
        if (carry == 1u || rem >= c) {
            rem -= c;
            if (k < 32) {
                q |= 1u << u32(k);
            }
        }
    }
    return q;
}

// ---- colour (ngp::data::color) ----

fn srgb_to_linear(s: f32) -> f32 {
    if (s <= 0.04045) {
        return s / 12.92;
    }
    return pow((s + 0.055) / 1.055, 2.4);
}

fn linear_to_srgb(l: f32) -> f32 {
    if (l < 0.0031308) {
        return 12.92 * l;
    }
    return 1.055 * pow(l, 0.41666) - 0.055;
}

// Image::linear_premul: linear RGB premultiplied by alpha, and alpha.
fn linear_premul(c: Cam, x: u32, y: u32) -> vec4<f32> {
    let i = y * c.width + x;
    if ((c.flags & 1u) != 0u) {
        let rg = unpack2x16float(images[c.offset + 2u * i]);
        let ba = unpack2x16float(images[c.offset + 2u * i + 1u]);
        return vec4<f32>(rg, ba);
    }
    let w = images[c.offset + i];
    let a = f32(w >> 24u) * (1.0 / 255.0);
    return vec4<f32>(lut[w & 0xffu] * a, lut[(w >> 8u) & 0xffu] * a, lut[(w >> 16u) & 0xffu] * a, a);
}

// Image::target_on: srgb(lin_rgb·a + (1 − a)·lin(bg)).
fn target_on(c: Cam, x: u32, y: u32, bg: vec3<f32>) -> vec3<f32> {
    let q = linear_premul(c, x, y);
    let t = 1.0 - q.w;
    return vec3<f32>(
        linear_to_srgb(q.x + t * srgb_to_linear(bg.x)),
        linear_to_srgb(q.y + t * srgb_to_linear(bg.y)),
        linear_to_srgb(q.z + t * srgb_to_linear(bg.z)),
    );
}

// ---- camera (ngp::camera) ----

fn lens_delta(k: vec4<f32>, u: f32, v: f32) -> vec2<f32> {
    let u2 = u * u;
    let uv = u * v;
    let v2 = v * v;
    let r2 = u2 + v2;
    let radial = k.x * r2 + k.y * r2 * r2;
    return vec2<f32>(
        u * radial + 2.0 * k.z * uv + k.w * (r2 + 2.0 * u2),
        v * radial + 2.0 * k.w * uv + k.z * (r2 + 2.0 * v2),
    );
}

// Distortion::undistort: Newton with a central-difference Jacobian, 100 iterations at most.
fn undistort(k: vec4<f32>, uv0: vec2<f32>) -> vec2<f32> {
    var x = uv0;
    let eps = 1.1920929e-7; // f32::EPSILON
    for (var it = 0u; it < 100u; it++) {
        let s0 = max(eps, abs(1e-6 * x.x));
        let s1 = max(eps, abs(1e-6 * x.y));
        let d = lens_delta(k, x.x, x.y);
        let d0b = lens_delta(k, x.x - s0, x.y);
        let d0f = lens_delta(k, x.x + s0, x.y);
        let d1b = lens_delta(k, x.x, x.y - s1);
        let d1f = lens_delta(k, x.x, x.y + s1);
        let j00 = 1.0 + (d0f.x - d0b.x) / (2.0 * s0);
        let j01 = (d1f.x - d1b.x) / (2.0 * s1);
        let j10 = (d0f.y - d0b.y) / (2.0 * s0);
        let j11 = 1.0 + (d1f.y - d1b.y) / (2.0 * s1);
        let r = vec2<f32>(x.x + d.x - uv0.x, x.y + d.y - uv0.y);
        let det = j00 * j11 - j01 * j10;
        // det == 0 or not finite (the CPU's test; inf − inf or NaN fail `abs(det) < inf`).
        if (det == 0.0 || !(abs(det) <= 3.4028235e38)) {
            break;
        }
        let step = vec2<f32>((j11 * r.x - j01 * r.y) / det, (-j10 * r.x + j00 * r.y) / det);
        x -= step;
        if (step.x * step.x + step.y * step.y < 1e-10) {
            break;
        }
    }
    return x;
}

struct CamRay {
    o: vec3<f32>,
    // Unit length (unless zero).
    d: vec3<f32>,
}

// Camera::ray through continuous pixel coordinates (px, py): pinhole, OpenCV distortion
// inverted as the CPU inverts it, the direction rotated and normalised.
fn camera_ray(c: Cam, px: f32, py: f32) -> CamRay {
    var uv = vec2<f32>((px - c.intr.z) / c.intr.x, (py - c.intr.w) / c.intr.y);
    if ((c.flags & 2u) != 0u) {
        uv = undistort(c.dist, uv);
    }
    let m = c.c2w;
    var d = vec3<f32>(
        m[0].x * uv.x + m[0].y * uv.y + m[0].z,
        m[1].x * uv.x + m[1].y * uv.y + m[1].z,
        m[2].x * uv.x + m[2].y * uv.y + m[2].z,
    );
    let len = sqrt(dot(d, d));
    if (len > 0.0) {
        d = d / len;
    }
    return CamRay(vec3<f32>(m[0].w, m[1].w, m[2].w), d);
}

// ---- marching (ngp::render::march, ngp::occupancy) ----

fn to_stepping_space(t: f32) -> f32 {
    if (p.cone_angle <= 1e-5) {
        return t / MIN_CONE_STEPSIZE;
    }
    if (t <= p.step_at) {
        return (t - p.step_at) / MIN_CONE_STEPSIZE + p.step_a;
    } else if (t <= p.step_bt) {
        return log(t) / p.step_l;
    }
    return (t - p.step_bt) / p.max_step + p.step_b;
}

fn from_stepping_space(n: f32) -> f32 {
    if (p.cone_angle <= 1e-5) {
        return n * MIN_CONE_STEPSIZE;
    }
    if (n <= p.step_a) {
        return (n - p.step_a) * MIN_CONE_STEPSIZE + p.step_at;
    } else if (n <= p.step_b) {
        return exp(n * p.step_l);
    }
    return (n - p.step_b) * p.max_step + p.step_bt;
}

fn advance_n_steps(t: f32, n: f32) -> f32 {
    return from_stepping_space(to_stepping_space(t) + n);
}

fn calc_dt(t: f32) -> f32 {
    return max(advance_n_steps(t, 1.0) - t, 0.0);
}

// frexp's exponent of a positive normal float.
fn exponent(v: f32) -> i32 {
    return i32((bitcast<u32>(v) >> 23u) & 0xffu) - 126;
}

fn mip_from_pos(q: vec3<f32>) -> u32 {
    let a = abs(q - 0.5);
    let m = max(a.x, max(a.y, a.z));
    var e = 0i;
    if (m != 0.0) {
        e = exponent(m);
    }
    return u32(clamp(e + 1, 0i, i32(p.max_cascade)));
}

fn mip_from_dt(dt: f32, q: vec3<f32>) -> u32 {
    let mip = mip_from_pos(q);
    let d = dt * 2.0 * GRID_SIZE;
    if (d < 1.0) {
        return mip;
    }
    return u32(min(max(i32(mip), exponent(d)), i32(p.max_cascade)));
}

fn expand_bits(v: u32) -> u32 {
    var x = v & 0x3ffu;
    x = (x | (x << 16u)) & 0x030000ffu;
    x = (x | (x << 8u)) & 0x0300f00fu;
    x = (x | (x << 4u)) & 0x030c30c3u;
    x = (x | (x << 2u)) & 0x09249249u;
    return x;
}

// OccupancyGrid::is_occupied: the cell of q in cascade `mip`, looked up in the bitfield.
fn is_occupied(q: vec3<f32>, mip: u32) -> bool {
    // 2^−mip exactly: the scaling below is exact, as the CPU's.
    let s = ldexp(1.0, -i32(mip));
    let f = (q - 0.5) * s + 0.5;
    if (any(f < vec3<f32>(0.0))) {
        return false;
    }
    let g = f * GRID_SIZE;
    if (any(g >= vec3<f32>(GRID_SIZE))) {
        return false;
    }
    let i = vec3<u32>(g);
    let cell = expand_bits(i.x) | (expand_bits(i.y) << 1u) | (expand_bits(i.z) << 2u);
    let b = cell + mip * N_CELLS;
    return ((bitfield[b >> 5u] >> (b & 31u)) & 1u) != 0u;
}

fn distance_to_next_voxel(q: vec3<f32>, d: vec3<f32>, idir: vec3<f32>, res: f32) -> f32 {
    var tmin = bitcast<f32>(0x7f800000u); // +inf
    for (var k = 0u; k < 3u; k++) {
        // A zero direction component never bounds the step (the CPU's ±inf/NaN case).
        if (d[k] == 0.0) {
            continue;
        }
        let c = res * (q[k] - 0.5);
        let s = select(-1.0, 1.0, d[k] > 0.0);
        let tk = (floor(c + 0.5 + 0.5 * s) - c) * idir[k];
        tmin = min(tmin, tk);
    }
    return max(tmin / res, 0.0);
}

fn advance_to_next_voxel(t: f32, q: vec3<f32>, d: vec3<f32>, idir: vec3<f32>, mip: u32) -> f32 {
    let res = ldexp(GRID_SIZE, -i32(mip));
    let target_t = t + distance_to_next_voxel(q, d, idir, res);
    let ts = to_stepping_space(t);
    let tt = to_stepping_space(target_t);
    return from_stepping_space(ts + ceil(max(tt - ts, 0.5)));
}

fn inside_box(q: vec3<f32>) -> bool {
    return all(q >= p.aabb_min) && all(q <= p.aabb_max);
}

// Marcher::intersect: the entry distance (≥ 0) of the slab test, or −1 for a miss.
fn intersect(o: vec3<f32>, d: vec3<f32>) -> f32 {
    var t0 = bitcast<f32>(0xff800000u); // −inf
    var t1 = bitcast<f32>(0x7f800000u);
    for (var k = 0u; k < 3u; k++) {
        if (d[k] == 0.0) {
            // Parallel to the slab: inside it or not (the CPU reaches the same answer
            // through infinities).
            if (o[k] < p.aabb_min[k] || o[k] > p.aabb_max[k]) {
                return -1.0;
            }
            continue;
        }
        let inv = 1.0 / d[k];
        var a = (p.aabb_min[k] - o[k]) * inv;
        var b = (p.aabb_max[k] - o[k]) * inv;
        if (a > b) {
            let tmp = a;
            a = b;
            b = tmp;
        }
        t0 = max(t0, a);
        t1 = min(t1, b);
    }
    if (t0 > t1 || t1 < 0.0) {
        return -1.0;
    }
    return max(t0, 0.0);
}

@compute @workgroup_size(64)
fn gen_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * p.row_width;
    if (i >= p.n_rays) {
        return;
    }
    var r = pcg_new(p.seed, i, 0u);
    let img = mul_div(i, p.n_images, p.n_rays);
    let c = cams[img];
    let x = pcg_below(&r, c.width);
    let y = pcg_below(&r, c.height);
    let bg = vec3<f32>(pcg_f32(&r), pcg_f32(&r), pcg_f32(&r));
    // The ray through the pixel's centre.
    let ray = camera_ray(c, f32(x) + 0.5, f32(y) + 0.5);
    let o = ray.o;
    let d = ray.d;
    var g: GenRay;
    g.o = o;
    g.d = d;
    g.bg = bg;
    g.pixel = y * c.width + x;
    g.image = img;
    g.target_rgb = target_on(c, x, y, bg);
    let tmin = intersect(o, d);
    g.hit = select(0u, 1u, tmin >= 0.0);
    g.t = 0.0;
    if (tmin >= 0.0) {
        // The CPU draws this only for rays that meet the box: the same draw either way.
        g.t = advance_n_steps(tmin, pcg_f32(&r));
    }
    gen[i] = g;
}

// Where a march stands between two samples: the distance along the ray, and the
// iterations the pass has spent (it stops at MAX_ITERATIONS).
struct MarchCursor {
    t: f32,
    it: u32,
}

// A sample a march takes: its point, step and distance along the ray.
struct MarchSample {
    q: vec3<f32>,
    dt: f32,
    t: f32,
}

// What `march_step` found.
const MARCH_SAMPLE: u32 = 0u;
// The ray is out of the box at the cursor.
const MARCH_LEFT: u32 = 1u;
// The caller takes no more samples (`room` false); the ray is still in the box.
const MARCH_FULL: u32 = 2u;
// The pass has spent its iterations.
const MARCH_BOUND: u32 = 3u;

// Marcher::march's loop, the one both training (`march`) and rendering (`march_wave`, in
// renderer.wgsl) run: from the cursor, skips the empty cells to the next occupied sample,
// returns MARCH_SAMPLE with it in `*s` and the cursor past it. Each iteration checks, in
// this order, the iteration bound, the box, and whether the caller has room for a sample
// (`room`); a march that stops leaves the cursor where it stood.
fn march_step(
    o: vec3<f32>,
    d: vec3<f32>,
    idir: vec3<f32>,
    c: ptr<function, MarchCursor>,
    room: bool,
    s: ptr<function, MarchSample>,
) -> u32 {
    while ((*c).it < MAX_ITERATIONS) {
        let t = (*c).t;
        let q = o + t * d;
        if (!inside_box(q)) {
            return MARCH_LEFT;
        }
        if (!room) {
            return MARCH_FULL;
        }
        (*c).it += 1u;
        let dt = calc_dt(t);
        let mip = mip_from_dt(dt, q);
        var next: f32;
        let occupied = is_occupied(q, mip);
        if (occupied) {
            *s = MarchSample(q, dt, t);
            next = t + dt;
        } else {
            next = advance_to_next_voxel(t, q, d, idir, mip);
        }
        // Far from the camera a step can fall below the float spacing at t: the next float
        // (t ≥ 0 here, so one more in the bit pattern).
        (*c).t = select(bitcast<f32>(bitcast<u32>(t) + 1u), next, next > t);
        if (occupied) {
            return MARCH_SAMPLE;
        }
    }
    return MARCH_BOUND;
}

// One pass of Marcher::march from t: counts the samples (write = false), or writes them
// from slot `base` on. Returns the number of samples.
fn march(o: vec3<f32>, d: vec3<f32>, t0: f32, write: bool, base: u32) -> u32 {
    let idir = 1.0 / d;
    var c = MarchCursor(t0, 0u);
    var s: MarchSample;
    var n = 0u;
    while (march_step(o, d, idir, &c, n < p.max_per_ray, &s) == MARCH_SAMPLE) {
        if (write) {
            let k = base + n;
            let w = (s.q - p.aabb_min) * p.inv_extent;
            pos[3u * k] = w.x;
            pos[3u * k + 1u] = w.y;
            pos[3u * k + 2u] = w.z;
            dts[k] = s.dt;
            dists[k] = s.t;
        }
        n += 1u;
    }
    return n;
}

@compute @workgroup_size(64)
fn march_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * p.row_width;
    if (i >= p.n_rays) {
        return;
    }
    let g = gen_in[i];
    var out: OutRay;
    out.start = 0u;
    out.n = 0u;
    out.bg = array<f32, 3>(g.bg.x, g.bg.y, g.bg.z);
    // A ray without samples shows its background: with the target equal to it, the loss
    // kernel gives it loss 0 and no gradient (the CPU drops such rays).
    out.target_rgb = out.bg;
    if (g.hit != 0u) {
        let n = march(g.o, g.d, g.t, false, 0u);
        if (n > 0u) {
            let base = atomicAdd(&counters[0], n);
            if (base + n <= p.sample_budget && base + n >= base) {
                march(g.o, g.d, g.t, true, base);
                atomicAdd(&counters[1], n);
                atomicAdd(&counters[2], 1u);
                out.start = base;
                out.n = n;
                out.target_rgb = array<f32, 3>(g.target_rgb.x, g.target_rgb.y, g.target_rgb.z);
            } else {
                atomicAdd(&counters[3], 1u);
            }
        }
    }
    rays_out[i] = out;
}
