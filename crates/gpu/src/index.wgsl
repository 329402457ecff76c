// Per-level hash-grid index functions, bit-identical to the CPU's kernels in
// crates/ngp/src/encoding/index.rs and sip.rs (evaluating the LevelIndex data that crates/stego makes
// from keys: permutation tables, confinement maps).
//
// Included by every kernel that indexes the grid. The including module declares
//   var<storage, read> index_tables: array<u32>;
// (the permutation / confinement tables of all levels, one after another), at whatever
// binding it likes: WGSL resolves module-scope names in any order.
//
// WGSL has no 64-bit integers, so the u64 arithmetic of `primes` and SipHash runs on
// vec2<u32> (x = low word, y = high word), with the helpers of u64.wgsl (included first).

const INDEX_REFERENCE: u32 = 0u;
const INDEX_PRIMES: u32 = 1u;
const INDEX_SIP: u32 = 2u;

// Bit k set: some level has kind k. A pipeline made with the uploaded index's kinds
// (GpuIndex::kinds, index_constants) compiles only their code: a level's branch is uniform
// on a GPU, but the unused kinds' code still costs registers there, and llvmpipe runs
// 2–5× slower with SipHash compiled in beside the reference. A level whose kind is not in
// the set would be indexed as the reference: pipelines must take the index's own set.
override INDEX_KINDS: u32 = 7u;

fn has_kind(kind: u32) -> bool {
    return (INDEX_KINDS & (1u << kind)) != 0u;
}

// tcnn's CoherentPrime constants (REFERENCE_PRIMES).
const REF_PI2: u32 = 2654435761u;
const REF_PI3: u32 = 805459861u;

// Mirrors `GpuLevel` (crates/gpu/src/index.rs), 72 bytes; kind 0 reference, 1 primes, 2 SipHash.
struct LevelIndex {
    kind: u32,
    resolution: u32,
    size: u32,
    dense: u32,
    k0: vec2<u32>,
    k1: vec2<u32>,
    k2: vec2<u32>,
    sip_k0: vec2<u32>,
    sip_k1: vec2<u32>,
    // Into index_tables; table_len = 0: no table.
    table_offset: u32,
    table_len: u32,
    // floor((2^64 − 1) / size), for mod64.
    mu: vec2<u32>,
}

// h mod s, exact for every u64 h and u32 s > 0 (the CPU's `(h % s as u64) as u32`), by
// Barrett reduction with mu = floor((2^64 − 1) / s) from the host: q = floor(h·mu / 2^64)
// is floor(h / s) or one less, so h − q·s < 2s needs one conditional subtraction. No
// division: GPUs emulate integer division, and llvmpipe scalarises it per lane.
fn mod64(h: vec2<u32>, s: u32, mu: vec2<u32>) -> u32 {
    // High 64 bits of the 128-bit product h·mu.
    let p00 = mul_wide(h.x, mu.x);
    let p01 = mul_wide(h.x, mu.y);
    let p10 = mul_wide(h.y, mu.x);
    let p11 = mul_wide(h.y, mu.y);
    let mid = add64(add64(vec2<u32>(p00.y, 0u), vec2<u32>(p01.x, 0u)), vec2<u32>(p10.x, 0u));
    let q = add64(add64(add64(p11, vec2<u32>(p01.y, 0u)), vec2<u32>(p10.y, 0u)), vec2<u32>(mid.y, 0u));
    // r = h − q·s < 2s, in 64 bits (2s passes 2^32 when s > 2^31).
    let qs = mul_u32_u64(s, q);
    let lo = h.x - qs.x;
    let hi = h.y - qs.y - select(0u, 1u, h.x < qs.x);
    if (hi != 0u || lo >= s) {
        return lo - s;
    }
    return lo;
}

// The CPU reduces a power-of-two size with a mask, anything else with `%`: the same value.
fn reduce64(h: vec2<u32>, lv: LevelIndex) -> u32 {
    let s = lv.size;
    if ((s & (s - 1u)) == 0u) {
        return h.x & (s - 1u);
    }
    return mod64(h, s, lv.mu);
}

fn reduce32(h: u32, s: u32) -> u32 {
    if ((s & (s - 1u)) == 0u) {
        return h & (s - 1u);
    }
    return h % s;
}

// ---- reference (tiny-cuda-nn), wrapping u32 ----

fn reference_index(lv: LevelIndex, p: vec3<u32>) -> u32 {
    if (lv.dense != 0u) {
        let r = lv.resolution;
        return (p.x + p.y * r + p.z * (r * r)) % lv.size;
    }
    return reduce32(p.x ^ (p.y * REF_PI2) ^ (p.z * REF_PI3), lv.size);
}

// ---- SipHash-2-4 of the 12-byte message x‖y‖z (crates/stego/src/prf.rs) ----

