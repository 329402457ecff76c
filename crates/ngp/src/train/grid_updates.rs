//! When training refreshes its occupancy grids, and how much of them.
//!
//! The reference (instant-ngp's `training_prep_nerf`) updates before every one of the first
//! 32 steps, then every `clamp(step / 16, 1, 16)` steps, and each update of the first 256
//! steps evaluates the density at one point of every cell of every cascade (2 M a cascade).
//! On a GPU that is a millisecond. On the CPU a capture's five cascades cost seconds an
//! update, and the first 256 steps make 67 of them: the first minutes of training went there.
//!
//! A budget keeps the reference's update steps and its first update (every cell), and sizes
//! each later update by the work done since the previous one: `per_sample` density
//! evaluations per trained sample. An update that can afford a share `s` of the reference's
//! draws makes them (a share `s` of the cells, at random as the reference draws them) and
//! decays the grid by `0.95^s` instead of `0.95`, so that a cell loses what the reference's
//! grid loses between two of its samples: the grid is the reference's, on a slower clock. It
//! is counted, never timed, so a seed still gives the same model. With several scenes, each
//! grid is paid for by its own scene's samples: a hidden scene that trains a fraction of the
//! batch, or not yet, takes nothing from the cover's updates.

/// The occupancy-update pacing of a training.
#[derive(Clone, Debug)]
pub struct GridUpdates {
    per_sample: Option<f32>,
    /// Each scene's trained samples since the last update.
    since: Vec<u64>,
    updates: u32,
}

impl GridUpdates {
    /// The clock a training state keeps: each scene's trained samples since the last
    /// update, and the updates made.
    pub fn clock(&self) -> (&[u64], u32) {
        (&self.since, self.updates)
    }

    /// Sets the clock; `since` has one count a scene (a single count, a state saved before
    /// the clocks were the scenes' own, is the first scene's).
    pub fn set_clock(&mut self, since: &[u64], updates: u32) {
        self.since.fill(0);
        for (a, b) in self.since.iter_mut().zip(since) {
            *a = *b;
        }
        self.updates = updates;
    }

    /// `per_sample`: density evaluations allowed per trained sample; `None` (or 0) for the
    /// reference's schedule. Each of the `n_scenes` grids is paid for by its own scene's
    /// samples, so that a scene that trains little (a hidden scene at a fraction of the
    /// batch, or not yet: a cover's warm-up) does not take its updates from the others.
    pub fn new(per_sample: Option<f32>, n_scenes: usize) -> Self {
        GridUpdates {
            per_sample: per_sample.filter(|&r| r > 0.0),
            since: vec![0; n_scenes],
            updates: 0,
        }
    }

    /// The reference's rule: every step below 32, then every `clamp(step / 16, 1, 16)`.
    pub fn reference_due(step: u32) -> bool {
        step.is_multiple_of((step / 16).clamp(1, 16))
    }

