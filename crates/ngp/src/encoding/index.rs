//! Per-level index functions, as plain data: where a grid vertex lives in its level's table.
//!
//! A level's index is a [`LevelIndex`]: one of three arithmetic kinds ([`IndexFn`]) and an
//! optional table applied after it. The reference (tiny-cuda-nn) index is
//! [`IndexFn::Reference`] without a table: dense `x + y·res + z·res²` where the level fits,
//! else the coherent-prime hash, both in wrapping u32 and taken modulo the level size (spec
//! §1.3–1.4). Keyed indices are built by `crate::stego` from the same kinds and tables; the
//! engine evaluates them and knows nothing of keys. Data rather than a trait object, so
//! that the CPU picks a level's arithmetic once per level of a chunk (no virtual call per
//! corner) and a GPU can upload it.

use super::layout::{GridLayout, LevelInfo};
use super::sip;
use crate::error::{Error, Result};
use std::fmt;
use std::sync::Arc;

/// tiny-cuda-nn's CoherentPrime constants for 3-D inputs.
pub const REFERENCE_PRIMES: [u32; 3] = [1, 2654435761, 805459861];

/// The arithmetic of one level's index, before any table.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum IndexFn {
    /// tiny-cuda-nn's: on a dense level `x + y·r + z·r²` (wrapping u32) mod size, else
    /// [`coherent_prime_hash`] with [`REFERENCE_PRIMES`] mod size.
    Reference,
    /// `(x·k1 ⊕ y·k2 ⊕ z·k3) mod size`, products in wrapping u64.
    Primes([u64; 3]),
    /// `SipHash-2-4(key, x‖y‖z) mod size`, the 12-byte message of the coordinates as u32
    /// little-endian ([`sip`]).
    Sip([u64; 2]),
}

/// Keyed variants hold secrets: debug output names the kind only.
impl fmt::Debug for IndexFn {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            IndexFn::Reference => "Reference",
            IndexFn::Primes(_) => "Primes(..)",
            IndexFn::Sip(_) => "Sip(..)",
        })
    }
}

/// The index function of one grid level: `table[base(x, y, z)]`, or `base(x, y, z)` without
/// a table.
#[derive(Clone, PartialEq)]
pub struct LevelIndex {
    pub resolution: u32,
    pub size: u32,
    pub dense: bool,
    pub base: IndexFn,
    /// Length `size`, entries in `[0, size)` ([`LevelIndex::check`]): a dense level's keyed
    /// permutation, a stealth confinement map, or the two composed (one lookup a corner).
    pub table: Option<Arc<[u32]>>,
}

impl fmt::Debug for LevelIndex {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("LevelIndex")
            .field("resolution", &self.resolution)
            .field("size", &self.size)
            .field("dense", &self.dense)
            .field("base", &self.base)
            .field("table_len", &self.table.as_ref().map(|t| t.len()))
            .finish()
    }
}

/// One index function per level, in level order.
pub type LevelIndices = Vec<LevelIndex>;

/// The reference index for every level of `layout`.
pub fn reference_indices(layout: &GridLayout) -> LevelIndices {
    layout.levels.iter().map(LevelIndex::reference).collect()
}

/// [`LevelIndex::check`] of every level, and one index per level.
pub fn check_indices(indices: &[LevelIndex], layout: &GridLayout) -> Result<()> {
    if indices.len() != layout.levels.len() {
        return Err(Error::Config(format!(
            "{} index functions for {} grid levels",
            indices.len(),
            layout.levels.len()
        )));
    }
    indices
        .iter()
        .zip(&layout.levels)
        .try_for_each(|(ix, lv)| ix.check(lv))
}

/// `x·π1 ⊕ y·π2 ⊕ z·π3` in wrapping u32 (tcnn `lcg_hash`).
#[inline(always)]
pub fn coherent_prime_hash(x: u32, y: u32, z: u32, primes: [u32; 3]) -> u32 {
    x.wrapping_mul(primes[0]) ^ y.wrapping_mul(primes[1]) ^ z.wrapping_mul(primes[2])
}

