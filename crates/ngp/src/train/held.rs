//! The CPU's gradient mechanisms behind [`PolicyOps`]: a gate with hold-back and a kept
//! MLP gradient. Both act on the workers' partial gradients between the scenes' backward
//! passes and the update; the rays, the network and the optimizer are untouched. (The GPU
//! backend has the same mechanisms in kernels.)
//!
//! [`PolicyOps`]: super::hooks::PolicyOps

use super::hooks::TableBounds;
use super::optimizer::{GROUP, Touched, set_bits};
use super::worker::Worker;

/// The gate and the held-back table gradients ([`super::hooks::PolicyOps::hold_back`]).
pub(super) struct HoldBack {
    /// One bit per parameter: open in this step.
    gate: Vec<u64>,
    /// Gradients waiting for their parameter's gate to open.
    pending: Vec<f32>,
    /// Parameters below this index are MLP weights, never held back.
    n_matrix: usize,
}

impl HoldBack {
    pub(super) fn new(n_params: usize, n_matrix: usize) -> Self {
        HoldBack {
            gate: vec![0; n_params.div_ceil(64)],
            pending: crate::pages::zeroed(n_params),
            n_matrix,
        }
    }

    /// The held-back sums, one per parameter (the MLP's always 0).
    pub(super) fn pending(&self) -> &[f32] {
        &self.pending
    }

    pub(super) fn pending_mut(&mut self) -> &mut [f32] {
        &mut self.pending
    }

    fn gated(&self, i: usize) -> bool {
        self.gate[i / 64] >> (i % 64) & 1 != 0
    }

    /// Opens the gate of every table parameter whose summed gradient so far is not zero
    /// (the optimizer's own rule for a touched entry, and the GPU's).
    pub(super) fn open_gate(&mut self, workers: &[Worker]) {
        let n = self.pending.len();
        for group in Touched::groups_of_any(workers.iter().map(|w| &w.touched)) {
            for i in (group * GROUP).max(self.n_matrix)..((group + 1) * GROUP).min(n) {
                if workers.iter().map(|w| w.grad[i]).sum::<f32>() != 0.0 {
                    self.gate[i / 64] |= 1 << (i % 64);
                }
            }
        }
    }

    /// Table gradients the gate keeps closed go to `pending`; held-back gradients of
    /// parameters it lets through join the workers' (the first's). The gate is always open
    /// at a bounded entry (`bounds`): its bound keeps its magnitude. Closes the gate.
    pub(super) fn hold_back(&mut self, workers: &mut [Worker], bounds: Option<&TableBounds>) {
        let open = |i: usize| match bounds {
            Some(b) => b.is_bounded((i - self.n_matrix) / b.n_features()),
            None => false,
        };
        for w in workers.iter_mut() {
            for group in w.touched.groups() {
                let g0 = (group * GROUP).max(self.n_matrix);
                for i in g0..((group + 1) * GROUP).min(w.grad.len()) {
                    if !self.gated(i) && w.grad[i] != 0.0 && !open(i) {
                        self.pending[i] += w.grad[i];
                        w.grad[i] = 0.0;
                    }
                }
            }
        }
        let Some(first) = workers.first_mut() else {
            return;
        };
        for i in set_bits(self.gate.iter().copied()) {
            first.grad[i] += std::mem::take(&mut self.pending[i]);
        }
        self.gate.fill(0);
    }
}

/// Each worker's MLP gradient set aside ([`super::hooks::PolicyOps::keep_mlp`]) while later
/// scenes' rays add theirs, and put back ([`super::hooks::PolicyOps::restore_mlp`]).
pub(super) struct KeptMlp {
    kept: Vec<Vec<f32>>,
    /// Parameters below this index are MLP weights.
    n_matrix: usize,
    /// Something was set aside in this step.
    any: bool,
}

impl KeptMlp {
    pub(super) fn new(n_workers: usize, n_matrix: usize) -> Self {
        KeptMlp {
            kept: vec![vec![0.0; n_matrix]; n_workers],
            n_matrix,
            any: false,
        }
    }

    pub(super) fn keep(&mut self, workers: &[Worker]) {
        for (kept, w) in self.kept.iter_mut().zip(workers) {
            kept.copy_from_slice(&w.grad[..self.n_matrix]);
        }
        self.any = true;
    }

