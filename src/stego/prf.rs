//! SipHash-2-4 as the keyed PRF of the `prf` scheme: subkey derivation and a lane-parallel
//! evaluation of the 8 corners of a cell.
//!
//! Index message: the 12 bytes `x ‖ y ‖ z` (each u32 little-endian), so
//! `index = SipHash-2-4(subkey_l, x‖y‖z) mod size_l` is checkable with any SipHash library.
//!
//! Subkey derivation (KDF): the 256-bit secret is split into two 128-bit SipHash keys
//! `Ka = secret[0..16]`, `Kb = secret[16..32]` (each two u64 little-endian) and
//! `subkey = SipHash-2-4-128(Ka, msg ‖ "a") ⊕ SipHash-2-4-128(Kb, msg ‖ "b")` with
//! `msg = "stegongp/v1/" ‖ purpose ‖ 0x00 ‖ level (u32 LE) ‖ size (u32 LE)`.
//! Each half is a PRF on its own, so the XOR stays unpredictable while either half is
//! secret, and every level/purpose/size gets an independent 128-bit subkey. The two
//! messages differ so that a secret with equal halves does not cancel to zero.
//!
//! The `secret` fed to the KDF is the key's *master*: for a version-1 key file, its one
//! 256-bit secret; for version 2, [`combine_secrets`] of its m independent 256-bit secrets
//! (a keyed chain over `s_0 ‖ … ‖ s_{m−1}` in which every secret keys one step, so a
//! wrong or missing secret changes the master, and with it every level's subkey).

// Lane loops index several arrays in step on purpose: that is what vectorises.
#![allow(clippy::needless_range_loop)]

use siphasher::sip128::{Hasher128, SipHasher24 as Sip128};
use std::hash::Hasher;

/// Purpose labels used in subkey derivation (domain separation).
pub const PURPOSE_INDEX: &str = "index";
pub const PURPOSE_DENSE_PERMUTE: &str = "dense-permute";
pub const PURPOSE_PRIMES_DENSE_PERMUTE: &str = "primes-dense-permute";

/// A SipHash key as two u64 words (k0, k1).
pub type SipKey = [u64; 2];

fn half(secret: &[u8; 32], at: usize) -> SipKey {
    let w = |o: usize| u64::from_le_bytes(secret[o..o + 8].try_into().unwrap_or([0; 8]));
    [w(at), w(at + 8)]
}

/// The documented KDF (module docs).
pub fn derive_subkey(secret: &[u8; 32], purpose: &str, level: u32, size: u32) -> SipKey {
    let mut msg = Vec::with_capacity(32);
    msg.extend_from_slice(b"stegongp/v1/");
    msg.extend_from_slice(purpose.as_bytes());
    msg.push(0);
    msg.extend_from_slice(&level.to_le_bytes());
    msg.extend_from_slice(&size.to_le_bytes());
    let h = |k: SipKey, tag: &[u8]| {
        let mut s = Sip128::new_with_keys(k[0], k[1]);
        s.write(&msg);
        s.write(tag);
        s.finish128()
    };
    let (a, b) = (h(half(secret, 0), b"a"), h(half(secret, 16), b"b"));
    [a.h1 ^ b.h1, a.h2 ^ b.h2]
}

/// 256 bits from a 256-bit key: `W(s, msg) = w(s, msg‖"a", msg‖"b") ‖ w(s, msg‖"c", msg‖"d")`
/// with `w(s, u, v) = SipHash-2-4-128(s[0..16], u) ⊕ SipHash-2-4-128(s[16..32], v)` (each
/// 128-bit half as two u64 little-endian). Each output half depends on both key halves.
pub fn wide_prf(secret: &[u8; 32], msg: &[u8]) -> [u8; 32] {
    let h = |k: SipKey, tag: &[u8]| {
        let mut s = Sip128::new_with_keys(k[0], k[1]);
        s.write(msg);
        s.write(tag);
        s.finish128()
    };
    let (ka, kb) = (half(secret, 0), half(secret, 16));
    let mut out = [0u8; 32];
    for (i, (ta, tb)) in [(b"a", b"b"), (b"c", b"d")].into_iter().enumerate() {
        let (a, b) = (h(ka, ta), h(kb, tb));
        out[16 * i..16 * i + 8].copy_from_slice(&(a.h1 ^ b.h1).to_le_bytes());
        out[16 * i + 8..16 * i + 16].copy_from_slice(&(a.h2 ^ b.h2).to_le_bytes());
    }
    out
}

