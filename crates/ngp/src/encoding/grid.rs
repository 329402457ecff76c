//! Multi-resolution hash-grid encoding (spec §1): per level, trilinear interpolation of the
//! `F` features stored at the 8 corners of the cell containing the sample; the corners'
//! table entries come from the level's [`LevelIndex`](super::index::LevelIndex).
//!
//! Work is done level by level over a whole chunk: a first pass computes every sample's
//! corner offsets and weights (kept in a [`GridCache`] for the backward pass) and prefetches
//! each corner as soon as it is known, so the misses overlap the index arithmetic (a level
//! whose index ends in a table keeps the chunk's base entries first, prefetching their
//! lines of the table, and maps them after); a second pass gathers from (by then) cached
//! lines. A level of a 512-sample chunk touches at most
//! 4096 lines (256 KB), which fits in L2. The backward scatter prefetches the next level's
//! gradient lines while it writes the current one.
//! Encodings are feature-major: feature `l·F + f` of sample `s` lives at `enc[(l·F+f)·ld + s]`.

use super::index::{Kernel, LevelIndices, WithKernel, table_lookup};
use super::layout::{GridLayout, LevelInfo};

const CORNERS: usize = 8;
/// Samples ahead of the current one whose corners are prefetched where no earlier pass
/// could (cpu-performance-notes).
const PREFETCH_AHEAD: usize = 16;
/// Prefetch table lines in the corner pass rather than a few samples ahead in the gather:
/// measured ~1.5x faster forward on the shared 2-core machine.
const PREFETCH_IN_CORNERS: bool = true;
/// Prefetch the next level's gradient lines during the scatter: ~+20 % fwd+bwd measured.
const PREFETCH_NEXT_LEVEL: bool = true;

/// Prefetches `p`'s line into L2, not L1. The prefetches here run a whole pass ahead of their
/// use (a level's corners for a chunk, then its gather; the next level's gradient lines
/// during this level's scatter): up to 4096 lines, 256 KB, in between, which L2 holds and
/// L1 (32–48 KB) does not. (The last level's scatter has no next level; it prefetches
/// `PREFETCH_AHEAD` samples ahead instead.) Against `_MM_HINT_T0` on the AMD EPYC, the same bits: training
/// +14 % (medians), views −4 to −6 % (benchmarks/engine.md, "Prefetching into L2").
#[inline(always)]
fn prefetch<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: prefetch is a hint; it never faults, even on an invalid address.
    unsafe {
        core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T1 }>(p as *const i8);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Corner offsets and trilinear weights of one chunk, per (level, sample, corner).
pub struct GridCache {
    capacity: usize,
    /// Whether every level's corners are kept, for a backward pass; an inference cache's
    /// levels reuse one slot (32 KB against 512 KB a chunk, which left the table's lines
    /// more of L2). A flag, not the slot count: a one-level layout keeps every level in one.
    keeps_every_level: bool,
    /// Levels the slots hold (the layout's, or 1 for inference).
    slots: usize,
    n: usize,
    /// Offset in floats (entry·F) into the grid table of each corner.
    offs: Vec<u32>,
    weights: Vec<f32>,
}

impl GridCache {
    pub fn new(layout: &GridLayout, capacity: usize) -> Self {
        Self::keeping(true, layout.levels.len(), capacity)
    }

    /// A cache for [`forward`] alone: it keeps the last level's corners only, so neither
    /// [`backward`] nor [`corner_offsets`](Self::corner_offsets) can use it.
    pub fn for_inference(capacity: usize) -> Self {
        Self::keeping(false, 1, capacity)
    }

    fn keeping(keeps_every_level: bool, slots: usize, capacity: usize) -> Self {
        let len = slots * capacity * CORNERS;
        GridCache {
            capacity,
            keeps_every_level,
            slots,
            n: 0,
            offs: vec![0; len],
            weights: vec![0.0; len],
        }
    }

    /// The slot of `level`'s corners.
    fn slot(&self, level: usize) -> usize {
        if self.keeps_every_level { level } else { 0 }
    }

    /// Whether a [`backward`] can use the corners of the last [`forward`].
    pub fn keeps_every_level(&self) -> bool {
        self.keeps_every_level
    }

    /// Samples of the last forward pass.
    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Float offsets into the grid table read for sample `s` at `level` by the last forward.
    pub fn corner_offsets(&self, level: usize, s: usize) -> &[u32] {
        assert!(
            self.keeps_every_level,
            "an inference cache keeps no level's corners for later"
        );
        let b = (level * self.capacity + s) * CORNERS;
        &self.offs[b..b + CORNERS]
    }
}

/// Cell and fractional position of `x` at a level, exactly as tcnn (`fmaf(scale, x, 0.5)`,
/// `(uint)(int)floor`).
#[inline(always)]
pub fn cell_of(level: &LevelInfo, x: [f32; 3]) -> ([u32; 3], [f32; 3]) {
    let mut cell = [0u32; 3];
    let mut frac = [0f32; 3];
    for d in 0..3 {
        let p = level.scale.mul_add(x[d], 0.5);
        let fl = p.floor();
        cell[d] = fl as i32 as u32;
        frac[d] = p - fl;
    }
    (cell, frac)
}

