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

pub struct Optimizer {
    pub config: OptimizerConfig,
    /// Parameters below this index are MLP weights (L2, never skipped).
    n_matrix: usize,
    m: Vec<f32>,
    v: Vec<f32>,
    steps: Vec<u32>,
    ema: Vec<f32>,
    /// Global step count (number of `step` calls).
    pub step: u32,
    /// `sqrt(1 − β2^t) / (1 − β1^t)` for t = 0..=step.
    correction: Vec<f32>,
}

const BLOCK: usize = 1 << 14;

impl Optimizer {
    pub fn new(config: OptimizerConfig, n_params: usize, n_matrix: usize) -> Self {
        Optimizer {
            config,
            n_matrix,
            m: vec![0.0; n_params],
            v: vec![0.0; n_params],
            steps: vec![0; n_params],
            ema: vec![0.0; n_params],
            step: 0,
            correction: vec![0.0],
        }
    }

    /// Learning rate in force for the next step (ExponentialDecay).
    pub fn learning_rate(&self) -> f32 {
        let c = &self.config;
        let mut lr = c.lr;
        if self.step >= c.decay_start {
            let k = (self.step - c.decay_start) / c.decay_interval + 1;
            lr *= c.decay_base.powi(k as i32);
        }
        lr
    }

    /// One update. `grads` are per-thread gradient buffers (summed in order, then zeroed).
    pub fn step(&mut self, params: &mut [f32], grads: &mut [Vec<f32>]) {
        let c = self.config;
        self.step += 1;
        let t = self.step as usize;
        while self.correction.len() <= t {
            let k = self.correction.len() as i32;
            let b1 = 1.0 - (c.beta1 as f64).powi(k);
            let b2 = 1.0 - (c.beta2 as f64).powi(k);
            self.correction.push((b2.sqrt() / b1) as f32);
        }
        let lr = {
            self.step -= 1;
            let lr = self.learning_rate();
            self.step += 1;
            lr
        };
        let correction = &self.correction;
        let n_matrix = self.n_matrix;
        let n = params.len();
        // Raw pointers let each block take disjoint slices of every gradient buffer.
        let grad_ptrs: Vec<usize> = grads.iter_mut().map(|g| g.as_mut_ptr() as usize).collect();
        params
            .par_chunks_mut(BLOCK)
            .zip(self.m.par_chunks_mut(BLOCK))
            .zip(self.v.par_chunks_mut(BLOCK))
            .zip(self.steps.par_chunks_mut(BLOCK))
            .zip(self.ema.par_chunks_mut(BLOCK))
            .enumerate()
            .for_each(|(b, ((((w, m), v), st), ema))| {
                let start = b * BLOCK;
                let len = w.len();
                debug_assert!(start + len <= n);
                // SAFETY: blocks are disjoint and each buffer has n elements.
                let gs: Vec<&mut [f32]> = grad_ptrs
                    .iter()
                    .map(|&p| unsafe {
                        std::slice::from_raw_parts_mut((p as *mut f32).add(start), len)
                    })
                    .collect();
                for i in 0..len {
                    let mut g = 0.0f32;
                    for gb in gs.iter() {
                        g += gb[i];
                    }
                    let global = start + i;
                    let matrix = global < n_matrix;
                    if matrix || g != 0.0 {
                        if matrix {
                            g += c.l2_reg * w[i];
                        }
                        st[i] += 1;
                        m[i] = c.beta1 * m[i] + (1.0 - c.beta1) * g;
                        v[i] = c.beta2 * v[i] + (1.0 - c.beta2) * g * g;
                        let lr_eff = lr * correction[st[i] as usize];
                        w[i] -= lr_eff * m[i] / (v[i].sqrt() + c.epsilon);
                    }
                    ema[i] = c.ema_decay * ema[i] + (1.0 - c.ema_decay) * w[i];
                }
                for gb in gs {
                    gb.fill(0.0);
                }
            });
        for g in grads.iter() {
            debug_assert_eq!(g.len(), n);
        }
    }

    /// The debiased EMA of the weights: what renders and what a snapshot stores.
    pub fn ema_params(&self, params: &[f32]) -> Vec<f32> {
        if self.step == 0 {
            return params.to_vec();
        }
        let debias = 1.0 - (self.config.ema_decay as f64).powi(self.step as i32);
        let k = (1.0 / debias) as f32;
        self.ema.par_iter().map(|&e| e * k).collect()
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
        opt.step(&mut w, &mut grads);
        // First Adam step moves each parameter by lr·g/|g| = 0.01 against the gradient.
        assert!((w[0] - 0.99).abs() < 1e-6, "{}", w[0]);
        assert_eq!(w[1], 2.0, "zero-gradient grid entry must stay untouched");
        assert!((w[2] - 2.99).abs() < 1e-6);
        assert!(grads.iter().all(|g| g.iter().all(|&x| x == 0.0)));
        assert_eq!(opt.steps, vec![1, 0, 1]);
        // A matrix parameter is updated even with zero gradient (and counts the step).
        let mut grads = vec![vec![0.0f32; 3]];
        opt.step(&mut w, &mut grads);
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
        opt.step(&mut w, &mut [vec![1.0]]);
        opt.step(&mut w, &mut [vec![-1.0]]);
        // By hand: m2 = 0.9·0.1 − 0.1 = −0.01, v2 = 0.99·0.01 + 0.01 = 0.0199,
        // lr_eff = 0.01·sqrt(1 − 0.99²)/(1 − 0.9²), step = lr_eff·m2/sqrt(v2).
        let lr_eff = 0.01 * (1.0f64 - 0.99f64.powi(2)).sqrt() / (1.0 - 0.81);
        let want = -0.01 - lr_eff * (-0.01) / 0.0199f64.sqrt();
        assert!((w[0] as f64 - want).abs() < 1e-6, "{} vs {want}", w[0]);
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