/// Domain label of [`combine_secrets`].
pub const COMBINE_DOMAIN: &[u8] = b"stegongp/v2/prf-master";

/// The master secret of a version-2 `prf` key from its m independent secrets:
/// `state_0 = 0^256`, `state_{j+1} = W(s_j, "stegongp/v2/prf-master" ‖ 0x00 ‖ m ‖ j ‖ state_j)`
/// (m, j as u32 LE; W = [`wide_prf`]), master = `state_m`. Every secret is a key of the
/// chain, so the master is a PRF output under any one secret the attacker lacks: with
/// m − 1 secrets disclosed, 256 bits (the missing secret, or equally the state it keys)
/// remain to search, and nothing about the master can be tested without all m.
pub fn combine_secrets(secrets: &[[u8; 32]]) -> [u8; 32] {
    let m = secrets.len() as u32;
    let mut state = [0u8; 32];
    let mut msg = Vec::with_capacity(COMBINE_DOMAIN.len() + 41);
    for (j, s) in secrets.iter().enumerate() {
        msg.clear();
        msg.extend_from_slice(COMBINE_DOMAIN);
        msg.push(0);
        msg.extend_from_slice(&m.to_le_bytes());
        msg.extend_from_slice(&(j as u32).to_le_bytes());
        msg.extend_from_slice(&state);
        state = wide_prf(s, &msg);
    }
    state
}

/// One SipHash-2-4 (64-bit output) of a short message, for table building and tests.
pub fn siphash24(key: SipKey, msg: &[u8]) -> u64 {
    let mut s = siphasher::sip::SipHasher24::new_with_keys(key[0], key[1]);
    s.write(msg);
    s.finish()
}

const C0: u64 = 0x736f_6d65_7073_6575;
const C1: u64 = 0x646f_7261_6e64_6f6d;
const C2: u64 = 0x6c79_6765_6e65_7261;
const C3: u64 = 0x7465_6462_7974_6573;

/// SipHash state for N independent messages under one key, one array per state word, so
/// that each step is a plain loop over lanes that LLVM turns into vector instructions.
#[derive(Clone, Copy)]
struct Lanes<const N: usize> {
    v0: [u64; N],
    v1: [u64; N],
    v2: [u64; N],
    v3: [u64; N],
}

impl<const N: usize> Lanes<N> {
    /// One SipRound, written as whole-array steps (add, rotate, xor over all lanes) so the
    /// vectoriser sees N independent lanes per instruction.
    #[inline(always)]
    fn round(&mut self) {
        #[inline(always)]
        fn add<const N: usize>(a: &mut [u64; N], b: &[u64; N]) {
            for i in 0..N {
                a[i] = a[i].wrapping_add(b[i]);
            }
        }
        #[inline(always)]
        fn rotxor<const N: usize>(a: &mut [u64; N], r: u32, b: &[u64; N]) {
            for i in 0..N {
                a[i] = a[i].rotate_left(r) ^ b[i];
            }
        }
        #[inline(always)]
        fn rot32<const N: usize>(a: &mut [u64; N]) {
            for v in a.iter_mut() {
                *v = v.rotate_left(32);
            }
        }
        let Lanes { v0, v1, v2, v3 } = self;
        add(v0, v1);
        rotxor(v1, 13, v0);
        rot32(v0);
        add(v2, v3);
        rotxor(v3, 16, v2);
        add(v0, v3);
        rotxor(v3, 21, v0);
        add(v2, v1);
        rotxor(v1, 17, v2);
        rot32(v2);
    }

    #[inline(always)]
    fn absorb(&mut self, m: &[u64; N]) {
        for i in 0..N {
            self.v3[i] ^= m[i];
        }
        self.round();
        self.round();
        for i in 0..N {
            self.v0[i] ^= m[i];
        }
    }
}

/// The keyed PRF index of one level: `SipHash-2-4(subkey, x‖y‖z) mod size`.
#[derive(Clone, Debug)]
pub struct PrfIndex {
    /// SipHash initial state (depends only on the subkey).
    init: [u64; 4],
    size: u32,
}

/// SipHash's final block for a 12-byte message: the last 4 bytes (z) and the length.
#[inline(always)]
fn tail_block(z: u32) -> u64 {
    (12u64 << 56) | z as u64
}

impl PrfIndex {
    pub fn new(subkey: SipKey, size: u32) -> Self {
        let [k0, k1] = subkey;
        PrfIndex {
            init: [k0 ^ C0, k1 ^ C1, k0 ^ C2, k1 ^ C3],
            size,
        }
    }