/// Fills corner offsets and weights of one level for all samples. `T` is the table's
/// element (f32, or the fp16 bits of [`GridTable::F16`]); only its lines are prefetched.
struct LevelCorners<'a, P> {
    /// `*const T` of the table's first element (`()` until [`LevelCorners::over`] gives it).
    table: P,
    level: &'a LevelInfo,
    n_features: u32,
    pos: &'a [[f32; 3]],
    offs: &'a mut [u32],
    weights: &'a mut [f32],
}

impl<'a> LevelCorners<'a, ()> {
    /// The same level's corners, prefetching the lines of `table`.
    fn over<T>(self, table: &[T]) -> LevelCorners<'a, *const T> {
        LevelCorners {
            table: table.as_ptr(),
            level: self.level,
            n_features: self.n_features,
            pos: self.pos,
            offs: self.offs,
            weights: self.weights,
        }
    }
}

impl<T> LevelCorners<'_, *const T> {
    fn fill<K: Kernel, const MAPPED: bool>(self, index: K, map: &[u32]) {
        let LevelCorners {
            table,
            level,
            n_features,
            pos,
            offs,
            weights,
        } = self;
        level_corners::<K, MAPPED, T>(index, map, table, level, n_features, pos, offs, weights);
    }
}

impl<T> WithKernel for LevelCorners<'_, *const T> {
    type Output = ();

    fn run<K: Kernel>(self, index: K) {
        self.fill::<K, false>(index, &[])
    }

    /// Every base entry first (prefetching its line of the map), then the map: looking each
    /// corner up as it is made stalled the corner pass on a miss per corner (stealth's
    /// occupancy updates ran at a third of a keyed index's speed).
    fn run_tabled<K: Kernel>(self, base: K, map: &[u32]) {
        self.fill::<K, true>(base, map)
    }
}

/// The kernel's corners as a call of its own (direct, compiled per kind of index), as the
/// trait object's call was: inlined into the sample loop, the corners come out as scalars
/// and LLVM no longer vectorises the range and offset pass over them (+7 % instructions in
/// `forward`, callgrind).
#[inline(never)]
fn corners_apart<K: Kernel>(index: &K, cell: [u32; 3], out: &mut [u32; CORNERS]) {
    index.corners(cell, out)
}

/// One level's corners, compiled once per kind of index (no dispatch in the sample loop).
/// The slices are arguments, not fields of [`LevelCorners`], on purpose: LLVM knows that
/// reference arguments do not alias, but not references inside a struct, and without that it
/// reloads the level's size and offset after every store and stops vectorising the corner
/// pass (+10 % instructions in `forward`, callgrind).
/// With `MAPPED`, `index` is a level's base arithmetic and `map` the table after it: the
/// first pass keeps the base entries (and prefetches their map lines), a second maps them.
#[allow(clippy::too_many_arguments)]
fn level_corners<K: Kernel, const MAPPED: bool, T>(
    index: K,
    map: &[u32],
    table: *const T,
    level: &LevelInfo,
    n_features: u32,
    pos: &[[f32; 3]],
    offs: &mut [u32],
    weights: &mut [f32],
) {
    let mut bad = false;
    for (s, p) in pos.iter().enumerate() {
        let (cell, frac) = cell_of(level, *p);
        let mut e = [0u32; CORNERS];
        corners_apart(&index, cell, &mut e);
        let o = &mut offs[s * CORNERS..(s + 1) * CORNERS];
        if MAPPED {
            o.copy_from_slice(&e);
            for &ec in &e {
                prefetch(map.as_ptr().wrapping_add(ec as usize));
            }
        } else {
            for c in 0..CORNERS {
                bad |= e[c] >= level.size;
                o[c] = level.offset.wrapping_add(e[c]).wrapping_mul(n_features);
            }
            if PREFETCH_IN_CORNERS {
                for &oc in o.iter() {
                    prefetch(table.wrapping_add(oc as usize));
                }
            }
        }
        let wx = [1.0 - frac[0], frac[0]];
        let wy = [1.0 - frac[1], frac[1]];
        let wz = [1.0 - frac[2], frac[2]];
        let w = &mut weights[s * CORNERS..(s + 1) * CORNERS];
        for c in 0..CORNERS {
            w[c] = wx[c & 1] * wy[(c >> 1) & 1] * wz[c >> 2];
        }
    }
    if MAPPED {
        for o in offs.iter_mut() {
            let e = table_lookup(map, *o);
            bad |= e >= level.size;
            *o = level.offset.wrapping_add(e).wrapping_mul(n_features);
            prefetch(table.wrapping_add(*o as usize));
        }
    }
    // An index outside its level would read another level's (or no) entry: refuse, since
    // the gather below relies on the offsets being in range.
    assert!(
        !bad,
        "LevelIndex of level {} returned an entry >= level size {}",
        level.level, level.size
    );
}

