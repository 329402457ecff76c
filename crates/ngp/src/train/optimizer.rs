//! tiny-cuda-nn's optimizer stack for NeRF: Ema(0.95) ∘ ExponentialDecay ∘ Adam (spec §3.4).
//!
//! - Adam β1 0.9, β2 0.99, ε 1e-15, lr 1e-2, per-parameter step counters for bias correction.
//! - L2 1e-6 on the MLP ("matrix") parameters only.
//! - Grid ("non-matrix") parameters whose gradient is exactly 0 are skipped entirely.
//! - lr × 0.33 at step 20 000 and every 10 000 steps after.
//! - A debiased EMA of the weights (decay 0.95) is what renders and what snapshots store.
//!
//! Gradients arrive as one buffer per worker thread; the update sums them, zeroes them and
//! updates every parameter in one parallel pass over memory.

use crate::pages;
use rayon::prelude::*;

#[derive(Clone, Copy, Debug)]
pub struct OptimizerConfig {
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    pub l2_reg: f32,
    pub decay_start: u32,
    pub decay_interval: u32,
    pub decay_base: f32,
    pub ema_decay: f32,
}

impl Default for OptimizerConfig {
    fn default() -> Self {
        OptimizerConfig {
            lr: 1e-2,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-15,
            l2_reg: 1e-6,
            decay_start: 20000,
            decay_interval: 10000,
            decay_base: 0.33,
            ema_decay: 0.95,
        }
    }
}

impl OptimizerConfig {
    /// Learning rate of the update after `step` updates (ExponentialDecay).
    pub fn learning_rate(&self, step: u32) -> f32 {
        let mut lr = self.lr;
        if step >= self.decay_start {
            let k = (step - self.decay_start) / self.decay_interval + 1;
            lr *= self.decay_base.powi(k as i32);
        }
        lr
    }

    /// Adam's bias correction `sqrt(1 − β2^t) / (1 − β1^t)` of a parameter's t-th update,
    /// in f64 then rounded once, so that every backend applies the same f32.
    pub fn adam_correction(&self, t: u32) -> f32 {
        let b1 = 1.0 - (self.beta1 as f64).powi(t as i32);
        let b2 = 1.0 - (self.beta2 as f64).powi(t as i32);
        (b2.sqrt() / b1) as f32
    }
}

pub struct Optimizer {
    pub config: OptimizerConfig,
    /// Parameters below this index are MLP weights (L2, never skipped).
    n_matrix: usize,
    m: Vec<f32>,
    v: Vec<f32>,
    steps: Vec<u32>,
    ema: Vec<f32>,
    /// Per group of [`GROUP`] parameters: the step its EMA was last brought up to date.
    /// Untouched groups keep constant weights, so their EMA catches up lazily in closed form.
    ema_step: Vec<u32>,
    /// Global step count (number of `step` calls).
    pub step: u32,
    /// `sqrt(1 − β2^t) / (1 − β1^t)` for t = 0..=step.
    correction: Vec<f32>,
    /// `ema_decay^k` for k = 0..=step.
    decay_pow: Vec<f32>,
}

/// Parameters per touched-bitmap bit: hashed levels scatter a batch over most 64-float
/// lines, so only a fine granularity lets untouched entries be skipped.
pub const GROUP: usize = 4;
/// The most optimizer steps a restored state may have taken (the paper trains 50 000).
pub const MAX_STEPS: u32 = 10_000_000;
const BLOCK: usize = 1 << 14;

/// One block's share of every worker's gradient buffer: each block owns a disjoint range
/// of every buffer, so the blocks run in parallel without building a list of slices a
/// block (which would allocate in the optimizer's hot loop).
struct GradBlock<'a> {
    /// The buffers' base addresses, in worker order (the order the sum is taken in).
    bases: &'a [usize],
    start: usize,
    len: usize,
}

