//! SipHash-2-4 as the keyed PRF of the `prf` scheme: the derivation of per-level subkeys.
//!
//! Index message: the 12 bytes `x ‖ y ‖ z` (each u32 little-endian), so
//! `index = SipHash-2-4(subkey_l, x‖y‖z) mod size_l` is checkable with any SipHash library.
//! The engine evaluates it (`IndexFn::Sip(subkey_l)`, [`ngp::encoding::sip`]); keys
//! and their derivation stay here.
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

#[cfg(test)]
mod tests {
    use super::*;

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
