//! Keys drawn from a seeded stream, so that a test's runs compare (these keys protect
//! nothing).

use ngp::rng::Pcg32;
use stego::{Key, SchemeKind, generate_with};

/// A key of `kind` with `m` groups, drawn from the stream (`seed`, `stream`).
pub fn seeded_key(kind: SchemeKind, m: usize, seed: u64, stream: u64) -> Key {
    let mut rng = Pcg32::new(seed, stream);
    generate_with(kind, m, || {
        Ok(((rng.next_u32() as u64) << 32) | rng.next_u32() as u64)
    })
    .expect("a seeded key")
}
