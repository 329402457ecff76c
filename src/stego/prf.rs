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
    #[inline(always)]
    fn round(&mut self) {
        for i in 0..N {
            let (mut v0, mut v1, mut v2, mut v3) = (self.v0[i], self.v1[i], self.v2[i], self.v3[i]);
            v0 = v0.wrapping_add(v1);
            v1 = v1.rotate_left(13) ^ v0;
            v0 = v0.rotate_left(32);
            v2 = v2.wrapping_add(v3);
            v3 = v3.rotate_left(16) ^ v2;
            v0 = v0.wrapping_add(v3);
            v3 = v3.rotate_left(21) ^ v0;
            v2 = v2.wrapping_add(v1);
            v1 = v1.rotate_left(17) ^ v2;
            v2 = v2.rotate_left(32);
            self.v0[i] = v0;
            self.v1[i] = v1;
            self.v2[i] = v2;
            self.v3[i] = v3;
        }
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

impl crate::ngp::encoding::LevelIndex for PrfIndex {
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        self.reduce(self.prf(x, y, z))
    }

    /// The first message block `x‖y` takes only 4 values over the 8 corners, so it is
    /// absorbed on 4 lanes; the tail (z) and finalisation run on all 8.
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        let mut head = Lanes::<4> {
            v0: [self.init[0]; 4],
            v1: [self.init[1]; 4],
            v2: [self.init[2]; 4],
            v3: [self.init[3]; 4],
        };
        let mut m0 = [0u64; 4];
        for (c, m) in m0.iter_mut().enumerate() {
            let x = cell[0].wrapping_add(c as u32 & 1) as u64;
            let y = cell[1].wrapping_add((c as u32 >> 1) & 1) as u64;
            *m = x | y << 32;
        }
        head.absorb(&m0);
        let mut s = Lanes::<8> {
            v0: [0; 8],
            v1: [0; 8],
            v2: [0; 8],
            v3: [0; 8],
        };
        let mut m1 = [0u64; 8];
        for c in 0..8 {
            s.v0[c] = head.v0[c & 3];
            s.v1[c] = head.v1[c & 3];
            s.v2[c] = head.v2[c & 3];
            s.v3[c] = head.v3[c & 3];
            m1[c] = tail_block(cell[2].wrapping_add((c as u32 >> 2) & 1));
        }
        s.absorb(&m1);
        for v in &mut s.v2 {
            *v ^= 0xff;
        }
        for _ in 0..4 {
            s.round();
        }
        for c in 0..8 {
            out[c] = self.reduce(s.v0[c] ^ s.v1[c] ^ s.v2[c] ^ s.v3[c]);
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
}