impl GradBlock<'_> {
    /// The sum over workers of parameters `start + i0 ..` (`width` of them, at most
    /// [`GROUP`]; the rest of the lanes 0), each buffer's entries zeroed as they are read.
    #[inline(always)]
    fn take(&mut self, i0: usize, width: usize) -> [f32; GROUP] {
        assert!(width <= GROUP && i0 + width <= self.len);
        let mut g = [0.0f32; GROUP];
        for &base in self.bases {
            // SAFETY: `step` checked that every buffer holds the parameters' count, this
            // block's range lies within it (asserted above), no other block touches it,
            // and `step` holds the buffers mutably borrowed while the blocks run.
            let gb = unsafe {
                std::slice::from_raw_parts_mut((base as *mut f32).add(self.start + i0), width)
            };
            for (gj, x) in g.iter_mut().zip(gb.iter_mut()) {
                *gj += *x;
                *x = 0.0;
            }
        }
        g
    }
}

/// The Adam + EMA update of one group of parameters, `width` of them (a whole group but
/// maybe the last), the first `n_matrix` of them MLP weights: written lane-wise with
/// selects instead of a branch a parameter, so that a whole group's square roots and
/// divisions go in one vector instruction each. Every lane takes the per-parameter
/// order of operations (tiny-cuda-nn's), so either path gives the same bits.
// Lane loops index several arrays in step on purpose: that is what vectorises.
#[allow(clippy::needless_range_loop, clippy::too_many_arguments)]
#[inline(always)]
fn adam_group(
    c: &OptimizerConfig,
    lr: f32,
    correction: &[f32],
    n_matrix: usize,
    g: [f32; GROUP],
    w: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    st: &mut [u32],
    ema: &mut [f32],
) {
    let width = w.len();
    // Lanes past `width` compute on zeros and are never stored.
    let lanes = |x: &[f32]| {
        let mut a = [0.0f32; GROUP];
        a[..width].copy_from_slice(x);
        a
    };
    let (w0, m0, v0, e0) = (lanes(w), lanes(m), lanes(v), lanes(ema));
    let mut st0 = [0u32; GROUP];
    st0[..width].copy_from_slice(st);
    let last = correction.len() - 1;
    let (mut w1, mut m1, mut v1, mut st1, mut e1) = (w0, m0, v0, st0, e0);
    for j in 0..GROUP {
        let is_matrix = j < n_matrix;
        let update = is_matrix || g[j] != 0.0;
        let gj = if is_matrix {
            g[j] + c.l2_reg * w0[j]
        } else {
            g[j]
        };
        let t = st0[j] + 1;
        let mj = c.beta1 * m0[j] + (1.0 - c.beta1) * gj;
        let vj = c.beta2 * v0[j] + (1.0 - c.beta2) * gj * gj;
        // `t` is at most the optimizer's step, the table's last entry (`extend_tables`).
        let lr_eff = lr * correction[(t as usize).min(last)];
        let wj = w0[j] - lr_eff * mj / (vj.sqrt() + c.epsilon);
        if update {
            st1[j] = t;
            m1[j] = mj;
            v1[j] = vj;
            w1[j] = wj;
        }
        e1[j] = c.ema_decay * e0[j] + (1.0 - c.ema_decay) * w1[j];
    }
    w.copy_from_slice(&w1[..width]);
    m.copy_from_slice(&m1[..width]);
    v.copy_from_slice(&v1[..width]);
    st.copy_from_slice(&st1[..width]);
    ema.copy_from_slice(&e1[..width]);
}

/// The positions of the set bits of a bitmap given as 64-bit words, in increasing order.
pub fn set_bits(words: impl Iterator<Item = u64>) -> impl Iterator<Item = usize> {
    words.enumerate().flat_map(|(k, word)| {
        let mut rest = word;
        std::iter::from_fn(move || {
            if rest == 0 {
                return None;
            }
            let b = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            Some(k * 64 + b)
        })
    })
}

/// One bit per [`GROUP`] parameters: which groups a worker's gradient touched.
#[derive(Clone, Debug, Default)]
pub struct Touched {
    bits: Vec<u64>,
}

