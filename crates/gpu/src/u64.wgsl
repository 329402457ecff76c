// 64-bit unsigned integers as vec2<u32> (x = low word, y = high word): WGSL has no u64.
// Wrapping arithmetic, as Rust's wrapping_* on u64. Included before every kernel that needs
// it (index.wgsl, occupancy.wgsl).

// a·b as a full 64-bit product, from 16-bit halves (no carries lost: each partial sum < 2^18).
fn mul_wide(a: u32, b: u32) -> vec2<u32> {
    let a0 = a & 0xffffu;
    let a1 = a >> 16u;
    let b0 = b & 0xffffu;
    let b1 = b >> 16u;
    let p00 = a0 * b0;
    let p01 = a0 * b1;
    let p10 = a1 * b0;
    let p11 = a1 * b1;
    let mid = (p00 >> 16u) + (p01 & 0xffffu) + (p10 & 0xffffu);
    let lo = (p00 & 0xffffu) | (mid << 16u);
    let hi = p11 + (p01 >> 16u) + (p10 >> 16u) + (mid >> 16u);
    return vec2<u32>(lo, hi);
}

// u32 × u64, wrapping at 2^64 (Rust's `(x as u64).wrapping_mul(k)`).
fn mul_u32_u64(x: u32, k: vec2<u32>) -> vec2<u32> {
    let p = mul_wide(x, k.x);
    return vec2<u32>(p.x, p.y + x * k.y);
}

fn add64(a: vec2<u32>, b: vec2<u32>) -> vec2<u32> {
    let lo = a.x + b.x;
    return vec2<u32>(lo, a.y + b.y + select(0u, 1u, lo < a.x));
}

// Rotate left by 0 < n < 32.
fn rotl64(v: vec2<u32>, n: u32) -> vec2<u32> {
    return vec2<u32>((v.x << n) | (v.y >> (32u - n)), (v.y << n) | (v.x >> (32u - n)));
}

// a·b wrapping at 2^64.
fn mul64(a: vec2<u32>, b: vec2<u32>) -> vec2<u32> {
    let p = mul_u32_u64(a.x, b);
    return vec2<u32>(p.x, p.y + a.y * b.x);
}
