//! What a training policy can change in a step, on either backend.
//!
//! The engine trains one or more scenes on one set of weights; scene 0 is the one a model
//! publishes (its occupancy grid, its loss). Plain training needs nothing more. A policy
//! (the stego layer's stealth, say) decides *when* and *where* a step deviates from that,
//! through a [`TrainPolicy`] the trainer calls at fixed points of every step; the *how* —
//! the mechanisms below, on the host's gradient buffers or in device kernels — is each
//! backend's, behind [`PolicyOps`]:
//!
//! - an **index refresh**: new index functions for scenes 1.. from scene 0's grid and the
//!   published weights, at installation and after each update of that grid;
//! - an **extra loss term** on a scene's density at points of the policy's choosing
//!   ([`PolicyOps::density_loss`]);
//! - a **gradient gate with hold-back**: table gradients that the gate keeps closed wait,
//!   summed, until a later step opens it ([`PolicyOps::open_gate`], [`PolicyOps::hold_back`]);
//! - a **kept MLP gradient**: the MLP block of the gradient set aside and put back
//!   ([`PolicyOps::keep_mlp`], [`PolicyOps::restore_mlp`]), so that later scenes of a step
//!   reach the table only;
//! - **bounds** on table entries' magnitudes, applied after every optimizer step
//!   ([`TableBounds`], [`PolicyOps::update_bounds`]);
//! - a **clock**: whether a step updates the weights and grids at all
//!   ([`TrainPolicy::updates_weights`]).
//!
//! Every mechanism starts unused and costs nothing until a policy asks for it.

use crate::encoding::LevelIndices;
use crate::error::Result;
use crate::occupancy::OccupancyGrid;

/// Where a step stands, for a policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StepInfo {
    /// The trainer's seed.
    pub seed: u64,
    /// Steps taken before this one: the schedule's and the rays' clock.
    pub step: u32,
    /// Steps that updated the weights before this one: the optimizer's and the occupancy
    /// grids' clock, and the step count a model file records.
    pub weight_steps: u32,
}

/// What [`TrainPolicy::grid_updated`] and [`TrainPolicy::indices`] read, so that a backend
/// fetches (a GPU: reads back) only that.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PolicyReads {
    /// Scene 0's occupancy grid after each of its updates.
    pub grid: bool,
    /// The weights as they would be published (the debiased EMA) at each update.
    pub published: bool,
}

/// A training policy: called by the trainer (CPU or GPU) at fixed points of every step.
/// Every method has a default that does nothing, i.e. plain training.
pub trait TrainPolicy: Send {
    /// What the policy reads at scene 0's grid updates.
    fn reads(&self) -> PolicyReads {
        PolicyReads::default()
    }

    /// Whether a step that trains `scenes` updates the weights and the occupancy grids. A
    /// step that does not leaves its gradients in the buffers for the next one that does.
    fn updates_weights(&self, scenes: &[usize]) -> bool {
        let _ = scenes;
        true
    }

    /// Index functions that follow scene 0's grid: called when the policy is installed and
    /// after every update of scene 0's grid (after [`Self::grid_updated`]) with that grid
    /// and the published weights (only when [`PolicyReads::published`]); returns new index
    /// functions for the scenes it names (never scene 0). They take effect before the other
    /// scenes' grids update.
    fn indices(&mut self, grid: &OccupancyGrid, published: &[f32]) -> Vec<(usize, LevelIndices)> {
        let _ = (grid, published);
        Vec::new()
    }

    /// After every update of scene 0's grid (not at installation): `grid` and `published`
    /// as [`Self::reads`] asked.
    fn grid_updated(
        &mut self,
        grid: Option<&OccupancyGrid>,
        published: Option<&[f32]>,
        ops: &mut dyn PolicyOps,
    ) -> Result<()> {
        let _ = (grid, published, ops);
        Ok(())
    }

    /// After scene `scene`'s rays have added their gradient, before the next scene's.
    fn after_scene(&mut self, scene: usize, step: StepInfo, ops: &mut dyn PolicyOps) -> Result<()> {
        let _ = (scene, step, ops);
        Ok(())
    }

    /// After the step's last scene, before the optimizer (also in a step that does not
    /// update the weights).
    fn before_update(&mut self, step: StepInfo, ops: &mut dyn PolicyOps) -> Result<()> {
        let _ = (step, ops);
        Ok(())
    }

    /// The policy's own state between two steps, for a training state ([`super::state`]):
    /// what it carries from one step to the next that building it again does not give
    /// back. `None`: nothing (the default).
    fn save_state(&self) -> Result<Option<Vec<u8>>> {
        Ok(None)
    }

    /// Takes back a [`Self::save_state`] into a policy built the same way and installed in
    /// a trainer whose own state has just been restored; `origin` names the state in
    /// errors. Returns the index functions the policy had last given ([`Self::indices`]),
    /// which the trainer sets again.
    fn restore_state(
        &mut self,
        bytes: Option<&[u8]>,
        origin: &std::path::Path,
    ) -> Result<Vec<(usize, LevelIndices)>> {
        match bytes {
            None => Ok(Vec::new()),
            Some(_) => Err(crate::error::Error::format(
                origin,
                "holds a training policy's state that this policy does not keep",
            )),
        }
    }
}