impl Touched {
    pub fn new(n_params: usize) -> Self {
        Touched {
            bits: vec![0; n_params.div_ceil(GROUP).div_ceil(64)],
        }
    }
    #[inline]
    pub fn mark(&mut self, param: usize) {
        let g = param / GROUP;
        self.bits[g / 64] |= 1 << (g % 64);
    }
    #[inline]
    fn get(&self, group: usize) -> bool {
        self.bits[group / 64] >> (group % 64) & 1 != 0
    }
    /// The marked groups, in increasing order.
    pub fn groups(&self) -> impl Iterator<Item = usize> + '_ {
        set_bits(self.bits.iter().copied())
    }
    /// The groups any of `ts` marked, each once, in increasing order.
    pub fn groups_of_any<'a>(
        ts: impl Iterator<Item = &'a Touched> + Clone + 'a,
    ) -> impl Iterator<Item = usize> + 'a {
        let words = ts.clone().next().map_or(0, |t| t.bits.len());
        set_bits((0..words).map(move |k| ts.clone().fold(0, |a, t| a | t.bits[k])))
    }
    pub fn clear(&mut self) {
        self.bits.fill(0);
    }
    /// The marks, one bit a group (a training state saves them).
    pub fn words(&self) -> &[u64] {
        &self.bits
    }
    pub fn words_mut(&mut self) -> &mut [u64] {
        &mut self.bits
    }
}

impl Optimizer {
    pub fn new(config: OptimizerConfig, n_params: usize, n_matrix: usize) -> Self {
        Optimizer {
            config,
            n_matrix,
            m: pages::zeroed(n_params),
            v: pages::zeroed(n_params),
            steps: pages::zeroed(n_params),
            ema: pages::zeroed(n_params),
            ema_step: vec![0; n_params.div_ceil(GROUP)],
            step: 0,
            correction: vec![0.0],
            decay_pow: vec![1.0],
        }
    }

    /// The bias-correction and decay tables up to the current step (each entry is a
    /// function of its index alone, so a restored optimizer rebuilds the same values).
    fn extend_tables(&mut self) {
        let c = self.config;
        let t = self.step as usize;
        while self.correction.len() <= t {
            let k = self.correction.len() as u32;
            self.correction.push(c.adam_correction(k));
            self.decay_pow
                .push((c.ema_decay as f64).powi(k as i32) as f32);
        }
    }

