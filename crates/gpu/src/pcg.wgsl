// PCG32 (rng::Pcg32) in 64-bit words, bit for bit the CPU's generator. Included after
// u64.wgsl by every kernel that draws as the CPU draws (occupancy.wgsl, rays.wgsl).

const PCG_MULT: vec2<u32> = vec2<u32>(0x4c957f2du, 0x5851f42du); // 6364136223846793005

struct Pcg {
    state: vec2<u32>,
    inc: vec2<u32>,
}

fn pcg_next(r: ptr<function, Pcg>) -> u32 {
    let old = (*r).state;
    (*r).state = add64(mul64(old, PCG_MULT), (*r).inc);
    // ((old >> 18) ^ old) >> 27, low 32 bits.
    let s18 = vec2<u32>((old.x >> 18u) | (old.y << 14u), old.y >> 18u);
    let x = vec2<u32>(s18.x ^ old.x, s18.y ^ old.y);
    let xorshifted = (x.x >> 27u) | (x.y << 5u);
    let rot = old.y >> 27u;
    return (xorshifted >> rot) | (xorshifted << ((32u - rot) & 31u));
}

// Pcg32::new(seed, stream) with stream = hi·2^32 + lo.
fn pcg_new(seed: vec2<u32>, stream_lo: u32, stream_hi: u32) -> Pcg {
    var r: Pcg;
    r.state = vec2<u32>(0u, 0u);
    r.inc = vec2<u32>((stream_lo << 1u) | 1u, (stream_hi << 1u) | (stream_lo >> 31u));
    pcg_next(&r);
    r.state = add64(r.state, seed);
    pcg_next(&r);
    return r;
}

// Pcg32::next_f32: uniform in [0, 1).
fn pcg_f32(r: ptr<function, Pcg>) -> f32 {
    return f32(pcg_next(r) >> 8u) * (1.0 / 16777216.0);
}

// Pcg32::below: the high word of next_u32 · n.
fn pcg_below(r: ptr<function, Pcg>, n: u32) -> u32 {
    return mul_wide(pcg_next(r), n).y;
}