    #[inline(always)]
    fn reduce(&self, h: u64) -> u32 {
        if self.size.is_power_of_two() {
            (h & (self.size as u64 - 1)) as u32
        } else {
            (h % self.size as u64) as u32
        }
    }

    /// The raw 64-bit PRF value of one vertex.
    pub fn prf(&self, x: u32, y: u32, z: u32) -> u64 {
        let mut s = Lanes::<1> {
            v0: [self.init[0]],
            v1: [self.init[1]],
            v2: [self.init[2]],
            v3: [self.init[3]],
        };
        s.absorb(&[x as u64 | (y as u64) << 32]);
        s.absorb(&[tail_block(z)]);
        s.v2[0] ^= 0xff;
        for _ in 0..4 {
            s.round();
        }
        s.v0[0] ^ s.v1[0] ^ s.v2[0] ^ s.v3[0]
    }
}

/// SipHash-2-4 of eight 12-byte messages (blocks `m0`, `m1`) under one key.
///
/// Written with explicit AVX-512 / AVX2 intrinsics where the build targets them: left to
/// itself LLVM notices that corner lanes share message words and "optimises" the lanes
/// into shuffles, which was ~2× slower than plain lockstep vectors.
mod x8 {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    #[inline(always)]
    pub fn siphash24(init: [u64; 4], m0: &[u64; 8], m1: &[u64; 8]) -> [u64; 8] {
        use std::arch::x86_64::*;
        // SAFETY: the loads/stores touch exactly the 64 bytes of the given arrays, and the
        // instructions are available (target_feature checked at compile time).
        unsafe {
            let mut v0 = _mm512_set1_epi64(init[0] as i64);
            let mut v1 = _mm512_set1_epi64(init[1] as i64);
            let mut v2 = _mm512_set1_epi64(init[2] as i64);
            let mut v3 = _mm512_set1_epi64(init[3] as i64);
            macro_rules! round {
                () => {
                    v0 = _mm512_add_epi64(v0, v1);
                    v1 = _mm512_xor_si512(_mm512_rol_epi64::<13>(v1), v0);
                    v0 = _mm512_rol_epi64::<32>(v0);
                    v2 = _mm512_add_epi64(v2, v3);
                    v3 = _mm512_xor_si512(_mm512_rol_epi64::<16>(v3), v2);
                    v0 = _mm512_add_epi64(v0, v3);
                    v3 = _mm512_xor_si512(_mm512_rol_epi64::<21>(v3), v0);
                    v2 = _mm512_add_epi64(v2, v1);
                    v1 = _mm512_xor_si512(_mm512_rol_epi64::<17>(v1), v2);
                    v2 = _mm512_rol_epi64::<32>(v2);
                };
            }
            for m in [m0, m1] {
                let mv = _mm512_loadu_si512(m.as_ptr() as *const _);
                v3 = _mm512_xor_si512(v3, mv);
                round!();
                round!();
                v0 = _mm512_xor_si512(v0, mv);
            }
            v2 = _mm512_xor_si512(v2, _mm512_set1_epi64(0xff));
            round!();
            round!();
            round!();
            round!();
            let h = _mm512_xor_si512(_mm512_xor_si512(v0, v1), _mm512_xor_si512(v2, v3));
            let mut out = [0u64; 8];
            _mm512_storeu_si512(out.as_mut_ptr() as *mut _, h);
            out
        }
    }

    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "avx2",
        not(target_feature = "avx512f")
    ))]
    #[inline(always)]
    pub fn siphash24(init: [u64; 4], m0: &[u64; 8], m1: &[u64; 8]) -> [u64; 8] {
        siphash24_avx2(init, m0, m1)
    }

    /// Two 4-lane halves; compiled wherever AVX2 is, so AVX-512 machines test it too.
    #[allow(dead_code)]
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn siphash24_avx2(init: [u64; 4], m0: &[u64; 8], m1: &[u64; 8]) -> [u64; 8] {
        use std::arch::x86_64::*;
        // SAFETY: as above; each half loads/stores 32 bytes inside the arrays.
        unsafe {
            macro_rules! rotl {
                ($x:expr, $r:literal, $s:literal) => {
                    _mm256_or_si256(_mm256_slli_epi64::<$r>($x), _mm256_srli_epi64::<$s>($x))
                };
            }
            let mut out = [0u64; 8];
            for half in 0..2 {
                let mut v0 = _mm256_set1_epi64x(init[0] as i64);
                let mut v1 = _mm256_set1_epi64x(init[1] as i64);
                let mut v2 = _mm256_set1_epi64x(init[2] as i64);
                let mut v3 = _mm256_set1_epi64x(init[3] as i64);
                macro_rules! round {
                    () => {
                        v0 = _mm256_add_epi64(v0, v1);
                        v1 = _mm256_xor_si256(rotl!(v1, 13, 51), v0);
                        v0 = _mm256_shuffle_epi32::<0b10_11_00_01>(v0);
                        v2 = _mm256_add_epi64(v2, v3);
                        v3 = _mm256_xor_si256(rotl!(v3, 16, 48), v2);
                        v0 = _mm256_add_epi64(v0, v3);
                        v3 = _mm256_xor_si256(rotl!(v3, 21, 43), v0);
                        v2 = _mm256_add_epi64(v2, v1);
                        v1 = _mm256_xor_si256(rotl!(v1, 17, 47), v2);
                        v2 = _mm256_shuffle_epi32::<0b10_11_00_01>(v2);
                    };
                }
                for m in [m0, m1] {
                    let mv = _mm256_loadu_si256(m.as_ptr().add(4 * half) as *const _);
                    v3 = _mm256_xor_si256(v3, mv);
                    round!();
                    round!();
                    v0 = _mm256_xor_si256(v0, mv);
                }
                v2 = _mm256_xor_si256(v2, _mm256_set1_epi64x(0xff));
                round!();
                round!();
                round!();
                round!();
                let h = _mm256_xor_si256(_mm256_xor_si256(v0, v1), _mm256_xor_si256(v2, v3));
                _mm256_storeu_si256(out.as_mut_ptr().add(4 * half) as *mut _, h);
            }
            out
        }
    }

    #[cfg(not(all(
        target_arch = "x86_64",
        any(target_feature = "avx2", target_feature = "avx512f")
    )))]
    #[inline(always)]
    pub fn siphash24(init: [u64; 4], m0: &[u64; 8], m1: &[u64; 8]) -> [u64; 8] {
        super::portable_x8(init, m0, m1)
    }
}