fn gather<const F: usize>(
    table: &[f32],
    offs: &[u32],
    weights: &[f32],
    n: usize,
    enc: &mut [f32],
    ld: usize,
) {
    let tp = table.as_ptr();
    for s in 0..n {
        if !PREFETCH_IN_CORNERS && s + PREFETCH_AHEAD < n {
            let ahead = &offs[(s + PREFETCH_AHEAD) * CORNERS..(s + PREFETCH_AHEAD + 1) * CORNERS];
            for &o in ahead {
                prefetch(tp.wrapping_add(o as usize));
            }
        }
        let o = &offs[s * CORNERS..(s + 1) * CORNERS];
        let w = &weights[s * CORNERS..(s + 1) * CORNERS];
        let mut acc = [0f32; F];
        for c in 0..CORNERS {
            let base = o[c] as usize;
            debug_assert!(base + F <= table.len());
            // SAFETY: LevelCorners checked entry < level size, so base + F <= table.len()
            // (the table holds n_entries·F floats; checked in `forward`).
            let v = unsafe { table.get_unchecked(base..base + F) };
            for f in 0..F {
                acc[f] = w[c].mul_add(v[f], acc[f]);
            }
        }
        for f in 0..F {
            enc[f * ld + s] = acc[f];
        }
    }
}

/// [`gather`] for two features a corner, the paper's: each corner's pair is one 8-byte load
/// into the low half of a vector, and one fused multiply-add takes both features, in the
/// same order as `gather::<2>` (so the same bits). Left to itself LLVM vectorises
/// `gather::<2>` across samples with two hardware gathers a corner, one per feature, each
/// fetching the same line; on the AMD EPYC that builds with AVX-512 this took 11 % off a
/// fox-colmap view's rendering (benchmarks/engine.md, "Why an unbounded view is slow").
fn gather_pairs(
    table: &[f32],
    offs: &[u32],
    weights: &[f32],
    n: usize,
    enc: &mut [f32],
    ld: usize,
) {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma"))]
    {
        use core::arch::x86_64::*;
        let tp = table.as_ptr();
        let (e0, e1) = enc.split_at_mut(ld);
        for s in 0..n {
            let o = &offs[s * CORNERS..(s + 1) * CORNERS];
            let w = &weights[s * CORNERS..(s + 1) * CORNERS];
            // SAFETY: LevelCorners checked entry < level size, so o[c] + 2 <= table.len();
            // the load reads exactly those 8 bytes (unaligned allowed); fma is enabled.
            unsafe {
                let mut acc = _mm_setzero_ps();
                for c in 0..CORNERS {
                    debug_assert!(o[c] as usize + 2 <= table.len());
                    let v = _mm_castpd_ps(_mm_load_sd(tp.add(o[c] as usize) as *const f64));
                    acc = _mm_fmadd_ps(_mm_set1_ps(w[c]), v, acc);
                }
                e0[s] = _mm_cvtss_f32(acc);
                e1[s] = _mm_cvtss_f32(_mm_shuffle_ps::<1>(acc, acc));
            }
        }
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "fma")))]
    gather::<2>(table, offs, weights, n, enc, ld);
}

/// [`gather`] over fp16 bits: each feature widened to f32 (exactly) and taken in the same
/// order, so over a table of fp16 values it gives `gather`'s bits.
fn gather_half<const F: usize>(
    table: &[u16],
    offs: &[u32],
    weights: &[f32],
    n: usize,
    enc: &mut [f32],
    ld: usize,
) {
    for s in 0..n {
        let o = &offs[s * CORNERS..(s + 1) * CORNERS];
        let w = &weights[s * CORNERS..(s + 1) * CORNERS];
        let mut acc = [0f32; F];
        for c in 0..CORNERS {
            let base = o[c] as usize;
            let v = &table[base..base + F];
            for f in 0..F {
                acc[f] = w[c].mul_add(half::f16::from_bits(v[f]).to_f32(), acc[f]);
            }
        }
        for f in 0..F {
            enc[f * ld + s] = acc[f];
        }
    }
}

/// [`gather_pairs`] over fp16 bits: a corner's pair is one 4-byte load, widened by the
/// hardware's converter (exact), then the same fused multiply-add: the same bits as
/// `gather_pairs` over the widened table, from half the bytes.
fn gather_pairs_half(
    table: &[u16],
    offs: &[u32],
    weights: &[f32],
    n: usize,
    enc: &mut [f32],
    ld: usize,
) {
    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "fma",
        target_feature = "f16c"
    ))]
    {
        use core::arch::x86_64::*;
        let tp = table.as_ptr();
        let (e0, e1) = enc.split_at_mut(ld);
        for s in 0..n {
            let o = &offs[s * CORNERS..(s + 1) * CORNERS];
            let w = &weights[s * CORNERS..(s + 1) * CORNERS];
            // SAFETY: LevelCorners checked entry < level size, so o[c] + 2 <= table.len()
            // (checked in `forward`); the load reads exactly those 4 bytes, unaligned;
            // fma and f16c are enabled.
            unsafe {
                let mut acc = _mm_setzero_ps();
                for c in 0..CORNERS {
                    debug_assert!(o[c] as usize + 2 <= table.len());
                    let bits = (tp.add(o[c] as usize) as *const u32).read_unaligned();
                    let v = _mm_cvtph_ps(_mm_cvtsi32_si128(bits as i32));
                    acc = _mm_fmadd_ps(_mm_set1_ps(w[c]), v, acc);
                }
                e0[s] = _mm_cvtss_f32(acc);
                e1[s] = _mm_cvtss_f32(_mm_shuffle_ps::<1>(acc, acc));
            }
        }
    }
    #[cfg(not(all(
        target_arch = "x86_64",
        target_feature = "fma",
        target_feature = "f16c"
    )))]
    gather_half::<2>(table, offs, weights, n, enc, ld);
}

