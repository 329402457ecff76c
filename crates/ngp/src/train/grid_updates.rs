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
//! is counted, never timed, so a seed still gives the same model.

/// The occupancy-update pacing of a training.
#[derive(Clone, Debug)]
pub struct GridUpdates {
    per_sample: Option<f32>,
    /// Trained samples since the last update.
    since: u64,
    updates: u32,
}

impl GridUpdates {
    /// The clock a training state keeps: trained samples since the last update, updates.
    pub fn clock(&self) -> (u64, u32) {
        (self.since, self.updates)
    }

    pub fn set_clock(&mut self, since: u64, updates: u32) {
        self.since = since;
        self.updates = updates;
    }

    /// `per_sample`: density evaluations allowed per trained sample; `None` (or 0) for the
    /// reference's schedule.
    pub fn new(per_sample: Option<f32>) -> Self {
        GridUpdates {
            per_sample: per_sample.filter(|&r| r > 0.0),
            since: 0,
            updates: 0,
        }
    }

    /// The reference's rule: every step below 32, then every `clamp(step / 16, 1, 16)`.
    pub fn reference_due(step: u32) -> bool {
        step.is_multiple_of((step / 16).clamp(1, 16))
    }

    /// Once per weight-updating step, before its rays: the share of the reference's update
    /// to make now (1 = all of it), or `None`. The step trains `step_samples` samples (its
    /// target); the reference's update would evaluate about `full()` densities (asked only
    /// when a share is to be sized).
    pub fn due(&mut self, step: u32, step_samples: u64, full: impl FnOnce() -> u64) -> Option<f32> {
        let Some(r) = self.per_sample else {
            return Self::reference_due(step).then_some(1.0);
        };
        self.since += step_samples;
        if !Self::reference_due(step) {
            return None;
        }
        let share = if self.updates == 0 {
            // The first update finds what every camera's rays cross; a partial one would
            // leave the cells it did not draw empty until drawn.
            1.0
        } else {
            (r as f64 * self.since as f64 / full().max(1) as f64).min(1.0) as f32
        };
        self.since = 0;
        self.updates += 1;
        Some(share)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shares(mut g: GridUpdates, steps: u32, samples: u64, full: u64) -> Vec<(u32, f32)> {
        (0..steps)
            .filter_map(|s| g.due(s, samples, || full).map(|share| (s, share)))
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
        for g in [GridUpdates::new(None), GridUpdates::new(Some(0.0))] {
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
        let s = shares(GridUpdates::new(Some(1.0)), 100, 1000, 4000);
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
        let h = shares(GridUpdates::new(Some(0.5)), 40, 1000, 4000);
        assert_eq!(h[1], (1, 0.125));
        assert_eq!(h[33], (34, 0.25));
    }
}
