//! SipHash-2-4 of a grid vertex, `SipHash-2-4(k, x‖y‖z)` with the 12-byte message of the
//! three coordinates as u32 little-endian (checkable with any SipHash library), and a
//! lane-parallel evaluation of a cell's 8 corners in lockstep. The engine only evaluates
//! it for a given 128-bit key ([`super::IndexFn::Sip`]); where keys come from is the stego
//! layer's business.

// Lane loops index several arrays in step on purpose: that is what vectorises.
#![allow(clippy::needless_range_loop)]

const C0: u64 = 0x736f_6d65_7073_6575;
const C1: u64 = 0x646f_7261_6e64_6f6d;
const C2: u64 = 0x6c79_6765_6e65_7261;
const C3: u64 = 0x7465_6462_7974_6573;

/// SipHash's initial state for key `(k0, k1)`: it depends on the key alone, so a level
/// computes it once.
#[inline(always)]
pub fn key_state(key: [u64; 2]) -> [u64; 4] {
    let [k0, k1] = key;
    [k0 ^ C0, k1 ^ C1, k0 ^ C2, k1 ^ C3]
}

/// SipHash's final block for a 12-byte message: the last 4 bytes (z) and the length.
#[inline(always)]
fn tail_block(z: u32) -> u64 {
    (12u64 << 56) | z as u64
}

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

/// SipHash-2-4 of the vertex `(x, y, z)` from the state [`key_state`] made.
#[inline]
pub fn vertex(init: [u64; 4], x: u32, y: u32, z: u32) -> u64 {
    let mut s = Lanes::<1> {
        v0: [init[0]],
        v1: [init[1]],
        v2: [init[2]],
        v3: [init[3]],
    };
    s.absorb(&[x as u64 | (y as u64) << 32]);
    s.absorb(&[tail_block(z)]);
    s.v2[0] ^= 0xff;
    for _ in 0..4 {
        s.round();
    }
    s.v0[0] ^ s.v1[0] ^ s.v2[0] ^ s.v3[0]
}

/// SipHash-2-4 of the 8 corners of `cell` (corner bit `d` selects `cell[d] + 1`, x is bit
/// 0), run in lockstep, one vector lane per corner.
#[inline(always)]
pub fn corners(init: [u64; 4], cell: [u32; 3]) -> [u64; 8] {
    let mut m0 = [0u64; 8];
    let mut m1 = [0u64; 8];
    for c in 0..8 {
        let x = cell[0].wrapping_add(c as u32 & 1) as u64;
        let y = cell[1].wrapping_add((c as u32 >> 1) & 1) as u64;
        m0[c] = x | y << 32;
        m1[c] = tail_block(cell[2].wrapping_add((c as u32 >> 2) & 1));
    }
    x8::siphash24(init, &m0, &m1)
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::hash::Hasher;

    fn siphasher(key: [u64; 2], x: u32, y: u32, z: u32) -> u64 {
        let mut b = [0u8; 12];
        b[..4].copy_from_slice(&x.to_le_bytes());
        b[4..8].copy_from_slice(&y.to_le_bytes());
        b[8..].copy_from_slice(&z.to_le_bytes());
        let mut s = siphasher::sip::SipHasher24::new_with_keys(key[0], key[1]);
        s.write(&b);
        s.finish()
    }

    #[test]
    fn lanes_match_siphasher() {
        let key = [0x0706_0504_0302_0100, 0x0f0e_0d0c_0b0a_0908];
        let st = key_state(key);
        for (x, y, z) in [
            (0, 0, 0),
            (1, 2, 3),
            (2047, 5, 1024),
            (u32::MAX, 7, u32::MAX),
        ] {
            assert_eq!(vertex(st, x, y, z), siphasher(key, x, y, z));
        }
        for cell in [[10u32, 20, 30], [u32::MAX, 0, u32::MAX - 1]] {
            let h = corners(st, cell);
            for (c, &v) in h.iter().enumerate() {
                let (x, y, z) = (
                    cell[0].wrapping_add(c as u32 & 1),
                    cell[1].wrapping_add(c as u32 >> 1 & 1),
                    cell[2].wrapping_add(c as u32 >> 2),
                );
                assert_eq!(v, siphasher(key, x, y, z), "cell {cell:?} corner {c}");
            }
        }
    }

    #[test]
    fn vector_paths_agree_with_portable_lanes() {
        let st = key_state([0x1234_5678_9abc_def0, 42]);
        let m0: [u64; 8] = std::array::from_fn(|i| ((i as u64) << 33) | (i as u64 * 7));
        let m1: [u64; 8] = std::array::from_fn(|i| 12 << 56 | (i as u64 * 99));
        assert_eq!(x8::siphash24(st, &m0, &m1), portable_x8(st, &m0, &m1));
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        assert_eq!(x8::siphash24_avx2(st, &m0, &m1), portable_x8(st, &m0, &m1));
    }
}