/// A level's arithmetic with its per-level choices made (dense or hashed, table or not,
/// SipHash's key state): loops over many cells are compiled once per kind of kernel.
pub trait Kernel: Copy {
    /// Table entry of vertex `(x, y, z)`.
    fn index(&self, x: u32, y: u32, z: u32) -> u32;
    /// The 8 corners of a cell; corner bit `d` selects `cell[d] + 1` (x is bit 0), as the
    /// reference interpolation does.
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]);
}

/// Work done over one level with its [`Kernel`] ([`LevelIndex::with_kernel`]).
pub trait WithKernel: Sized {
    type Output;
    fn run<K: Kernel>(self, kernel: K) -> Self::Output;

    /// A level with a table: `base`, then [`table_lookup`] in `table`. By default the two as
    /// one kernel; work over many cells can instead take every base entry first and look
    /// them up after, so that the table's cache misses overlap instead of stalling each
    /// corner (a stealth confinement map is 2 MB a hashed level, read at random).
    #[inline(always)]
    fn run_tabled<K: Kernel>(self, base: K, table: &[u32]) -> Self::Output {
        self.run(Tabled { base, table })
    }
}

/// `table[e]`, or an entry outside every level (which the grid refuses) where `e` is outside
/// the table (an index that fails [`LevelIndex::check`]), rather than a panic.
#[inline(always)]
pub fn table_lookup(table: &[u32], e: u32) -> u32 {
    table.get(e as usize).copied().unwrap_or(u32::MAX)
}

impl LevelIndex {
    pub fn new(level: &LevelInfo, base: IndexFn) -> Self {
        LevelIndex {
            resolution: level.resolution,
            size: level.size,
            dense: level.dense,
            base,
            table: None,
        }
    }

    /// The reference (tiny-cuda-nn) index of `level`.
    pub fn reference(level: &LevelInfo) -> Self {
        LevelIndex::new(level, IndexFn::Reference)
    }

    /// The same arithmetic followed by `table` (replacing any table it had).
    pub fn with_table(self, table: impl Into<Arc<[u32]>>) -> Self {
        LevelIndex {
            table: Some(table.into()),
            ..self
        }
    }

    /// That this is an index of `level`: the same resolution, size and layout, and a table
    /// (if any) of `size` entries inside the level. Every entry the index returns is then
    /// in `[0, size)`.
    pub fn check(&self, level: &LevelInfo) -> Result<()> {
        let want = (level.resolution, level.size, level.dense);
        if (self.resolution, self.size, self.dense) != want || self.size == 0 {
            return Err(Error::Config(format!(
                "level {}: index function for resolution {}, size {}, dense {} on a level of \
                 resolution {}, size {}, dense {}",
                level.level, self.resolution, self.size, self.dense, want.0, want.1, want.2
            )));
        }
        if let Some(t) = &self.table
            && (t.len() != self.size as usize || t.iter().any(|&e| e >= self.size))
        {
            return Err(Error::Config(format!(
                "level {}: index table of {} entries does not map into the level's {} slots",
                level.level,
                t.len(),
                self.size
            )));
        }
        Ok(())
    }

    /// Runs `work` with this level's kernel: the one `match` on the description.
    #[inline]
    pub fn with_kernel<W: WithKernel>(&self, work: W) -> W::Output {
        let (size, pow2) = (self.size, self.size.is_power_of_two());
        match self.base {
            IndexFn::Reference if self.dense => {
                self.then_table(ReferenceDense::new(self.resolution, size), work)
            }
            IndexFn::Reference if pow2 => {
                self.then_table(ReferenceHashedPow2 { mask: size - 1 }, work)
            }
            IndexFn::Reference => self.then_table(ReferenceHashedMod { size }, work),
            IndexFn::Primes(k) => self.then_table(Primes { k, size, pow2 }, work),
            IndexFn::Sip(key) => self.then_table(
                Sip {
                    state: sip::key_state(key),
                    size,
                    pow2,
                },
                work,
            ),
        }
    }

    #[inline(always)]
    fn then_table<K: Kernel, W: WithKernel>(&self, base: K, work: W) -> W::Output {
        match self.table.as_deref() {
            None => work.run(base),
            Some(table) => work.run_tabled(base, table),
        }
    }