    /// Once per weight-updating step, before its rays: `trained[i]` is the samples scene
    /// `i` trains this step (its target; 0 when it does not train). When an update is due,
    /// writes into `shares` each scene's share of the reference's update to make now (1 =
    /// all of it, 0 = none) and returns true. `first(i)`: scene `i`'s grid has never been
    /// updated; `full(i)`: the densities its whole update evaluates (asked only when a
    /// share is to be sized).
    pub fn due(
        &mut self,
        step: u32,
        trained: &[u64],
        shares: &mut [f32],
        first: impl Fn(usize) -> bool,
        full: impl Fn(usize) -> u64,
    ) -> bool {
        let Some(r) = self.per_sample else {
            shares.fill(1.0);
            return Self::reference_due(step);
        };
        for (s, t) in self.since.iter_mut().zip(trained) {
            *s += t;
        }
        if !Self::reference_due(step) {
            return false;
        }
        for (i, share) in shares.iter_mut().enumerate() {
            let since = self.since[i];
            *share = if since == 0 {
                0.0
            } else if first(i) {
                // The first update finds what every camera's rays cross; a partial one
                // would leave the cells it did not draw empty until drawn.
                1.0
            } else {
                (r as f64 * since as f64 / full(i).max(1) as f64).min(1.0) as f32
            };
        }
        self.since.fill(0);
        self.updates += 1;
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One scene's updates: (step, share) of each.
    fn shares(mut g: GridUpdates, steps: u32, samples: u64, full: u64) -> Vec<(u32, f32)> {
        let mut updated = false;
        let mut share = [0.0];
        (0..steps)
            .filter_map(|s| {
                let due = g.due(s, &[samples], &mut share, |_| !updated, |_| full);
                updated |= due && share[0] > 0.0;
                due.then_some((s, share[0]))
            })
            .collect()
    }

    #[test]
    fn the_reference_schedule_by_hand() {
        let due: Vec<u32> = (0..100)
            .filter(|&s| GridUpdates::reference_due(s))
            .collect();
        // Every step to 31, every 2nd to 47, every 3rd to 63 (48, 51, …, 63), every 4th …
        let mut want: Vec<u32> = (0..32).collect();
        want.extend([32, 34, 36, 38, 40, 42, 44, 46, 48, 51, 54, 57, 60, 63]);
        want.extend([64, 68, 72, 76, 80, 85, 90, 95, 96]);
        assert_eq!(due, want);
        assert_eq!(
            (256..300)
                .filter(|&s| GridUpdates::reference_due(s))
                .count(),
            3
        );
        // No budget, or a zero one, is the reference: whole updates on its steps.
        for g in [GridUpdates::new(None, 1), GridUpdates::new(Some(0.0), 1)] {
            let s = shares(g, 100, 1, 1 << 30);
            assert_eq!(s.iter().map(|x| x.0).collect::<Vec<_>>(), want);
            assert!(s.iter().all(|x| x.1 == 1.0));
        }
    }

    #[test]
    fn a_budget_sizes_each_update_by_the_work_since_the_last() {
        // 1000 samples a step at 1 evaluation each; a whole update costs 4000. The first is
        // whole; then one step pays a quarter of an update, two steps (from step 32, every
        // 2nd) half, and past step 64 (every 4th step) a whole one.
        let s = shares(GridUpdates::new(Some(1.0), 1), 100, 1000, 4000);
        assert_eq!(s[0], (0, 1.0));
        assert_eq!(s[1], (1, 0.25));
        assert_eq!(s[31], (31, 0.25));
        assert_eq!(s[32], (32, 0.25));
        assert_eq!(s[33], (34, 0.5));
        assert_eq!(s[40], (48, 0.5));
        assert_eq!(s[41], (51, 0.75));
        // Step 64 follows 63 (a quarter); from 68 on, four or more steps pay for it all.
        assert_eq!(s.iter().find(|x| x.0 == 64), Some(&(64, 0.25)));
        let late: Vec<&(u32, f32)> = s.iter().filter(|x| (68..96).contains(&x.0)).collect();
        assert!(
            late.len() == 7 && late.iter().all(|x| x.1 == 1.0),
            "{late:?}"
        );
        // Same steps as the reference's.
        assert!(s.iter().all(|x| GridUpdates::reference_due(x.0)));
        // Half the budget, half the share.
        let h = shares(GridUpdates::new(Some(0.5), 1), 40, 1000, 4000);
        assert_eq!(h[1], (1, 0.125));
        assert_eq!(h[33], (34, 0.25));
    }

    #[test]
    fn each_grid_is_paid_for_by_its_own_scenes_samples() {
        // Scene 0 trains 1000 samples a step; scene 1 joins at step 40 with 250. A whole
        // update costs 4000 of either. Before it joins scene 1's grid is not updated; its
        // first update is whole; then each scene's share is its own samples' worth.
        let mut g = GridUpdates::new(Some(1.0), 2);
        let mut updated = [false; 2];
        let mut share = [0.0; 2];
        let mut seen = Vec::new();
        for step in 0..100 {
            let trained = [1000, if step < 40 { 0 } else { 250 }];
            if g.due(step, &trained, &mut share, |i| !updated[i], |_| 4000) {
                for i in 0..2 {
                    updated[i] |= share[i] > 0.0;
                }
                seen.push((step, share));
            }
        }
        let at = |step| seen.iter().find(|x| x.0 == step).unwrap().1;
        assert_eq!(at(0), [1.0, 0.0]);
        assert_eq!(at(34), [0.5, 0.0], "scene 1 waits for its samples");
        assert_eq!(at(40), [0.5, 1.0], "its first update is whole");
        assert_eq!(at(44), [0.5, 0.125]);
        assert_eq!(at(90), [1.0, 0.3125], "five steps since 85");
        // The reference's schedule updates every grid whole, trained or not.
        let mut r = GridUpdates::new(None, 2);
        assert!(r.due(3, &[1000, 0], &mut share, |_| false, |_| 4000));
        assert_eq!(share, [1.0, 1.0]);
    }
}
