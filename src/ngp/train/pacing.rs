//! What stealth training changes in a step's gradient before the optimizer sees it, so that
//! the shared weights move as a plain model's of the cover would: the table paced on the
//! cover ([`TrainConfig::cover_paced_table`]) and the MLP learnt from the cover alone
//! ([`TrainConfig::cover_only_mlp`]). Both act on the workers' partial gradients between the
//! scenes' backward passes and the update; the engine's rays, network and optimizer are
//! untouched.

use super::left_entries::LeftEntries;
use super::optimizer::{GROUP, Touched, set_bits};
#[cfg(doc)]
use super::trainer::TrainConfig;
use super::trainer::Worker;

/// [`TrainConfig::cover_paced_table`]'s state.
pub(super) struct Pacing {
    /// One bit per parameter: the cover's gradient of this step reached it.
    gate: Vec<u64>,
    /// Other scenes' gradients waiting for the cover to reach their entry.
    pending: Vec<f32>,
    /// Parameters below this index are MLP weights, never held back.
    n_matrix: usize,
}

impl Pacing {
    pub(super) fn new(n_params: usize, n_matrix: usize) -> Self {
        Pacing {
            gate: vec![0; n_params.div_ceil(64)],
            pending: vec![0.0; n_params],
            n_matrix,
        }
    }

    fn gated(&self, i: usize) -> bool {
        self.gate[i / 64] >> (i % 64) & 1 != 0
    }

    /// After the cover's rays: every table parameter the cover's gradient reached, i.e.
    /// whose summed gradient is not zero (the optimizer's own rule, and the GPU's).
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

    /// Before the update: table gradients the gate holds back go to `pending`; held-back
    /// gradients of entries the gate lets through join this update. The gate is open at
    /// every entry the cover has `left` ([`TrainConfig::bounded_left_entries`]): no cover
    /// gradient will reach it again, and its bound keeps its magnitude.
    ///
    /// [`TrainConfig::bounded_left_entries`]: super::TrainConfig::bounded_left_entries
    pub(super) fn hold_back(
        &mut self,
        workers: &mut [Worker],
        left: Option<(&LeftEntries, usize)>,
    ) {
        let open = |i: usize| match left {
            Some((l, f)) => l.is_left((i - self.n_matrix) / f),
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

/// [`TrainConfig::cover_only_mlp`]'s state: each worker's MLP gradient from the cover's rays,
/// kept while the other scenes' rays add theirs, and put back before the update.
pub(super) struct CoverOnlyMlp {
    kept: Vec<Vec<f32>>,
    /// Parameters below this index are MLP weights.
    n_matrix: usize,
    /// The cover's rays ran this step (a random-scene step may train another scene alone).
    cover_trained: bool,
}

impl CoverOnlyMlp {
    pub(super) fn new(n_workers: usize, n_matrix: usize) -> Self {
        CoverOnlyMlp {
            kept: vec![vec![0.0; n_matrix]; n_workers],
            n_matrix,
            cover_trained: false,
        }
    }

    /// After the cover's rays.
    pub(super) fn keep(&mut self, workers: &[Worker]) {
        for (kept, w) in self.kept.iter_mut().zip(workers) {
            kept.copy_from_slice(&w.grad[..self.n_matrix]);
        }
        self.cover_trained = true;
    }

    /// Before the update: the MLP gradient is the cover's, or zero in a step without it
    /// (the optimizer still steps the MLP, on momentum and L2, as in any step).
    pub(super) fn restore(&mut self, workers: &mut [Worker]) {
        for (kept, w) in self.kept.iter().zip(workers) {
            let mlp = &mut w.grad[..self.n_matrix];
            if self.cover_trained {
                mlp.copy_from_slice(kept);
            } else {
                mlp.fill(0.0);
            }
        }
        self.cover_trained = false;
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
    fn pacing_holds_table_gradients_until_the_cover_reaches_them() {
        // 24 parameters, the first 4 MLP weights; two workers.
        let mut ws = vec![Worker::new(24), Worker::new(24)];
        let mut p = Pacing::new(24, 4);
        // Step 1, the cover's rays: table parameters 5 and 9, and an MLP weight.
        add(&mut ws[0], 5, 1.0);
        add(&mut ws[1], 9, 2.0);
        add(&mut ws[1], 1, 0.5);
        p.open_gate(&ws);
        // The hidden scene's rays: 5 again, 6 and 13 (the cover's gradient missed them),
        // and an MLP weight the cover did not reach.
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
        // Step 2 (buffers zeroed by the optimizer): the cover reaches 6; 13 waits on.
        for w in &mut ws {
            w.grad.fill(0.0);
            w.touched.clear();
        }
        add(&mut ws[1], 6, -1.0);
        p.open_gate(&ws);
        add(&mut ws[0], 13, 1.0);
        p.hold_back(&mut ws, None);
        assert_eq!(sum(&ws, 6), 3.0, "the held gradient joins the cover's");
        assert_eq!(sum(&ws, 13), 0.0);
        assert_eq!((p.pending[6], p.pending[13]), (0.0, 25.0));
        assert!(
            p.gate.iter().all(|&w| w == 0),
            "the gate closes after each step"
        );
    }

    #[test]
    fn entries_the_cover_left_are_not_held() {
        use crate::ngp::train::left_entries::{LeftEntries, REACHED};
        // 4 MLP weights, then 10 entries of 2 features; the cover has left entries 1 and 3
        // (parameters 6, 7 and 10, 11).
        let mut ws = vec![Worker::new(24)];
        let mut p = Pacing::new(24, 4);
        let mut bounds = vec![REACHED; 10];
        bounds[1] = 0.5;
        bounds[3] = 0.0;
        let left = LeftEntries::from_bounds(bounds, 2);
        // A held gradient from an earlier step on parameter 7, before the cover left it.
        p.pending[7] = 9.0;
        p.open_gate(&ws);
        // Only the hidden scene's rays this step: a reached entry (parameter 8) and both
        // left ones.
        for (i, g) in [(8, 1.0), (6, 2.0), (7, 3.0), (11, 4.0)] {
            add(&mut ws[0], i, g);
        }
        p.hold_back(&mut ws, Some((&left, 2)));
        assert_eq!(ws[0].grad[8], 0.0, "a reached entry waits for the cover");
        assert_eq!(p.pending[8], 1.0);
        assert_eq!(
            [6, 7, 11].map(|i| ws[0].grad[i]),
            [2.0, 3.0, 4.0],
            "left entries move at the hidden scene's pace"
        );
        assert_eq!(p.pending[7], 9.0, "what waited before stays held");
    }

    #[test]
    fn a_cover_only_mlp_keeps_the_covers_mlp_gradient_alone() {
        // 12 parameters, the first 4 MLP weights; two workers.
        let mut ws = vec![Worker::new(12), Worker::new(12)];
        let mut m = CoverOnlyMlp::new(2, 4);
        // A mixed step: the cover's MLP and table gradients, then the hidden scene's.
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
        // A step without the cover (random scene): no MLP gradient at all.
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