/// `next_level` holds the next level's corner offsets: their gradient lines are prefetched
/// one level ahead (a whole level's lines fit in L2), which overlaps the scatter's misses far
/// better than a few samples ahead.
fn scatter<const F: usize>(
    grad: &mut [f32],
    offs: &[u32],
    weights: &[f32],
    n: usize,
    d_enc: &[f32],
    ld: usize,
    next_level: Option<&[u32]>,
) {
    let gp = grad.as_ptr();
    for s in 0..n {
        if let Some(next) = next_level {
            for &o in &next[s * CORNERS..(s + 1) * CORNERS] {
                prefetch(gp.wrapping_add(o as usize));
            }
        } else if s + PREFETCH_AHEAD < n {
            let ahead = &offs[(s + PREFETCH_AHEAD) * CORNERS..(s + PREFETCH_AHEAD + 1) * CORNERS];
            for &o in ahead {
                prefetch(gp.wrapping_add(o as usize));
            }
        }
        let mut g = [0f32; F];
        for f in 0..F {
            g[f] = d_enc[f * ld + s];
        }
        let o = &offs[s * CORNERS..(s + 1) * CORNERS];
        let w = &weights[s * CORNERS..(s + 1) * CORNERS];
        for c in 0..CORNERS {
            let base = o[c] as usize;
            debug_assert!(base + F <= grad.len());
            // SAFETY: as in `gather`; grad has the table's length (checked in `backward`).
            let v = unsafe { grad.get_unchecked_mut(base..base + F) };
            for f in 0..F {
                v[f] = w[c].mul_add(g[f], v[f]);
            }
        }
    }
}

/// The grid block of the parameters as [`forward`] reads it.
#[derive(Clone, Copy, Debug)]
pub enum GridTable<'a> {
    /// The trainer's f32 table.
    F32(&'a [f32]),
    /// fp16 bits of a table whose every value is an fp16 (a model read from its file, which
    /// stores fp16): the same encoding from half the memory, and a view's gathers are bound
    /// by memory (benchmarks/engine.md, "The grid read as the file stores it").
    F16(&'a [u16]),
}

impl GridTable<'_> {
    fn len(&self) -> usize {
        match self {
            GridTable::F32(t) => t.len(),
            GridTable::F16(t) => t.len(),
        }
    }
}

/// The fp16 bits of `table` if every value is an fp16 (so [`GridTable::F16`] encodes to the
/// same bits as the f32 table), else `None`.
pub fn exact_half_table(table: &[f32]) -> Option<Vec<u16>> {
    let mut out = crate::pages::with_capacity(table.len());
    for &v in table {
        let h = half::f16::from_f32(v);
        if h.to_f32().to_bits() != v.to_bits() {
            return None;
        }
        out.push(h.to_bits());
    }
    Some(out)
}

/// Encodes `pos` (in [0,1]^3) into `enc` (feature-major, leading dimension `ld`) and keeps
/// the corners in `cache` for [`backward`]. `table` is the grid block of the parameters.
pub fn forward<'t>(
    layout: &GridLayout,
    table: impl Into<GridTable<'t>>,
    indices: &LevelIndices,
    pos: &[[f32; 3]],
    cache: &mut GridCache,
    enc: &mut [f32],
    ld: usize,
) {
    let table = table.into();
    let n = pos.len();
    let nl = layout.levels.len();
    let nf = layout.config.n_features as usize;
    assert_eq!(table.len(), layout.n_params(), "grid table length");
    assert_eq!(indices.len(), nl, "one LevelIndex per level");
    assert!(n <= cache.capacity && n <= ld && enc.len() >= nl * nf * ld);
    assert!(
        !cache.keeps_every_level || cache.slots == nl,
        "cache of another layout"
    );
    cache.n = n;
    let cap = cache.capacity;
    for (l, level) in layout.levels.iter().enumerate() {
        let k = cache.slot(l);
        let offs = &mut cache.offs[k * cap * CORNERS..(k * cap + n) * CORNERS];
        let weights = &mut cache.weights[k * cap * CORNERS..(k * cap + n) * CORNERS];
        let out = &mut enc[l * nf * ld..(l + 1) * nf * ld];
        let corners = LevelCorners {
            table: (),
            level,
            n_features: nf as u32,
            pos,
            offs: &mut *offs,
            weights: &mut *weights,
        };
        match table {
            GridTable::F32(t) => indices[l].with_kernel(corners.over(t)),
            GridTable::F16(t) => indices[l].with_kernel(corners.over(t)),
        }
        match (table, nf) {
            (GridTable::F32(t), 1) => gather::<1>(t, offs, weights, n, out, ld),
            (GridTable::F32(t), 2) => gather_pairs(t, offs, weights, n, out, ld),
            (GridTable::F32(t), 4) => gather::<4>(t, offs, weights, n, out, ld),
            (GridTable::F32(t), 8) => gather::<8>(t, offs, weights, n, out, ld),
            (GridTable::F16(t), 1) => gather_half::<1>(t, offs, weights, n, out, ld),
            (GridTable::F16(t), 2) => gather_pairs_half(t, offs, weights, n, out, ld),
            (GridTable::F16(t), 4) => gather_half::<4>(t, offs, weights, n, out, ld),
            (GridTable::F16(t), 8) => gather_half::<8>(t, offs, weights, n, out, ld),
            _ => unreachable!("GridConfig::validate allows F in {{1, 2, 4, 8}}"),
        }
    }
}

