// Rendering whole images on the device, as ngp::render::image::render_image renders them on
// the CPU: a ray per pixel through its centre, marching from half a step inside the box in
// waves of at most `samples_per_wave` samples per live ray, every wave's samples through the
// network, composited (composite.wgsl), a ray retired once it left the box or its
// transmittance fell below the threshold. Concatenated after u64.wgsl, pcg.wgsl and
// rays.wgsl, whose camera, box and marching functions it calls: its uniform `p` (the box and
// stepping space), `cams` (the one camera, at 0) and `bitfield` are bound as there.
//
// One tile of pixels at a time. The live rays are a list of tile-local ray indices; a wave
// marches each listed ray, reserves its samples with one atomicAdd on the wave's counter
// (marching twice: count, then write, as rays.wgsl does), and after compositing the retire
// pass appends the rays still alive to the other list, which `render_next_main` makes the
// current one. Every length stays on the device (the passes over rays are dispatched over
// the whole tile and read the list's length; the network's, from a device count), so the
// host records many waves a submission and reads the counters once after them. The order
// of the lists and of the samples depends on the order the device runs the invocations;
// what each ray computes does not (the network evaluates every sample on its own).

struct RenderParams {
    // Rays (pixels) of this tile and the tile's first pixel; the image's width.
    n_tile: u32,
    first_pixel: u32,
    width: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    samples_per_wave: u32,
    min_transmittance: f32,
    _pad0: u32,
    _pad1: u32,
}

struct RenderRay {
    o: vec3<f32>,
    // Where the next wave resumes marching.
    t: f32,
    d: vec3<f32>,
    // 1 once marching left the box (the wave's samples are still composited).
    done: u32,
}

@group(0) @binding(12) var<storage, read_write> rrays: array<RenderRay>;
@group(0) @binding(13) var<storage, read_write> live: array<u32>;
@group(0) @binding(14) var<storage, read_write> live_next: array<u32>;
// [0]: samples of the wave marched last, [1]: rays in `live`, [2]: samples marched since the
// host last cleared it, [3]: rays the retire pass appended to `live_next`.
@group(0) @binding(15) var<storage, read_write> rcount: array<atomic<u32>, 4>;
// Per tile ray: this wave's samples (start, count), for composite.wgsl.
@group(0) @binding(16) var<storage, read_write> wave: array<vec2<u32>>;
// Per sample: warped position and view direction (3 floats each), dt, distance.
@group(0) @binding(17) var<storage, read_write> s_pos: array<f32>;
@group(0) @binding(18) var<storage, read_write> s_dir: array<f32>;
@group(0) @binding(19) var<storage, read_write> s_dt: array<f32>;
@group(0) @binding(20) var<storage, read_write> s_dist: array<f32>;
// Per tile ray: the compositing state's transmittance (gpu::render::RayState::trans).
@group(0) @binding(21) var<storage, read_write> trans: array<f32>;
@group(0) @binding(22) var<uniform> rp: RenderParams;

// The tile's rays: through pixel first_pixel + k's centre; a ray that meets the box starts
// half a step inside it and joins the live list.
@compute @workgroup_size(64)
fn render_gen_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x + gid.y * rp.row_width;
    if (k >= rp.n_tile) {
        return;
    }
    trans[k] = 1.0;
    let pixel = rp.first_pixel + k;
    let ray = camera_ray(cams[0], f32(pixel % rp.width) + 0.5, f32(pixel / rp.width) + 0.5);
    var r: RenderRay;
    r.o = ray.o;
    r.d = ray.d;
    r.t = 0.0;
    r.done = 1u;
    let tmin = intersect(ray.o, ray.d);
    if (tmin >= 0.0) {
        r.t = advance_n_steps(tmin, 0.5);
        r.done = 0u;
        live[atomicAdd(&rcount[1], 1u)] = k;
    }
    rrays[k] = r;
}

struct WaveEnd {
    n: u32,
    // Where the next wave resumes.
    t: f32,
    // 1: the ray left the box.
    left: u32,
}

// One wave of Marcher::march from t0 (rays.wgsl's `march_step`, the loop training runs
// too): at most max_n samples; counts them, or (write) writes them from sample slot `base`
// on. A wave that reaches the iteration bound (an invocation must end) stops where it is;
// the next wave resumes from there, so the bound changes no result.
fn march_wave(o: vec3<f32>, d: vec3<f32>, t0: f32, max_n: u32, write: bool, base: u32) -> WaveEnd {
    let idir = 1.0 / d;
    var c = MarchCursor(t0, 0u);
    var s: MarchSample;
    var n = 0u;
    var found = march_step(o, d, idir, &c, n < max_n, &s);
    while (found == MARCH_SAMPLE) {
        if (write) {
            let k = base + n;
            let w = (s.q - p.aabb_min) * p.inv_extent;
            s_pos[3u * k] = w.x;
            s_pos[3u * k + 1u] = w.y;
            s_pos[3u * k + 2u] = w.z;
            s_dir[3u * k] = d.x;
            s_dir[3u * k + 1u] = d.y;
            s_dir[3u * k + 2u] = d.z;
            s_dt[k] = s.dt;
            s_dist[k] = s.t;
        }
        n += 1u;
        found = march_step(o, d, idir, &c, n < max_n, &s);
    }
    return WaveEnd(n, c.t, select(0u, 1u, found == MARCH_LEFT));
}

// One wave of every live ray (the list's length is the device's counter).
@compute @workgroup_size(64)
fn render_march_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * rp.row_width;
    if (i >= atomicLoad(&rcount[1])) {
        return;
    }
    let k = live[i];
    let r = rrays[k];
    let end = march_wave(r.o, r.d, r.t, rp.samples_per_wave, false, 0u);
    var start = 0u;
    if (end.n > 0u) {
        start = atomicAdd(&rcount[0], end.n);
        atomicAdd(&rcount[2], end.n);
        // At most the samples reserved, whatever the second pass finds.
        march_wave(r.o, r.d, r.t, end.n, true, start);
    }
    wave[k] = vec2<u32>(start, end.n);
    rrays[k].t = end.t;
    rrays[k].done = end.left;
}

// After compositing: the rays still in the box and not yet opaque go on to the next list
// (`!(T < min)`: a NaN transmittance goes on, as on the CPU); the others get an empty wave
// record, since compositing passes over every ray of the tile (marching writes the live
// rays' records anew every wave).
@compute @workgroup_size(64)
fn render_retire_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * rp.row_width;
    if (i >= atomicLoad(&rcount[1])) {
        return;
    }
    let k = live[i];
    if (rrays[k].done == 0u && !(trans[k] < rp.min_transmittance)) {
        live_next[atomicAdd(&rcount[3], 1u)] = k;
    } else {
        wave[k] = vec2<u32>(0u, 0u);
    }
}

// Between the retire pass and the next wave's marching (one invocation): the list the
// retire pass wrote becomes the current one (the host swaps the two buffers' roles), and
// the wave's sample counter starts again.
@compute @workgroup_size(1)
fn render_next_main() {
    atomicStore(&rcount[1], atomicLoad(&rcount[3]));
    atomicStore(&rcount[3], 0u);
    atomicStore(&rcount[0], 0u);
}