    /// Table entry of vertex `(x, y, z)`, in `[0, size)` for an index that passes
    /// [`LevelIndex::check`].
    #[inline]
    pub fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        struct Vertex(u32, u32, u32);
        impl WithKernel for Vertex {
            type Output = u32;
            #[inline(always)]
            fn run<K: Kernel>(self, k: K) -> u32 {
                k.index(self.0, self.1, self.2)
            }
        }
        self.with_kernel(Vertex(x, y, z))
    }

    /// The 8 corners of a cell ([`Kernel::corners`]). Loops over many cells of one level
    /// should take the kernel once instead ([`LevelIndex::with_kernel`]).
    #[inline]
    pub fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        struct Cell<'a>([u32; 3], &'a mut [u32; 8]);
        impl WithKernel for Cell<'_> {
            type Output = ();
            #[inline(always)]
            fn run<K: Kernel>(self, k: K) {
                k.corners(self.0, self.1)
            }
        }
        self.with_kernel(Cell(cell, out))
    }
}

/// Reference dense level: `x + y·r + z·r²` in wrapping u32, mod size.
#[derive(Clone, Copy)]
struct ReferenceDense {
    r: u32,
    size: u32,
    /// Offsets of corners 0..8 from corner 0, wrapping like the index itself.
    steps: [u32; 8],
    /// Corner-0 values below this wrap no corner's sum (see `corners`); 0 where the short
    /// way never applies.
    no_wrap_below: u32,
}

impl ReferenceDense {
    #[inline(always)]
    fn new(r: u32, size: u32) -> Self {
        let rr = r.wrapping_mul(r);
        let steps = [
            0,
            1,
            r,
            r.wrapping_add(1),
            rr,
            rr.wrapping_add(1),
            rr.wrapping_add(r),
            rr.wrapping_add(r).wrapping_add(1),
        ];
        let max_step = steps.iter().copied().max().unwrap_or(0);
        // The short way needs steps < size (true of every real dense level: r² + r + 1 <
        // r³ ≤ size) and b + step not to wrap (b < size ≤ 2^31).
        let no_wrap_below = if max_step < size && size <= 1 << 31 {
            u32::MAX - max_step + 1
        } else {
            0
        };
        ReferenceDense {
            r,
            size,
            steps,
            no_wrap_below,
        }
    }
}

impl Kernel for ReferenceDense {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        let r = self.r;
        x.wrapping_add(y.wrapping_mul(r))
            .wrapping_add(z.wrapping_mul(r.wrapping_mul(r)))
            % self.size
    }

    #[inline(always)]
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        let r = self.r;
        let base = cell[0]
            .wrapping_add(cell[1].wrapping_mul(r))
            .wrapping_add(cell[2].wrapping_mul(r.wrapping_mul(r)));
        if base < self.no_wrap_below {
            // No corner's sum wraps, so (base + step) mod size = (base mod size + step) mod
            // size with both terms < size: one division a cell instead of eight. Then mod
            // size: v < 2·size, and where v < size, v − size wraps above v (size ≤ 2^31), so
            // the min is the conditional subtraction, in a form that vectorises.
            let b = base % self.size;
            for (o, &step) in out.iter_mut().zip(&self.steps) {
                let v = b + step;
                *o = v.min(v.wrapping_sub(self.size));
            }
        } else {
            for (o, &step) in out.iter_mut().zip(&self.steps) {
                *o = base.wrapping_add(step) % self.size;
            }
        }
    }
}

/// The coherent-prime hash's per-axis terms of a cell's two vertex rows: corner `c` hashes
/// to `x[c & 1] ^ y[(c >> 1) & 1] ^ z[c >> 2]`.
#[inline(always)]
fn reference_axis_terms(cell: [u32; 3]) -> ([u32; 2], [u32; 2], [u32; 2]) {
    let [_, p1, p2] = REFERENCE_PRIMES;
    (
        [cell[0], cell[0].wrapping_add(1)],
        [
            cell[1].wrapping_mul(p1),
            cell[1].wrapping_add(1).wrapping_mul(p1),
        ],
        [
            cell[2].wrapping_mul(p2),
            cell[2].wrapping_add(1).wrapping_mul(p2),
        ],
    )
}