/// Lane-array SipHash-2-4 of eight messages (the non-x86 path, and the test oracle of the
/// intrinsics).
#[allow(dead_code)]
fn portable_x8(init: [u64; 4], m0: &[u64; 8], m1: &[u64; 8]) -> [u64; 8] {
    let mut s = Lanes::<8> {
        v0: [init[0]; 8],
        v1: [init[1]; 8],
        v2: [init[2]; 8],
        v3: [init[3]; 8],
    };
    s.absorb(m0);
    s.absorb(m1);
    for v in &mut s.v2 {
        *v ^= 0xff;
    }
    for _ in 0..4 {
        s.round();
    }
    let mut h = [0u64; 8];
    for c in 0..8 {
        h[c] = s.v0[c] ^ s.v1[c] ^ s.v2[c] ^ s.v3[c];
    }
    h
}

impl crate::ngp::encoding::LevelIndex for PrfIndex {
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        self.reduce(self.prf(x, y, z))
    }

    /// The 8 SipHash evaluations run in lockstep, one vector lane per corner.
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        let mut m0 = [0u64; 8];
        let mut m1 = [0u64; 8];
        for c in 0..8 {
            let x = cell[0].wrapping_add(c as u32 & 1) as u64;
            let y = cell[1].wrapping_add((c as u32 >> 1) & 1) as u64;
            m0[c] = x | y << 32;
            m1[c] = tail_block(cell[2].wrapping_add((c as u32 >> 2) & 1));
        }
        let h = x8::siphash24(self.init, &m0, &m1);
        // One branch per call, so the power-of-two case stays a vector AND.
        if self.size.is_power_of_two() {
            let mask = self.size as u64 - 1;
            for c in 0..8 {
                out[c] = (h[c] & mask) as u32;
            }
        } else {
            for c in 0..8 {
                out[c] = (h[c] % self.size as u64) as u32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ngp::encoding::LevelIndex;

    fn msg(x: u32, y: u32, z: u32) -> [u8; 12] {
        let mut b = [0u8; 12];
        b[..4].copy_from_slice(&x.to_le_bytes());
        b[4..8].copy_from_slice(&y.to_le_bytes());
        b[8..].copy_from_slice(&z.to_le_bytes());
        b
    }

    #[test]
    fn lanes_match_siphasher() {
        let key = [0x0706_0504_0302_0100, 0x0f0e_0d0c_0b0a_0908];
        let idx = PrfIndex::new(key, 1 << 19);
        for (x, y, z) in [
            (0, 0, 0),
            (1, 2, 3),
            (2047, 5, 1024),
            (u32::MAX, 7, u32::MAX),
        ] {
            assert_eq!(idx.prf(x, y, z), siphash24(key, &msg(x, y, z)));
        }
        let mut out = [0u32; 8];
        let dense = PrfIndex::new(key, 12168);
        for idx in [&idx, &dense] {
            idx.corners([10, 20, 30], &mut out);
            for (c, &o) in out.iter().enumerate() {
                let (x, y, z) = (
                    10 + (c as u32 & 1),
                    20 + (c as u32 >> 1 & 1),
                    30 + (c as u32 >> 2),
                );
                let want = siphash24(key, &msg(x, y, z)) % idx.size as u64;
                assert_eq!(o as u64, want, "corner {c}");
                assert_eq!(o, idx.index(x, y, z));
            }
        }
    }

    #[test]
    fn vector_paths_agree_with_portable_lanes() {
        let init = PrfIndex::new([0x1234_5678_9abc_def0, 42], 8).init;
        let m0: [u64; 8] = std::array::from_fn(|i| ((i as u64) << 33) | (i as u64 * 7));
        let m1: [u64; 8] = std::array::from_fn(|i| 12 << 56 | (i as u64 * 99));
        assert_eq!(x8::siphash24(init, &m0, &m1), portable_x8(init, &m0, &m1));
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        assert_eq!(
            x8::siphash24_avx2(init, &m0, &m1),
            portable_x8(init, &m0, &m1)
        );
    }

    #[test]
    fn subkeys_separate_levels_purposes_and_secret_halves() {
        let mut s = [7u8; 32];
        let a = derive_subkey(&s, PURPOSE_INDEX, 3, 79512);
        assert_ne!(a, [0, 0], "equal halves must not cancel");
        assert_ne!(a, derive_subkey(&s, PURPOSE_INDEX, 4, 79512));
        assert_ne!(a, derive_subkey(&s, PURPOSE_INDEX, 3, 79520));
        assert_ne!(a, derive_subkey(&s, PURPOSE_DENSE_PERMUTE, 3, 79512));
        s[31] ^= 1;
        assert_ne!(a, derive_subkey(&s, PURPOSE_INDEX, 3, 79512));
        s[31] ^= 1;
        s[0] ^= 1;
        assert_ne!(a, derive_subkey(&s, PURPOSE_INDEX, 3, 79512));
    }

    #[test]
    fn derive_subkey_is_the_documented_kdf() {
        // Version-1 key files must keep their index functions: the KDF is frozen.
        let s: [u8; 32] = std::array::from_fn(|i| i as u8);
        let mut msg = b"stegongp/v1/index\0".to_vec();
        msg.extend_from_slice(&9u32.to_le_bytes());
        msg.extend_from_slice(&(1u32 << 19).to_le_bytes());
        let sip = |k: SipKey, tag: &[u8]| {
            let mut h = Sip128::new_with_keys(k[0], k[1]);
            h.write(&msg);
            h.write(tag);
            h.finish128()
        };
        let (a, b) = (sip(half(&s, 0), b"a"), sip(half(&s, 16), b"b"));
        assert_eq!(
            derive_subkey(&s, PURPOSE_INDEX, 9, 1 << 19),
            [a.h1 ^ b.h1, a.h2 ^ b.h2]
        );
    }

    #[test]
    fn combined_master_depends_on_every_secret_and_on_m() {
        let secrets: Vec<[u8; 32]> = (0..4u8).map(|j| [j.wrapping_mul(29) ^ 0x5a; 32]).collect();
        let master = combine_secrets(&secrets);
        assert_ne!(master, [0u8; 32]);
        for j in 0..4 {
            for bit in [0usize, 77, 255] {
                let mut t = secrets.clone();
                t[j][bit / 8] ^= 1 << (bit % 8);
                assert_ne!(combine_secrets(&t), master, "secret {j} bit {bit}");
            }
        }
        // Order, count and a single secret's own value all matter.
        let mut swapped = secrets.clone();
        swapped.swap(1, 2);
        assert_ne!(combine_secrets(&swapped), master);
        assert_ne!(
            combine_secrets(&secrets[..3]),
            combine_secrets(&secrets[..2])
        );
        assert_ne!(combine_secrets(&secrets[..1]), secrets[0]);
        // W's halves differ and depend on both key halves.
        let w = wide_prf(&secrets[0], b"x");
        assert_ne!(w[..16], w[16..]);
        let mut k = secrets[0];
        k[20] ^= 1;
        let w2 = wide_prf(&k, b"x");
        assert!(w[..16] != w2[..16] && w[16..] != w2[16..]);
    }
}