/// The mechanisms a policy drives, implemented by each backend on the gradient of the step
/// in progress (the CPU's per-worker partials, the GPU's device buffer). Their state lives
/// in the trainer, made on first use.
pub trait PolicyOps {
    /// Adds to the step's gradient that of an extra loss on scene `scene`'s density:
    /// `points` in the occupancy grid's coordinates (the unit cube of cascade 0, like its
    /// cells), `d_loss(raw)` the loss's derivative with respect to the network's raw
    /// log-density output at a point. Returns the points where the derivative is not zero.
    fn density_loss(
        &mut self,
        scene: usize,
        points: &[[f32; 3]],
        d_loss: &(dyn Fn(f32) -> f32 + Sync),
    ) -> Result<u32>;

    /// Opens the gate of every table parameter the step's gradient reaches so far (its
    /// summed gradient is not zero: the optimizer's own rule for a touched entry).
    fn open_gate(&mut self) -> Result<()>;

    /// Moves the table gradients the gate keeps closed into the held-back sum (entries
    /// under a bound excepted: [`TableBounds`]), adds the held-back sums of the parameters
    /// it lets through, and closes the gate.
    fn hold_back(&mut self) -> Result<()>;

    /// Sets aside the MLP block of the step's gradient so far.
    fn keep_mlp(&mut self) -> Result<()>;

    /// Puts back the MLP gradient [`Self::keep_mlp`] set aside in this step, or clears the
    /// MLP block where it set nothing aside.
    fn restore_mlp(&mut self) -> Result<()>;

    /// Lets `update` change the table's bounds (every entry unbounded at first), which the
    /// backend then applies after each optimizer step.
    fn update_bounds(&mut self, update: &mut dyn FnMut(&mut TableBounds)) -> Result<()>;
}

/// What [`TableBounds::bound`] holds for an entry without a bound.
pub const UNBOUNDED: f32 = -1.0;

/// A bound on the magnitude of table entries: after every optimizer step each bounded
/// entry's features are clamped to `±bound`; a gate's hold-back never holds a bounded entry
/// (a policy bounds what it lets move freely).
#[derive(Clone, Debug, PartialEq)]
pub struct TableBounds {
    bound: Vec<f32>,
    /// The bounded entries, for the clamp.
    bounded: Vec<u32>,
    n_features: usize,
}

impl TableBounds {
    /// `n_entries` entries of `n_features` features, none bounded.
    pub fn new(n_entries: usize, n_features: usize) -> Self {
        TableBounds {
            bound: vec![UNBOUNDED; n_entries],
            bounded: Vec::new(),
            n_features,
        }
    }

    /// Bounds given per entry ([`UNBOUNDED`], or any negative, for none).
    pub fn from_bounds(bound: Vec<f32>, n_features: usize) -> Self {
        let bounded = (0..bound.len() as u32)
            .filter(|&e| bound[e as usize] >= 0.0)
            .collect();
        TableBounds {
            bound,
            bounded,
            n_features,
        }
    }

    /// Sets every entry's bound: `f(entry, old bound)` returns the new one ([`UNBOUNDED`]
    /// for none). The entries are visited in table order.
    pub fn set_each(&mut self, mut f: impl FnMut(usize, f32) -> f32) {
        self.bounded.clear();
        for (e, b) in self.bound.iter_mut().enumerate() {
            *b = f(e, *b);
            if *b >= 0.0 {
                self.bounded.push(e as u32);
            }
        }
    }

    /// Entry `e`'s bound, or [`UNBOUNDED`].
    pub fn bound(&self, e: usize) -> f32 {
        self.bound[e]
    }

    /// Every entry's bound, in table order (what a GPU uploads).
    pub fn bounds(&self) -> &[f32] {
        &self.bound
    }

    /// Whether entry `e` is bounded.
    #[inline]
    pub fn is_bounded(&self, e: usize) -> bool {
        self.bound[e] >= 0.0
    }

    pub fn n_features(&self) -> usize {
        self.n_features
    }

    /// Holds every bounded entry of `table` (entries × features) within its bound.
    pub fn clamp(&self, table: &mut [f32]) {
        let f = self.n_features;
        for &e in &self.bounded {
            let b = self.bound[e as usize];
            for v in &mut table[e as usize * f..(e as usize + 1) * f] {
                *v = v.clamp(-b, b);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clamp_holds_bounded_entries_alone() {
        // Entries of 2 features; entries 1 and 3 bounded.
        let mut b = TableBounds::new(4, 2);
        b.set_each(|e, _| match e {
            1 => 0.5,
            3 => 0.0,
            _ => UNBOUNDED,
        });
        let mut table = vec![2.0, -2.0, 2.0, -0.25, 2.0, -2.0, 0.1, -0.1];
        b.clamp(&mut table);
        assert_eq!(table, [2.0, -2.0, 0.5, -0.25, 2.0, -2.0, 0.0, 0.0]);
        assert!(b.is_bounded(1) && b.is_bounded(3) && !b.is_bounded(0));
        assert_eq!(b, TableBounds::from_bounds(vec![-1.0, 0.5, -1.0, 0.0], 2));
        // A later update sees the old bounds.
        b.set_each(|_, old| if old >= 0.0 { UNBOUNDED } else { 1.0 });
        assert_eq!(b.bounds(), [1.0, UNBOUNDED, 1.0, UNBOUNDED]);
    }
}