/// Reference hashed level of a power-of-two size (every real one): the coherent-prime hash
/// masked. A kernel of its own, without the non-power-of-two branch, because with that
/// branch inside LLVM left the eight corners scalar, and the grid's vector load of them then
/// missed store forwarding (−10 % training throughput measured).
#[derive(Clone, Copy)]
struct ReferenceHashedPow2 {
    mask: u32,
}

impl Kernel for ReferenceHashedPow2 {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        coherent_prime_hash(x, y, z, REFERENCE_PRIMES) & self.mask
    }

    #[inline(always)]
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        let (hx, hy, hz) = reference_axis_terms(cell);
        for c in 0..8 {
            out[c] = (hx[c & 1] ^ hy[(c >> 1) & 1] ^ hz[c >> 2]) & self.mask;
        }
    }
}

/// Reference hashed level of any other size: the coherent-prime hash mod size.
#[derive(Clone, Copy)]
struct ReferenceHashedMod {
    size: u32,
}

impl Kernel for ReferenceHashedMod {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        coherent_prime_hash(x, y, z, REFERENCE_PRIMES) % self.size
    }

    #[inline(always)]
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        let (hx, hy, hz) = reference_axis_terms(cell);
        for c in 0..8 {
            out[c] = (hx[c & 1] ^ hy[(c >> 1) & 1] ^ hz[c >> 2]) % self.size;
        }
    }
}

/// `h mod size` of a 64-bit hash, a mask where size is a power of two.
#[inline(always)]
fn reduce64(h: u64, size: u32, pow2: bool) -> u32 {
    if pow2 {
        (h & (size as u64 - 1)) as u32
    } else {
        (h % size as u64) as u32
    }
}

/// [`reduce64`] of a cell's 8 corners, with one branch a cell (not a corner) so that the
/// power-of-two case stays a vector AND.
#[inline(always)]
fn reduce64x8(h: [u64; 8], size: u32, pow2: bool, out: &mut [u32; 8]) {
    if pow2 {
        let mask = size as u64 - 1;
        for (o, h) in out.iter_mut().zip(h) {
            *o = (h & mask) as u32;
        }
    } else {
        for (o, h) in out.iter_mut().zip(h) {
            *o = (h % size as u64) as u32;
        }
    }
}

/// `(x·k1 ⊕ y·k2 ⊕ z·k3) mod size` in wrapping u64.
#[derive(Clone, Copy)]
struct Primes {
    k: [u64; 3],
    size: u32,
    pow2: bool,
}

impl Kernel for Primes {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        let h = (x as u64).wrapping_mul(self.k[0])
            ^ (y as u64).wrapping_mul(self.k[1])
            ^ (z as u64).wrapping_mul(self.k[2]);
        reduce64(h, self.size, self.pow2)
    }

    #[inline(always)]
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        // Per-axis products: 6 multiplications a cell instead of 24.
        let axis = |i: usize| {
            let c = cell[i] as u64;
            [c.wrapping_mul(self.k[i]), (c + 1).wrapping_mul(self.k[i])]
        };
        let (hx, hy, hz) = (axis(0), axis(1), axis(2));
        for (c, o) in out.iter_mut().enumerate() {
            *o = reduce64(
                hx[c & 1] ^ hy[(c >> 1) & 1] ^ hz[(c >> 2) & 1],
                self.size,
                self.pow2,
            );
        }
    }
}

/// SipHash-2-4 of the vertex mod size.
#[derive(Clone, Copy)]
struct Sip {
    state: [u64; 4],
    size: u32,
    pow2: bool,
}

impl Kernel for Sip {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        reduce64(sip::vertex(self.state, x, y, z), self.size, self.pow2)
    }

    /// The 8 SipHash evaluations run in lockstep, one vector lane per corner.
    #[inline(always)]
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        reduce64x8(sip::corners(self.state, cell), self.size, self.pow2, out);
    }
}