    /// The MLP gradient is what was kept in this step, or zero where nothing was (the
    /// optimizer still steps the MLP, on momentum and L2, as in any step).
    pub(super) fn restore(&mut self, workers: &mut [Worker]) {
        for (kept, w) in self.kept.iter().zip(workers) {
            let mlp = &mut w.grad[..self.n_matrix];
            if self.any {
                mlp.copy_from_slice(kept);
            } else {
                mlp.fill(0.0);
            }
        }
        self.any = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn add(w: &mut Worker, i: usize, g: f32) {
        w.grad[i] += g;
        w.touched.mark(i);
    }

    #[test]
    fn the_gate_holds_table_gradients_until_it_opens() {
        // 24 parameters, the first 4 MLP weights; two workers.
        let mut ws = vec![Worker::new(24), Worker::new(24)];
        let mut p = HoldBack::new(24, 4);
        // Step 1, the first scene's rays (they open the gate): table parameters 5 and 9, and
        // an MLP weight.
        add(&mut ws[0], 5, 1.0);
        add(&mut ws[1], 9, 2.0);
        add(&mut ws[1], 1, 0.5);
        p.open_gate(&ws);
        // Another scene's rays: 5 again, 6 and 13 (the gate is closed there), and an MLP
        // weight the first scene did not reach.
        add(&mut ws[0], 5, 0.25);
        add(&mut ws[1], 6, 4.0);
        add(&mut ws[0], 13, 8.0);
        add(&mut ws[1], 13, 16.0);
        add(&mut ws[0], 2, 3.0);
        p.hold_back(&mut ws, None);
        let sum = |ws: &[Worker], i: usize| ws[0].grad[i] + ws[1].grad[i];
        assert_eq!(sum(&ws, 5), 1.25);
        assert_eq!(sum(&ws, 9), 2.0);
        assert_eq!((sum(&ws, 6), sum(&ws, 13)), (0.0, 0.0));
        assert_eq!(
            (sum(&ws, 1), sum(&ws, 2)),
            (0.5, 3.0),
            "MLP weights are never held"
        );
        assert_eq!((p.pending[6], p.pending[13]), (4.0, 24.0));
        // Step 2 (buffers zeroed by the optimizer): the gate opens at 6; 13 waits on.
        for w in &mut ws {
            w.grad.fill(0.0);
            w.touched.clear();
        }
        add(&mut ws[1], 6, -1.0);
        p.open_gate(&ws);
        add(&mut ws[0], 13, 1.0);
        p.hold_back(&mut ws, None);
        assert_eq!(sum(&ws, 6), 3.0, "the held gradient joins the step's");
        assert_eq!(sum(&ws, 13), 0.0);
        assert_eq!((p.pending[6], p.pending[13]), (0.0, 25.0));
        assert!(
            p.gate.iter().all(|&w| w == 0),
            "the gate closes after each step"
        );
    }

    #[test]
    fn bounded_entries_are_not_held() {
        use crate::train::hooks::UNBOUNDED;
        // 4 MLP weights, then 10 entries of 2 features; entries 1 and 3 are bounded
        // (parameters 6, 7 and 10, 11).
        let mut ws = vec![Worker::new(24)];
        let mut p = HoldBack::new(24, 4);
        let mut bounds = vec![UNBOUNDED; 10];
        bounds[1] = 0.5;
        bounds[3] = 0.0;
        let left = TableBounds::from_bounds(bounds, 2);
        // A held gradient from an earlier step on parameter 7, before it was bounded.
        p.pending[7] = 9.0;
        p.open_gate(&ws);
        // The gate stays closed this step: an unbounded entry (parameter 8) and both
        // bounded ones.
        for (i, g) in [(8, 1.0), (6, 2.0), (7, 3.0), (11, 4.0)] {
            add(&mut ws[0], i, g);
        }
        p.hold_back(&mut ws, Some(&left));
        assert_eq!(ws[0].grad[8], 0.0, "an unbounded entry waits for its gate");
        assert_eq!(p.pending[8], 1.0);
        assert_eq!(
            [6, 7, 11].map(|i| ws[0].grad[i]),
            [2.0, 3.0, 4.0],
            "bounded entries move at once"
        );
        assert_eq!(p.pending[7], 9.0, "what waited before stays held");
    }

    #[test]
    fn a_kept_mlp_gradient_is_the_first_scenes_alone() {
        // 12 parameters, the first 4 MLP weights; two workers.
        let mut ws = vec![Worker::new(12), Worker::new(12)];
        let mut m = KeptMlp::new(2, 4);
        // A step of two scenes: the first's MLP and table gradients (kept), then the
        // other's.
        add(&mut ws[0], 1, 1.0);
        add(&mut ws[1], 2, 2.0);
        add(&mut ws[0], 6, 0.5);
        m.keep(&ws);
        add(&mut ws[0], 1, 4.0);
        add(&mut ws[1], 3, 8.0);
        add(&mut ws[1], 7, 0.25);
        m.restore(&mut ws);
        let sum = |ws: &[Worker], i: usize| ws[0].grad[i] + ws[1].grad[i];
        assert_eq!([1, 2, 3].map(|i| sum(&ws, i)), [1.0, 2.0, 0.0]);
        // The table is left alone: both scenes' table gradients stay.
        assert_eq!((sum(&ws, 6), sum(&ws, 7)), (0.5, 0.25));
        // A step where nothing was kept: no MLP gradient at all.
        for w in &mut ws {
            w.grad.fill(0.0);
            w.touched.clear();
        }
        add(&mut ws[0], 1, 4.0);
        add(&mut ws[1], 9, 1.0);
        m.restore(&mut ws);
        assert_eq!((sum(&ws, 1), sum(&ws, 9)), (0.0, 1.0));
    }
}