struct Sip {
    v0: vec2<u32>,
    v1: vec2<u32>,
    v2: vec2<u32>,
    v3: vec2<u32>,
}

fn sip_round(s: ptr<function, Sip>) {
    (*s).v0 = add64((*s).v0, (*s).v1);
    (*s).v1 = rotl64((*s).v1, 13u) ^ (*s).v0;
    (*s).v0 = (*s).v0.yx;
    (*s).v2 = add64((*s).v2, (*s).v3);
    (*s).v3 = rotl64((*s).v3, 16u) ^ (*s).v2;
    (*s).v0 = add64((*s).v0, (*s).v3);
    (*s).v3 = rotl64((*s).v3, 21u) ^ (*s).v0;
    (*s).v2 = add64((*s).v2, (*s).v1);
    (*s).v1 = rotl64((*s).v1, 17u) ^ (*s).v2;
    (*s).v2 = (*s).v2.yx;
}

fn sip_absorb(s: ptr<function, Sip>, m: vec2<u32>) {
    (*s).v3 ^= m;
    sip_round(s);
    sip_round(s);
    (*s).v0 ^= m;
}

fn siphash24_xyz(k0: vec2<u32>, k1: vec2<u32>, p: vec3<u32>) -> vec2<u32> {
    // "somepseudorandomlygeneratedbytes"
    var s = Sip(
        k0 ^ vec2<u32>(0x70736575u, 0x736f6d65u),
        k1 ^ vec2<u32>(0x6e646f6du, 0x646f7261u),
        k0 ^ vec2<u32>(0x6e657261u, 0x6c796765u),
        k1 ^ vec2<u32>(0x79746573u, 0x74656462u),
    );
    // Blocks: x | y << 32, then z with the length 12 in the top byte.
    sip_absorb(&s, vec2<u32>(p.x, p.y));
    sip_absorb(&s, vec2<u32>(p.z, 12u << 24u));
    s.v2.x ^= 0xffu;
    sip_round(&s);
    sip_round(&s);
    sip_round(&s);
    sip_round(&s);
    return s.v0 ^ s.v1 ^ s.v2 ^ s.v3;
}

// ---- the level's function ----

fn apply_table(lv: LevelIndex, i: u32) -> u32 {
    if (lv.table_len == 0u) {
        return i;
    }
    // Past the table's end (an index that fails LevelIndex::check) the CPU gives u32::MAX,
    // an entry outside every level, which the grid refuses.
    if (i < lv.table_len) {
        return index_tables[lv.table_offset + i];
    }
    return 0xffffffffu;
}

// Base function of vertex p, before the table.
fn base_index(lv: LevelIndex, p: vec3<u32>) -> u32 {
    if (has_kind(INDEX_PRIMES) && lv.kind == INDEX_PRIMES) {
        let h = mul_u32_u64(p.x, lv.k0) ^ mul_u32_u64(p.y, lv.k1) ^ mul_u32_u64(p.z, lv.k2);
        return reduce64(h, lv);
    }
    if (has_kind(INDEX_SIP) && lv.kind == INDEX_SIP) {
        return reduce64(siphash24_xyz(lv.sip_k0, lv.sip_k1, p), lv);
    }
    return reference_index(lv, p);
}

// Table entry of vertex p (the CPU's `LevelIndex::index`).
fn level_index(lv: LevelIndex, p: vec3<u32>) -> u32 {
    return apply_table(lv, base_index(lv, p));
}

// The 8 corners of a cell, corner bit d selecting cell[d] + 1 (x is bit 0), as the CPU's
// `LevelIndex::corners`.
fn level_corners(lv: LevelIndex, cell: vec3<u32>) -> array<u32, 8> {
    var out: array<u32, 8>;
    if (has_kind(INDEX_PRIMES) && lv.kind == INDEX_PRIMES) {
        // The CPU forms (c + 1)·k in u64, where c + 1 does not wrap at 2^32: c·k + k.
        let x0 = mul_u32_u64(cell.x, lv.k0);
        let y0 = mul_u32_u64(cell.y, lv.k1);
        let z0 = mul_u32_u64(cell.z, lv.k2);
        let hx = array<vec2<u32>, 2>(x0, add64(x0, lv.k0));
        let hy = array<vec2<u32>, 2>(y0, add64(y0, lv.k1));
        let hz = array<vec2<u32>, 2>(z0, add64(z0, lv.k2));
        for (var c = 0u; c < 8u; c++) {
            out[c] = reduce64(hx[c & 1u] ^ hy[(c >> 1u) & 1u] ^ hz[c >> 2u], lv);
        }
    } else {
        // Reference and SipHash corners take c + 1 in wrapping u32.
        for (var c = 0u; c < 8u; c++) {
            let d = vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u);
            out[c] = base_index(lv, cell + d);
        }
    }
    for (var c = 0u; c < 8u; c++) {
        out[c] = apply_table(lv, out[c]);
    }
    return out;
}