impl<'a> From<&'a [f32]> for GridTable<'a> {
    fn from(t: &'a [f32]) -> Self {
        GridTable::F32(t)
    }
}

impl<'a> From<&'a Vec<f32>> for GridTable<'a> {
    fn from(t: &'a Vec<f32>) -> Self {
        GridTable::F32(t)
    }
}

/// Scatter-adds `weight · dL/d(enc)` into `grad_table` at exactly the entries the last
/// [`forward`] on `cache` read. Entries it did not read are not written.
pub fn backward(
    layout: &GridLayout,
    cache: &GridCache,
    d_enc: &[f32],
    ld: usize,
    grad_table: &mut [f32],
) {
    let n = cache.n;
    let nl = layout.levels.len();
    let nf = layout.config.n_features as usize;
    assert_eq!(grad_table.len(), layout.n_params(), "grid gradient length");
    assert!(n <= ld && d_enc.len() >= nl * nf * ld);
    assert!(
        cache.keeps_every_level && cache.slots == nl,
        "backward needs a cache that keeps every level's corners"
    );
    let cap = cache.capacity;
    for l in 0..nl {
        let offs = &cache.offs[l * cap * CORNERS..(l * cap + n) * CORNERS];
        let weights = &cache.weights[l * cap * CORNERS..(l * cap + n) * CORNERS];
        let g = &d_enc[l * nf * ld..(l + 1) * nf * ld];
        let next = (PREFETCH_NEXT_LEVEL && l + 1 < nl)
            .then(|| &cache.offs[(l + 1) * cap * CORNERS..((l + 1) * cap + n) * CORNERS]);
        match nf {
            1 => scatter::<1>(grad_table, offs, weights, n, g, ld, next),
            2 => scatter::<2>(grad_table, offs, weights, n, g, ld, next),
            4 => scatter::<4>(grad_table, offs, weights, n, g, ld, next),
            8 => scatter::<8>(grad_table, offs, weights, n, g, ld, next),
            _ => unreachable!("GridConfig::validate allows F in {{1, 2, 4, 8}}"),
        }
    }
}

/// ADDS dL/d(pos) of every sample of the last [`forward`] on `cache` into `d_pos`, from
/// `d_enc` = dL/d(enc) as [`backward`] takes it: at each level the slope of the trilinear
/// weights along each axis (scaled by the level's resolution) against the corners' values
/// weighted by the features' gradients. The table is read at the cached corners, so it must
/// be the table `forward` read. What camera refinement needs: a ray's origin and direction
/// move every sample on it.
pub fn position_gradient(
    layout: &GridLayout,
    table: &[f32],
    cache: &GridCache,
    pos: &[[f32; 3]],
    d_enc: &[f32],
    ld: usize,
    d_pos: &mut [[f32; 3]],
) {
    let n = cache.n;
    let nf = layout.config.n_features as usize;
    assert_eq!(table.len(), layout.n_params(), "grid table length");
    assert!(
        pos.len() == n && d_pos.len() >= n,
        "one position per cached sample"
    );
    assert!(n <= ld && d_enc.len() >= layout.levels.len() * nf * ld);
    assert!(
        cache.keeps_every_level,
        "the position gradient needs a cache that keeps every level's corners"
    );
    let cap = cache.capacity;
    let tp = table.as_ptr();
    for (l, level) in layout.levels.iter().enumerate() {
        let offs = &cache.offs[l * cap * CORNERS..(l * cap + n) * CORNERS];
        let g = &d_enc[l * nf * ld..(l + 1) * nf * ld];
        for s in 0..n {
            // The forward's lines are long gone from L1 by now: fetch ahead, as it did.
            if s + PREFETCH_AHEAD < n {
                let at = (s + PREFETCH_AHEAD) * CORNERS;
                for &o in &offs[at..at + CORNERS] {
                    prefetch(tp.wrapping_add(o as usize));
                }
            }
            let (_, frac) = cell_of(level, pos[s]);
            // Each corner's value against the features' gradients.
            let mut v = [0f32; CORNERS];
            for (c, vc) in v.iter_mut().enumerate() {
                let base = offs[s * CORNERS + c] as usize;
                for f in 0..nf {
                    *vc += g[f * ld + s] * table[base + f];
                }
            }
            // Corner c = x + 2y + 4z. Along x the weight's slope is ±1 times the other two
            // axes' weights, so the slope is the y-z-weighted sum of the x differences.
            let wx = [1.0 - frac[0], frac[0]];
            let wy = [1.0 - frac[1], frac[1]];
            let wz = [1.0 - frac[2], frac[2]];
            let mut slope = [0f32; 3];
            for a in 0..2 {
                for b in 0..2 {
                    slope[0] += wy[a] * wz[b] * (v[1 + 2 * a + 4 * b] - v[2 * a + 4 * b]);
                    slope[1] += wx[a] * wz[b] * (v[a + 2 + 4 * b] - v[a + 4 * b]);
                    slope[2] += wx[a] * wy[b] * (v[a + 2 * b + 4] - v[a + 2 * b]);
                }
            }
            for d in 0..3 {
                d_pos[s][d] += level.scale * slope[d];
            }
        }
    }
}