/// `base` followed by a table lookup.
#[derive(Clone, Copy)]
struct Tabled<'a, K> {
    base: K,
    table: &'a [u32],
}

impl<K: Kernel> Kernel for Tabled<'_, K> {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        table_lookup(self.table, self.base.index(x, y, z))
    }

    #[inline(always)]
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        self.base.corners(cell, out);
        for o in out.iter_mut() {
            *o = table_lookup(self.table, *o);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::layout::{GridConfig, GridLayout};
    use crate::rng::Pcg32;
    use std::hash::Hasher;

    fn layout() -> GridLayout {
        GridLayout::new(GridConfig::default(), 1).unwrap()
    }

    fn corner(cell: [u32; 3], c: usize) -> (u32, u32, u32) {
        (
            cell[0].wrapping_add(c as u32 & 1),
            cell[1].wrapping_add((c as u32 >> 1) & 1),
            cell[2].wrapping_add((c as u32 >> 2) & 1),
        )
    }

    #[test]
    fn dense_level_by_hand() {
        let g = layout();
        // Level 1: res 23, size 12168 = next_multiple(23³ = 12167, 8).
        let idx = LevelIndex::reference(&g.levels[1]);
        assert_eq!(idx.index(0, 0, 0), 0);
        assert_eq!(idx.index(5, 7, 11), 5 + 7 * 23 + 11 * 529); // 5985
        assert_eq!(idx.index(22, 22, 22), 12166);
        // The upper corner may equal res and wraps into the next row / past the end.
        assert_eq!(idx.index(23, 22, 22), 12167);
        assert_eq!(idx.index(23, 23, 22), (23 + 23 * 23 + 22 * 529) % 12168); // 1
        assert_eq!(idx.index(23, 23, 23), (23 + 23 * 23 + 23 * 529) % 12168); // 530
    }

    #[test]
    fn hashed_level_by_hand() {
        let g = layout();
        let idx = LevelIndex::reference(&g.levels[15]);
        // Worked out from the formula: 2·2654435761 mod 2^32 = 1013904226,
        // 3·805459861 mod 2^32 = 2416379583, 1 ^ 1013904226 ^ 2416379583 = 2892625372,
        // and 2892625372 mod 2^19 = 128476.
        assert_eq!(idx.index(1, 2, 3), 128476);
        assert_eq!(idx.index(0, 0, 0), 0);
        assert_eq!(idx.index(7, 0, 0), 7); // π1 = 1 leaves x unscrambled
        assert_eq!(idx.index(0, 1, 0), 489905); // 2654435761 mod 2^19
        // Level 5 (res 81) is the first hashed level of the paper config.
        let idx5 = LevelIndex::reference(&g.levels[5]);
        assert_eq!(idx5.index(1, 2, 3), 128476);
    }

    #[test]
    fn corners_agree_with_index() {
        let g = layout();
        for l in [0usize, 3, 4, 5, 9, 15] {
            let idx = LevelIndex::reference(&g.levels[l]);
            let r = g.levels[l].resolution;
            for cell in [[0, 0, 0], [r - 1, r - 1, r - 1], [3, r / 2, 1]] {
                let mut out = [0u32; 8];
                idx.corners(cell, &mut out);
                for (c, &o) in out.iter().enumerate() {
                    let (x, y, z) = corner(cell, c);
                    assert_eq!(o, idx.index(x, y, z), "level {l} cell {cell:?} corner {c}");
                    assert!(o < g.levels[l].size);
                }
            }
        }
    }

    /// Each kind against its formula written out the straightforward scalar way, on random
    /// cells in the level and far outside it (where the u32 arithmetic wraps), through
    /// `corners`, `index` and `with_kernel`.
    #[test]
    fn every_kind_equals_its_scalar_formula() {
        let sip_ref = |k: [u64; 2], x: u32, y: u32, z: u32| {
            let mut s = siphasher::sip::SipHasher24::new_with_keys(k[0], k[1]);
            for v in [x, y, z] {
                s.write(&v.to_le_bytes());
            }
            s.finish()
        };
        let mut rng = Pcg32::new(10, 1);
        for cfg in [
            GridConfig::default(),
            GridConfig::base_json_2023(),
            GridConfig {
                n_levels: 3,
                n_features: 1,
                log2_hashmap_size: 12,
                base_resolution: 2,
            },
        ] {
            let g = GridLayout::new(cfg, 1).unwrap();
            for lv in &g.levels {
                let (r, size) = (lv.resolution, lv.size);
                let keys = [rng.next_u32() as u64 * 7919, 1 << 40 | 3, 10_000_019];
                let sk = [0x0123_4567_89ab_cdef, rng.next_u32() as u64];
                let table: Arc<[u32]> = (0..size).map(|_| rng.below(size)).collect();
                type Formula<'a> = &'a dyn Fn(u32, u32, u32) -> u32;
                let kinds: [(IndexFn, Formula); 3] = [
                    (IndexFn::Reference, &|x, y, z| {
                        if lv.dense {
                            x.wrapping_add(y.wrapping_mul(r))
                                .wrapping_add(z.wrapping_mul(r.wrapping_mul(r)))
                                % size
                        } else {
                            (x ^ y.wrapping_mul(2654435761) ^ z.wrapping_mul(805459861)) % size
                        }
                    }),
                    (IndexFn::Primes(keys), &|x, y, z| {
                        let h = (x as u64).wrapping_mul(keys[0])
                            ^ (y as u64).wrapping_mul(keys[1])
                            ^ (z as u64).wrapping_mul(keys[2]);
                        (h % size as u64) as u32
                    }),
                    (IndexFn::Sip(sk), &|x, y, z| {
                        (sip_ref(sk, x, y, z) % size as u64) as u32
                    }),
                ];
                for (base, formula) in kinds {
                    let plain = LevelIndex::new(lv, base);
                    let tabled = plain.clone().with_table(table.clone());
                    plain.check(lv).unwrap();
                    tabled.check(lv).unwrap();
                    for i in 0..400 {
                        let cell = if i % 4 == 3 {
                            [0; 3].map(|_: u32| rng.next_u32() >> (i % 3))
                        } else {
                            [0; 3].map(|_: u32| rng.below(r + 1))
                        };
                        let (mut a, mut b) = ([0u32; 8], [0u32; 8]);
                        plain.corners(cell, &mut a);
                        tabled.corners(cell, &mut b);
                        for c in 0..8 {
                            let (x, y, z) = corner(cell, c);
                            let want = formula(x, y, z);
                            let ctx = format!("{base:?} level {} cell {cell:?} c {c}", lv.level);
                            assert_eq!(a[c], want, "{ctx}");
                            assert_eq!(b[c], table[want as usize], "{ctx} tabled");
                            assert_eq!(plain.index(x, y, z), want, "{ctx}");
                            assert_eq!(tabled.index(x, y, z), b[c], "{ctx}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn check_refuses_indices_of_another_level_and_bad_tables() {
        let g = layout();
        let (l1, l2) = (&g.levels[1], &g.levels[2]);
        assert!(LevelIndex::reference(l1).check(l1).is_ok());
        assert!(LevelIndex::reference(l1).check(l2).is_err());
        let short = LevelIndex::reference(l1).with_table(vec![0u32; 10]);
        assert!(short.check(l1).is_err());
        let outside = LevelIndex::reference(l1).with_table(vec![l1.size; l1.size as usize]);
        assert!(outside.check(l1).is_err());
        // Evaluated anyway, a short table gives an entry the grid refuses, not a panic.
        assert_eq!(short.index(5, 7, 11), u32::MAX);
    }

    #[test]
    fn debug_output_shows_no_key() {
        let g = layout();
        let idx = LevelIndex::new(&g.levels[7], IndexFn::Sip([0xdead_beef, 0x1234_5678]));
        let s = format!("{:?}", idx.with_table(vec![0u32; 4]));
        assert!(
            s.contains("Sip(..)") && s.contains("table_len: Some(4)"),
            "{s}"
        );
        assert!(!s.contains("3735928559") && !s.contains("deadbeef"), "{s}");
    }
}