    /// Everything [`restore`](Self::restore) needs, for a training state
    /// ([`super::state::OptimizerState`], laid out as tiny-cuda-nn serialises its optimizer):
    /// the moments and counts, the debiased EMA that instant-ngp reads, and what an exact
    /// resume needs besides (our EMA accumulators in f32 and the steps each group's was
    /// brought up to). `params` are the training weights.
    pub(super) fn state(&self, params: &[f32]) -> super::state::OptimizerState<'_> {
        use std::borrow::Cow::{Borrowed, Owned};
        super::state::OptimizerState {
            config: self.config,
            step: self.step,
            m: Borrowed(&self.m),
            v: Borrowed(&self.v),
            param_steps: Borrowed(&self.steps),
            published: Owned(self.ema_params(params)),
            ema: Borrowed(&self.ema),
            ema_step: Some(Borrowed(&self.ema_step)),
        }
    }

    /// The groups whose EMA is brought up to date lazily ([`Self::state`]'s `ema_step`).
    pub(super) fn ema_groups(&self) -> usize {
        self.ema_step.len()
    }

    /// Takes back a [`state`](Self::state), read for this optimizer (its lengths checked).
    pub(super) fn restore(&mut self, s: super::state::OptimizerState) {
        self.m.copy_from_slice(&s.m);
        self.v.copy_from_slice(&s.v);
        self.steps.copy_from_slice(&s.param_steps);
        self.ema.copy_from_slice(&s.ema);
        self.ema_step
            .copy_from_slice(s.ema_step.as_deref().expect("read for the CPU"));
        self.step = s.step;
        self.correction.truncate(1);
        self.decay_pow.truncate(1);
        self.extend_tables();
    }

    /// Learning rate in force for the next step (ExponentialDecay).
    pub fn learning_rate(&self) -> f32 {
        self.config.learning_rate(self.step)
    }

    /// One update. `grads` are per-worker gradient buffers (summed in order, then zeroed);
    /// `touched` says which groups of each buffer may be non-zero (`None`: all of them).
    /// Groups no worker touched are skipped entirely (beyond the MLP weights).
    pub fn step(
        &mut self,
        params: &mut [f32],
        grads: &mut [Vec<f32>],
        touched: Option<&[Touched]>,
    ) {
        let c = self.config;
        let lr = self.learning_rate();
        self.step += 1;
        self.extend_tables();
        let step = self.step;
        let correction = &self.correction;
        let decay_pow = &self.decay_pow;
        let n_matrix = self.n_matrix;
        let n = params.len();
        for g in grads.iter() {
            assert_eq!(g.len(), n, "gradient buffer size");
        }
        let bases: Vec<usize> = grads.iter_mut().map(|g| g.as_mut_ptr() as usize).collect();
        params
            .par_chunks_mut(BLOCK)
            .zip(self.m.par_chunks_mut(BLOCK))
            .zip(self.v.par_chunks_mut(BLOCK))
            .zip(self.steps.par_chunks_mut(BLOCK))
            .zip(self.ema.par_chunks_mut(BLOCK))
            .zip(self.ema_step.par_chunks_mut(BLOCK / GROUP))
            .enumerate()
            .for_each(|(b, (((((w, m), v), st), ema), es))| {
                let start = b * BLOCK;
                let len = w.len();
                let mut grads = GradBlock {
                    bases: &bases,
                    start,
                    len,
                };
                for (gi, g0) in (0..len).step_by(GROUP).enumerate() {
                    let group = start / GROUP + gi;
                    let g1 = (g0 + GROUP).min(len);
                    let matrix = start + g0 < n_matrix;
                    let active = matrix || touched.is_none_or(|ts| ts.iter().any(|t| t.get(group)));
                    if !active {
                        continue;
                    }
                    // Bring the EMA up to the previous step: w was constant since es[gi].
                    let lag = (step - 1 - es[gi]) as usize;
                    if lag > 0 {
                        let k = decay_pow[lag];
                        for i in g0..g1 {
                            ema[i] = w[i] + (ema[i] - w[i]) * k;
                        }
                    }
                    es[gi] = step;
                    let n_matrix = n_matrix.saturating_sub(start + g0);
                    let r = g0..g1;
                    let (w, m, v, st, ema) = (
                        &mut w[r.clone()],
                        &mut m[r.clone()],
                        &mut v[r.clone()],
                        &mut st[r.clone()],
                        &mut ema[r],
                    );
                    // The two calls differ only in that the first one's width is a
                    // constant, so that it inlines to straight vector code.
                    if g1 - g0 == GROUP {
                        let g = grads.take(g0, GROUP);
                        adam_group(&c, lr, correction, n_matrix, g, w, m, v, st, ema);
                    } else {
                        let g = grads.take(g0, g1 - g0);
                        adam_group(&c, lr, correction, n_matrix, g, w, m, v, st, ema);
                    }
                }
            });
    }

    /// (first moments, second moments, per-parameter update counts): for comparing
    /// backends.
    pub fn moments(&self) -> (&[f32], &[f32], &[u32]) {
        (&self.m, &self.v, &self.steps)
    }

    /// The debiased EMA of the weights: what renders and what a snapshot stores.
    pub fn ema_params(&self, params: &[f32]) -> Vec<f32> {
        if self.step == 0 {
            return params.to_vec();
        }
        let debias = 1.0 - (self.config.ema_decay as f64).powi(self.step as i32);
        let k = (1.0 / debias) as f32;
        let mut out = vec![0.0f32; params.len()];
        out.par_chunks_mut(GROUP)
            .zip(self.ema.par_chunks(GROUP))
            .zip(params.par_chunks(GROUP))
            .zip(self.ema_step.par_iter())
            .for_each(|(((o, e), w), &es)| {
                let lag = (self.step - es) as usize;
                let d = self.decay_pow[lag];
                for i in 0..o.len() {
                    o[i] = (w[i] + (e[i] - w[i]) * d) * k;
                }
            });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adam_by_hand_and_zero_grad_skip() {
        let cfg = OptimizerConfig {
            l2_reg: 0.0,
            ..Default::default()
        };
        let mut opt = Optimizer::new(cfg, 3, 1);
        let mut w = vec![1.0f32, 2.0, 3.0];
        let mut grads = vec![vec![0.5f32, 0.0, 0.25], vec![0.5f32, 0.0, 0.25]];
        opt.step(&mut w, &mut grads, None);
        // First Adam step moves each parameter by lr·g/|g| = 0.01 against the gradient.
        assert!((w[0] - 0.99).abs() < 1e-6, "{}", w[0]);
        assert_eq!(w[1], 2.0, "zero-gradient grid entry must stay untouched");
        assert!((w[2] - 2.99).abs() < 1e-6);
        assert!(grads.iter().all(|g| g.iter().all(|&x| x == 0.0)));
        assert_eq!(opt.steps, vec![1, 0, 1]);
        // A matrix parameter is updated even with zero gradient (and counts the step).
        let mut grads = vec![vec![0.0f32; 3]];
        opt.step(&mut w, &mut grads, None);
        assert_eq!(opt.steps, vec![2, 0, 1]);
        // EMA debiased after 2 steps: weights near 0.99 → EMA ≈ weights.
        let e = opt.ema_params(&w);
        assert!((e[1] - 2.0).abs() < 1e-5);
        assert!((e[0] - w[0]).abs() < 0.01);
    }

    #[test]
    fn second_step_bias_correction() {
        let cfg = OptimizerConfig {
            l2_reg: 0.0,
            ..Default::default()
        };
        let mut opt = Optimizer::new(cfg, 1, 0);
        let mut w = vec![0.0f32];
        opt.step(&mut w, &mut [vec![1.0]], None);
        opt.step(&mut w, &mut [vec![-1.0]], None);
        // By hand: m2 = 0.9·0.1 − 0.1 = −0.01, v2 = 0.99·0.01 + 0.01 = 0.0199,
        // lr_eff = 0.01·sqrt(1 − 0.99²)/(1 − 0.9²), step = lr_eff·m2/sqrt(v2).
        let lr_eff = 0.01 * (1.0f64 - 0.99f64.powi(2)).sqrt() / (1.0 - 0.81);
        let want = -0.01 - lr_eff * (-0.01) / 0.0199f64.sqrt();
        assert!((w[0] as f64 - want).abs() < 1e-6, "{} vs {want}", w[0]);
    }

    #[test]
    fn touched_groups_and_lazy_ema_match_the_dense_update() {
        // 4 groups; matrix = first 10 params. Worker 0 touches group 2, worker 1 nothing.
        let n = 4 * GROUP;
        let cfg = OptimizerConfig::default();
        let mut dense = Optimizer::new(cfg, n, 10);
        let mut sparse = Optimizer::new(cfg, n, 10);
        let mut wd: Vec<f32> = (0..n).map(|i| (i as f32 * 0.37).sin()).collect();
        let mut ws = wd.clone();
        for step in 0..5 {
            let mut g0 = vec![0.0f32; n];
            for i in [3usize, 2 * GROUP + 5, 2 * GROUP + 6] {
                g0[i] = 0.1 * (step as f32 + 1.0) * if i % 2 == 0 { 1.0 } else { -1.0 };
            }
            let mut t0 = Touched::new(n);
            t0.mark(3);
            t0.mark(2 * GROUP + 5);
            let t1 = Touched::new(n);
            let mut gd = vec![g0.clone(), vec![0.0; n]];
            let mut gs = vec![g0, vec![0.0; n]];
            dense.step(&mut wd, &mut gd, None);
            sparse.step(&mut ws, &mut gs, Some(&[t0, t1]));
            assert!(gs.iter().all(|g| g.iter().all(|&x| x == 0.0)));
        }
        assert_eq!(wd, ws);
        let (ed, es) = (dense.ema_params(&wd), sparse.ema_params(&ws));
        for i in 0..n {
            assert!(
                (ed[i] - es[i]).abs() <= 1e-6 * ed[i].abs().max(1.0),
                "param {i}: {} vs {}",
                ed[i],
                es[i]
            );
        }
    }

    /// `adam_group` against the per-parameter loop written out here, bit for bit: a group
    /// that straddles the MLP weights' end, a partial last group (the same function at a
    /// width under 4), lanes with zero, negative-zero and non-zero gradients from three
    /// workers, over steps enough for the bias correction to change.
    #[test]
    fn whole_groups_update_as_the_per_parameter_loop_does() {
        let (n, n_matrix) = (4 * GROUP + 3, GROUP + 2);
        let c = OptimizerConfig::default();
        let mut opt = Optimizer::new(c, n, n_matrix);
        let mut w: Vec<f32> = (0..n).map(|i| (i as f32 * 0.61).cos()).collect();
        let (mut rw, mut rm, mut rv, mut rst, mut rema) = (
            w.clone(),
            vec![0.0f32; n],
            vec![0.0f32; n],
            vec![0u32; n],
            vec![0.0f32; n],
        );
        let mut rng = crate::rng::Pcg32::new(5, 1);
        for step in 1..=12u32 {
            let grads: Vec<Vec<f32>> = (0..3)
                .map(|_| {
                    (0..n)
                        .map(|_| match rng.next_u32() % 4 {
                            0 => 0.0,
                            1 => -0.0,
                            _ => rng.next_f32() - 0.5,
                        })
                        .collect()
                })
                .collect();
            let lr = c.learning_rate(step - 1);
            for i in 0..n {
                let mut g = 0.0f32;
                for gb in &grads {
                    g += gb[i];
                }
                let is_matrix = i < n_matrix;
                if is_matrix || g != 0.0 {
                    if is_matrix {
                        g += c.l2_reg * rw[i];
                    }
                    rst[i] += 1;
                    rm[i] = c.beta1 * rm[i] + (1.0 - c.beta1) * g;
                    rv[i] = c.beta2 * rv[i] + (1.0 - c.beta2) * g * g;
                    let lr_eff = lr * c.adam_correction(rst[i]);
                    rw[i] -= lr_eff * rm[i] / (rv[i].sqrt() + c.epsilon);
                }
                rema[i] = c.ema_decay * rema[i] + (1.0 - c.ema_decay) * rw[i];
            }
            let mut grads = grads;
            opt.step(&mut w, &mut grads, None);
            assert!(grads.iter().all(|g| g.iter().all(|&x| x == 0.0)));
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let (m, v, st) = opt.moments();
            assert_eq!(bits(&w), bits(&rw), "weights, step {step}");
            assert_eq!(bits(m), bits(&rm), "first moments, step {step}");
            assert_eq!(bits(v), bits(&rv), "second moments, step {step}");
            assert_eq!(st, &rst[..], "update counts, step {step}");
            assert_eq!(bits(&opt.ema), bits(&rema), "EMA, step {step}");
        }
    }

    #[test]
    fn learning_rate_decay_schedule() {
        let mut opt = Optimizer::new(OptimizerConfig::default(), 1, 1);
        opt.step = 19999;
        assert_eq!(opt.learning_rate(), 1e-2);
        opt.step = 20000;
        assert!((opt.learning_rate() - 3.3e-3).abs() < 1e-9);
        opt.step = 30000;
        assert!((opt.learning_rate() - 1.089e-3).abs() < 1e-8);
    }
}