/// Straightforward per-sample encoding through `LevelIndex::index` (not a kernel), the
/// reference the fast path is tested against.
#[cfg(test)]
pub(crate) fn naive_encode(
    layout: &GridLayout,
    table: &[f32],
    indices: &LevelIndices,
    x: [f32; 3],
) -> Vec<f32> {
    let nf = layout.config.n_features as usize;
    let mut out = vec![0f32; layout.levels.len() * nf];
    for (l, level) in layout.levels.iter().enumerate() {
        let (cell, frac) = cell_of(level, x);
        for c in 0..8u32 {
            let mut w = 1.0f32;
            let mut v = [0u32; 3];
            for d in 0..3 {
                let bit = (c >> d) & 1;
                v[d] = cell[d].wrapping_add(bit);
                w *= if bit == 1 { frac[d] } else { 1.0 - frac[d] };
            }
            let e = indices[l].index(v[0], v[1], v[2]);
            let base = (level.offset + e) as usize * nf;
            for f in 0..nf {
                out[l * nf + f] += w * table[base + f];
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::index::{IndexFn, LevelIndex, reference_indices};
    use crate::encoding::layout::GridConfig;
    use crate::rng::Pcg32;

    fn small() -> GridLayout {
        GridLayout::new(
            GridConfig {
                n_levels: 4,
                n_features: 2,
                log2_hashmap_size: 10,
                base_resolution: 4,
            },
            1,
        )
        .unwrap()
    }

    fn random_table(layout: &GridLayout, seed: u64) -> Vec<f32> {
        let mut r = Pcg32::new(seed, 7);
        (0..layout.n_params())
            .map(|_| r.next_f32() * 2.0 - 1.0)
            .collect()
    }

    fn random_pos(n: usize, seed: u64) -> Vec<[f32; 3]> {
        let mut r = Pcg32::new(seed, 9);
        (0..n)
            .map(|_| [r.next_f32(), r.next_f32(), r.next_f32()])
            .collect()
    }

    #[test]
    fn small_config_has_dense_and_hashed_levels() {
        let g = small();
        assert!(g.levels.iter().any(|l| l.dense));
        assert!(g.levels.iter().any(|l| !l.dense));
    }

    #[test]
    fn fast_forward_matches_naive() {
        for cfg in [
            small().config,
            GridConfig::default(),
            GridConfig::base_json_2023(),
            GridConfig {
                n_levels: 3,
                n_features: 1,
                log2_hashmap_size: 12,
                base_resolution: 8,
            },
        ] {
            let g = GridLayout::new(cfg, 1).unwrap();
            let table = random_table(&g, 1);
            // Include the faces of the cube, where the upper corner wraps.
            let mut pos = random_pos(61, 2);
            pos.push([0.0, 0.0, 0.0]);
            pos.push([1.0, 1.0, 1.0]);
            pos.push([1.0, 0.0, 0.5]);
            let n = pos.len();
            let ld = 70;
            let width = g.config.n_output_dims();
            // The reference index, and indices with a table after them (the corner pass
            // that maps every base entry after the fact, `WithKernel::run_tabled`).
            for (name, idx) in [
                ("reference", reference_indices(&g)),
                ("reference + map", mapped_indices(&g, IndexFn::Reference, 3)),
                (
                    "primes + map",
                    mapped_indices(&g, IndexFn::Primes([7, 11, 13]), 4),
                ),
            ] {
                let mut enc = vec![0f32; width * ld];
                let mut cache = GridCache::new(&g, 80);
                forward(&g, &table, &idx, &pos, &mut cache, &mut enc, ld);
                for s in 0..n {
                    let want = naive_encode(&g, &table, &idx, pos[s]);
                    for j in 0..width {
                        let got = enc[j * ld + s];
                        assert!(
                            (got - want[j]).abs() <= 1e-5 * (1.0 + want[j].abs()),
                            "{name}, cfg {cfg:?} s {s} j {j}: {got} vs {}",
                            want[j]
                        );
                    }
                }
            }
        }
    }

    /// The paired loads give the generic gather's bits (the same fused multiply-adds in the
    /// same order), so rendering and training are unchanged by them, bit for bit.
    #[test]
    fn paired_gather_is_the_generic_gather_to_the_bit() {
        let g = GridLayout::new(GridConfig::default(), 1).unwrap();
        let table = random_table(&g, 3);
        let pos = random_pos(300, 4);
        let (n, ld) = (pos.len(), 304);
        let mut cache = GridCache::new(&g, n);
        let mut enc = vec![0f32; g.config.n_output_dims() * ld];
        forward(
            &g,
            &table,
            &reference_indices(&g),
            &pos,
            &mut cache,
            &mut enc,
            ld,
        );
        for l in 0..g.levels.len() {
            let offs = &cache.offs[l * n * CORNERS..(l + 1) * n * CORNERS];
            let weights = &cache.weights[l * n * CORNERS..(l + 1) * n * CORNERS];
            let mut generic = vec![f32::NAN; 2 * ld];
            let mut paired = vec![f32::NAN; 2 * ld];
            gather::<2>(&table, offs, weights, n, &mut generic, ld);
            gather_pairs(&table, offs, weights, n, &mut paired, ld);
            for f in 0..2 {
                for s in 0..n {
                    let (a, b) = (generic[f * ld + s], paired[f * ld + s]);
                    assert_eq!(a.to_bits(), b.to_bits(), "level {l} feature {f} sample {s}");
                    assert_eq!(b.to_bits(), enc[(2 * l + f) * ld + s].to_bits());
                }
            }
        }
    }

    /// A random table whose every value is an fp16, ties, subnormals and zeros of both signs
    /// included (what a model read from its file holds).
    fn fp16_table(layout: &GridLayout, seed: u64) -> Vec<f32> {
        let mut r = Pcg32::new(seed, 11);
        (0..layout.n_params())
            .map(|i| match i % 7 {
                0 => half::f16::from_bits(r.next_u32() as u16 & 0x83ff).to_f32(), // subnormal
                1 => [0.0, -0.0][i % 2],
                _ => half::f16::from_f32(r.next_f32() * 4.0 - 2.0).to_f32(),
            })
            .collect()
    }

    #[test]
    fn the_fp16_table_encodes_to_the_f32_tables_bits() {
        for n_features in [1, 2, 4, 8] {
            let g = GridLayout::new(
                GridConfig {
                    n_features,
                    ..GridConfig::default()
                },
                1,
            )
            .unwrap();
            let table = fp16_table(&g, n_features as u64);
            let bits = exact_half_table(&table).expect("every value is an fp16");
            let pos = random_pos(300, 4);
            let (n, ld) = (pos.len(), 304);
            let idx = reference_indices(&g);
            let mut enc32 = vec![f32::NAN; g.config.n_output_dims() * ld];
            let mut enc16 = enc32.clone();
            forward(
                &g,
                &table,
                &idx,
                &pos,
                &mut GridCache::new(&g, n),
                &mut enc32,
                ld,
            );
            let mut cache = GridCache::new(&g, n);
            forward(
                &g,
                GridTable::F16(&bits),
                &idx,
                &pos,
                &mut cache,
                &mut enc16,
                ld,
            );
            for (k, (a, b)) in enc32.iter().zip(&enc16).enumerate() {
                if k % ld < n {
                    assert_eq!(a.to_bits(), b.to_bits(), "F = {n_features}, element {k}");
                }
            }
            // The fp16 forward keeps the same corners, so a backward can follow it.
            assert!(cache.keeps_every_level() && cache.len() == n);
        }
    }

    #[test]
    fn a_table_that_is_not_all_fp16_has_no_fp16_copy() {
        let g = small();
        let mut table = fp16_table(&g, 1);
        assert!(exact_half_table(&table).is_some());
        // One value one f32 ulp off an fp16: the copy would not encode to the same bits.
        let last = table.len() - 1;
        table[last] = f32::from_bits(half::f16::from_f32(0.75).to_f32().to_bits() + 1);
        assert!(exact_half_table(&table).is_none());
        // Infinities are fp16s too.
        table[last] = f32::INFINITY;
        assert!(exact_half_table(&table).is_some());
    }

    #[test]
    fn an_inference_cache_encodes_the_same_and_refuses_a_backward() {
        let g = GridLayout::new(GridConfig::default(), 1).unwrap();
        let table = random_table(&g, 5);
        let pos = random_pos(200, 6);
        let (n, ld) = (pos.len(), 200);
        let idx = mapped_indices(&g, IndexFn::Reference, 8);
        let mut full = vec![f32::NAN; g.config.n_output_dims() * ld];
        let mut once = full.clone();
        forward(
            &g,
            &table,
            &idx,
            &pos,
            &mut GridCache::new(&g, n),
            &mut full,
            ld,
        );
        let mut cache = GridCache::for_inference(n);
        forward(&g, &table, &idx, &pos, &mut cache, &mut once, ld);
        assert!(
            full.iter()
                .zip(&once)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        assert!(!cache.keeps_every_level());
        let refused = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let mut grad = vec![0f32; g.n_params()];
            backward(&g, &cache, &full, ld, &mut grad);
        }));
        assert!(
            refused.is_err(),
            "a backward read corners the cache never kept"
        );
    }

    #[test]
    fn a_one_level_layouts_cache_keeps_its_level_for_a_backward() {
        let g = GridLayout::new(
            GridConfig {
                n_levels: 1,
                ..GridConfig::default()
            },
            1,
        )
        .unwrap();
        let table = random_table(&g, 9);
        let pos = random_pos(50, 10);
        let ld = pos.len();
        let mut enc = vec![0f32; g.config.n_output_dims() * ld];
        let mut cache = GridCache::new(&g, ld);
        forward(
            &g,
            &table,
            &reference_indices(&g),
            &pos,
            &mut cache,
            &mut enc,
            ld,
        );
        assert!(cache.keeps_every_level());
        assert_eq!(cache.corner_offsets(0, 0).len(), CORNERS);
        let mut grad = vec![0f32; g.n_params()];
        backward(&g, &cache, &enc, ld, &mut grad);
        assert!(grad.iter().any(|&v| v != 0.0));
    }

    /// `base` on every level, followed by a random map into the level (not a permutation:
    /// several entries share a target, as a stealth confinement map's do).
    fn mapped_indices(g: &GridLayout, base: IndexFn, seed: u64) -> LevelIndices {
        let mut r = Pcg32::new(seed, 5);
        g.levels
            .iter()
            .map(|lv| {
                let map: Vec<u32> = (0..lv.size).map(|_| r.next_u32() % lv.size).collect();
                LevelIndex::new(lv, base).with_table(map)
            })
            .collect()
    }

    /// The encoding is linear in the table, so central differences have no truncation error;
    /// only f32 rounding of O(1) outputs (~1e-7) divided by 2h = 0.2 remains, far below the
    /// 1e-4 tolerance.
    #[test]
    fn gradient_matches_finite_differences() {
        let g = small();
        let mut table = random_table(&g, 3);
        let idx = reference_indices(&g);
        let pos = random_pos(23, 4);
        let n = pos.len();
        let width = g.config.n_output_dims();
        let ld = 32;
        let mut r = Pcg32::new(5, 5);
        let coef: Vec<f32> = (0..width * ld).map(|_| r.next_f32() * 2.0 - 1.0).collect();
        let mut cache = GridCache::new(&g, ld);
        let mut enc = vec![0f32; width * ld];
        let mut loss = |table: &[f32], cache: &mut GridCache| -> f64 {
            forward(&g, table, &idx, &pos, cache, &mut enc, ld);
            let mut l = 0f64;
            for j in 0..width {
                for s in 0..n {
                    l += coef[j * ld + s] as f64 * enc[j * ld + s] as f64;
                }
            }
            l
        };
        loss(&table, &mut cache);
        let mut grad = vec![0f32; g.n_params()];
        backward(&g, &cache, &coef, ld, &mut grad);

        // Every touched entry of every level, plus untouched ones.
        let mut touched = vec![false; g.n_params()];
        for l in 0..g.levels.len() {
            for s in 0..n {
                for &o in cache.corner_offsets(l, s) {
                    touched[o as usize] = true;
                    touched[o as usize + 1] = true;
                }
            }
        }
        let h = 0.1f32;
        let mut checked = [0usize; 2];
        for p in 0..g.n_params() {
            if !touched[p] {
                assert_eq!(grad[p], 0.0, "untouched entry {p} got gradient");
                assert_eq!(grad[p].to_bits(), 0, "untouched entry {p} is -0");
                if p % 97 != 0 {
                    continue;
                }
            }
            let orig = table[p];
            table[p] = orig + h;
            let lp = loss(&table, &mut cache);
            table[p] = orig - h;
            let lm = loss(&table, &mut cache);
            table[p] = orig;
            let fd = (lp - lm) / (2.0 * h as f64);
            assert!(
                (fd - grad[p] as f64).abs() <= 1e-4 * (1.0 + fd.abs()),
                "param {p}: fd {fd} vs analytic {}",
                grad[p]
            );
            let lvl = g
                .levels
                .iter()
                .rposition(|lv| (lv.offset * 2) as usize <= p)
                .unwrap();
            checked[g.levels[lvl].dense as usize] += touched[p] as usize;
        }
        assert!(checked[0] > 50 && checked[1] > 50, "checked {checked:?}");
    }

    #[test]
    #[should_panic(expected = "returned an entry >= level size")]
    fn rejects_an_index_outside_its_level() {
        let g = small();
        let table = random_table(&g, 1);
        // Every vertex to u32::MAX, through a table.
        let idx: LevelIndices = reference_indices(&g)
            .into_iter()
            .map(|ix| {
                let n = ix.size as usize;
                ix.with_table(vec![u32::MAX; n])
            })
            .collect();
        let mut cache = GridCache::new(&g, 4);
        let mut enc = vec![0f32; 8 * 4];
        forward(&g, &table, &idx, &random_pos(3, 1), &mut cache, &mut enc, 4);
    }

    #[test]
    fn backward_accumulates() {
        let g = small();
        let table = random_table(&g, 8);
        let idx = reference_indices(&g);
        let pos = random_pos(10, 8);
        let width = g.config.n_output_dims();
        let ld = 10;
        let d = vec![0.5f32; width * ld];
        let mut cache = GridCache::new(&g, ld);
        let mut enc = vec![0f32; width * ld];
        forward(&g, &table, &idx, &pos, &mut cache, &mut enc, ld);
        let mut once = vec![0f32; g.n_params()];
        backward(&g, &cache, &d, ld, &mut once);
        let mut twice = once.clone();
        backward(&g, &cache, &d, ld, &mut twice);
        for p in 0..once.len() {
            assert!((twice[p] - 2.0 * once[p]).abs() <= 1e-6 * once[p].abs().max(1.0));
        }
    }
}
