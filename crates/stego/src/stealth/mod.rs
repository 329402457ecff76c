//! Stealth: a training policy that makes a model with hidden scenes look, from the file
//! alone, as much as it can like a plain model of its cover. It runs on either backend
//! through the engine's training hooks ([`ngp::train::hooks`]); the engine knows nothing of
//! it.
//!
//! A plain model's table records where its training went: entries the cover's samples never
//! reach stay at their initialisation, entries reached only before the occupancy grid pruned
//! empty space freeze where Adam left them. A hidden scene indexed across the whole table
//! trains those entries to the end, and an analyst can count that from the file alone
//! (`stegongp detect`). Stealth's parts ([`StealthParts`]), each answering what a detector
//! found in the one before:
//!
//! - **Confinement** ([`confine`]): every hidden-scene index is mapped into the entries the
//!   cover moved (those off their initial value), recomputed after every update of the
//!   cover's grid from the weights as they would be published (hook: index refresh).
//!   Entries the cover never reached stay at initialisation, as in a plain model.
//! - **Pacing on the cover**: Adam moves a table entry by about its learning rate at every
//!   step its gradient is non-zero, so an entry that the cover and a hidden scene both
//!   reach takes more steps than in a plain model, and ends larger (measured: the median
//!   magnitude of the reachable hashed entries, AUC 1.0 between plain and confined-only
//!   stealth models). An entry the cover's grid still reaches moves only in steps where the
//!   cover's own gradient reaches it; the hidden scenes' gradients on it wait, summed, for
//!   the cover's next touch (hooks: the gate, opened after the cover's rays, and the
//!   hold-back before the update). The optimizer also keeps the cover's clock: a step that
//!   does not train the cover (the random-scene schedule's hidden steps) updates no weight
//!   and no grid, its gradients waiting for the cover's next step (hook: the clock). A
//!   plain model's MLP takes one Adam, L2 and EMA step per cover step; one that took the
//!   hidden scenes' steps as well ended with other weight moments, which gave paced stealth
//!   models away under that schedule at any hidden weight.
//! - **Bounded left entries** ([`left_entries`]): entries the cover's grid no longer lets
//!   training reach — most of the coarse levels, the fog the cover cleared in its first
//!   steps — keep at most the magnitude they had when it left them, and move at the hidden
//!   scenes' pace (hook: the table's bounds). Sharing only the entries the cover still
//!   reaches cost the hidden scenes 1.5 dB on the small scenes and left those entries'
//!   magnitudes larger than a plain model's all the same (benchmarks/steganalysis.md,
//!   "Sharing the entries the cover left").
//! - **The density cap** ([`density_cap`]): sharing its entries with hidden scenes makes
//!   the cover's network decode dense cells inside its opaque objects, where no cover ray
//!   looks (10–100× a plain model's), and the stored grid showed it (its largest cells and
//!   its mean, hence its occupancy threshold). A penalty on the cover's optical thickness
//!   above 2 per finest step, in the cells its grid holds above 1, brings those statistics
//!   back to a plain model's (hook: an extra loss term; benchmarks/steganalysis.md,
//!   "Capping the cover's density").
//! - **A cover-only MLP** (optional, `--cover-only-mlp`): with the table paced, the shared
//!   MLP gave the models away next (the spread of its first density layer: AUC 0.98). The
//!   MLP then learns from the cover alone and the hidden scenes train their keyed entries
//!   only, decoded by the cover's MLP (hook: the kept MLP gradient): fewer statistics
//!   separate the arms, at a price in hidden fidelity that keeps it optional
//!   (benchmarks/steganalysis.md, "Stealth with the cover's own MLP").
//!
//! A key holder renders a stealth model's hidden scene with [`hidden_indices`]: the key's
//! indices confined by the maps the file's weights give.

pub mod confine;
pub mod density_cap;
pub mod left_entries;

pub use confine::{
    ConfineTo, confine, confined, confinement_map, confinement_maps, cover_entries, hidden_indices,
    reachable_cover_entries, robust_indices,
};
pub use density_cap::DensityCap;
pub use left_entries::LeftEntries;

use crate::keys::Key;
use density_cap::cap_gradient;
use ngp::encoding::LevelIndices;
use ngp::encoding::reach::EntrySet;
use ngp::error::{Error, Result};
use ngp::network::NerfLayout;
use ngp::occupancy::OccupancyGrid;
use ngp::train::{PolicyOps, PolicyReads, StepInfo, TrainPolicy};

/// Stealth's command-line options (`train`, `experiment`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct StealthOptions {
    /// Stealth: confine the hidden scenes to the table entries the cover itself trained
    /// (those off their initial value in the file), so that the file's statistics look like
    /// a plain model's (see `stegongp detect`); an entry the cover's occupancy grid still
    /// reaches moves only in steps where the cover's own gradient reaches it, one the grid
    /// has left keeps at most the magnitude it had then. Render and evaluate the hidden
    /// scenes with `--stealth` too.
    #[cfg_attr(feature = "clap", arg(long = "stealth"))]
    pub enabled: bool,
    /// With --stealth: the MLP learns from the cover alone, the hidden scenes train their
    /// keyed table entries only and are decoded by the cover's MLP. Fewer statistics tell
    /// the file from a plain one and the cover keeps more of its quality; the hidden scenes
    /// lose more (benchmarks/steganalysis.md, "Stealth with the cover's own MLP").
    #[cfg_attr(feature = "clap", arg(long))]
    pub cover_only_mlp: bool,
    /// With --stealth: the cap on the cover's optical thickness per finest marching step
    /// (the occupancy grid's unit), 0 for none. Hidden scenes sharing the cover's entries
    /// make its network decode dense cells inside opaque objects, where no cover ray looks,
    /// and the stored grid shows them; a penalty pulls the cover's density above the cap
    /// back down (benchmarks/steganalysis.md, "Capping the cover's density"). [default: 2]
    #[cfg_attr(feature = "clap", arg(long, value_name = "T"))]
    pub density_cap: Option<f32>,
}

impl StealthOptions {
    /// Refuses what cannot apply: a cap that is not a number ≥ 0, and the stealth options
    /// where no model trains with stealth (`stealth_trains`).
    pub fn check(&self, stealth_trains: bool) -> Result<()> {
        if let Some(c) = self.density_cap
            && !(c.is_finite() && c >= 0.0)
        {
            return Err(Error::Config(
                "--density-cap must be a number ≥ 0 (0: no cap)".into(),
            ));
        }
        if !stealth_trains && self.cover_only_mlp {
            return Err(Error::Config(
                "--cover-only-mlp changes stealth training: give it with --stealth".into(),
            ));
        }
        if !stealth_trains && self.density_cap.is_some() {
            return Err(Error::Config(
                "--density-cap changes stealth training: give it with --stealth".into(),
            ));
        }
        Ok(())
    }

    /// The cap the options give ([`DensityCap::stealth`]).
    pub fn cap(&self) -> Option<DensityCap> {
        DensityCap::stealth(self.density_cap)
    }

    /// One line on what stealth does with these options, for a command's log.
    pub fn describe(&self) -> String {
        format!(
            "stealth: hidden scenes confined to the entries the cover moved, those its grid \
             reaches paced on the cover, those it left bounded, the MLP {}, {}",
            if self.cover_only_mlp {
                "learnt from the cover alone"
            } else {
                "shared"
            },
            match self.cap() {
                Some(c) => format!(
                    "the cover's optical thickness capped at {}",
                    c.max_optical_thickness
                ),
                None => "the cover's density uncapped".into(),
            }
        )
    }
}

/// Which parts of stealth a [`Stealth`] policy runs: all of them for `--stealth`
/// ([`StealthParts::of`]); one at a time in the tests of each.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StealthParts {
    /// The hidden scenes' indices confined to the entries the cover moved.
    pub confine: bool,
    /// The table paced on the cover, and the optimizer on the cover's clock.
    pub pace: bool,
    /// Entries the cover left keep at most the magnitude they had then (with `pace`).
    pub bound_left: bool,
    /// The MLP learns from the cover alone.
    pub cover_only_mlp: bool,
    /// The cap on the cover's density.
    pub density_cap: Option<DensityCap>,
}

impl StealthParts {
    /// Every part, as `options` set them.
    pub fn of(options: &StealthOptions) -> Self {
        StealthParts {
            confine: true,
            pace: true,
            bound_left: true,
            cover_only_mlp: options.cover_only_mlp,
            density_cap: options.cap(),
        }
    }

    /// None of them (a start for a test of one part).
    pub fn none() -> Self {
        StealthParts {
            confine: false,
            pace: false,
            bound_left: false,
            cover_only_mlp: false,
            density_cap: None,
        }
    }
}

/// The stealth policy of a model whose scene 0 is the cover and whose scenes 1.. are
/// hidden, each under its key.
pub struct Stealth {
    layout: NerfLayout,
    parts: StealthParts,
    /// The keys' own index functions, made once (a dense level's keyed permutation costs a
    /// SipHash a slot, and early in training the grid is refreshed at every step); empty
    /// without confinement.
    keyed: Vec<LevelIndices>,
    left: Option<LeftEntries>,
    /// The density cap's cells, from the cover's grid as of its last update.
    cap_cells: Vec<u32>,
    /// The cover's entries the last confinement was made from (a training state saves
    /// them: the weights they were read from have moved on since); empty before.
    entries: Vec<EntrySet>,
    /// Which of the cover's entries confinement keeps to (`--robust`: those its grid
    /// reaches). Apart from [`StealthParts`], whose text a training state records: a state
    /// saved before it existed confined to the moved ones, and says nothing.
    confine_to: ConfineTo,
}

impl Stealth {
    /// Every part of stealth for `keys` (`keys[i]` is scene `i + 1`'s), as `options` set
    /// them.
    pub fn new(layout: NerfLayout, keys: &[Key], options: &StealthOptions) -> Result<Self> {
        Self::with_parts(layout, keys, StealthParts::of(options))
    }

    /// The parts chosen.
    pub fn with_parts(layout: NerfLayout, keys: &[Key], parts: StealthParts) -> Result<Self> {
        if parts.bound_left && !parts.pace {
            return Err(Error::Config(
                "stealth bounds the entries the cover left only with the table paced on it".into(),
            ));
        }
        if parts.confine && keys.is_empty() {
            return Err(Error::Config(
                "stealth confines hidden scenes: it needs at least one".into(),
            ));
        }
        let keyed = if parts.confine {
            keys.iter().map(|k| k.level_indices(&layout.grid)).collect()
        } else {
            Vec::new()
        };
        let left = parts.bound_left.then(|| LeftEntries::new(&layout.grid));
        Ok(Stealth {
            layout,
            parts,
            keyed,
            left,
            cap_cells: Vec::new(),
            entries: Vec::new(),
            confine_to: ConfineTo::Moved,
        })
    }

    /// The policy of `train --robust`, alone (`parts` none but confinement) or with
    /// stealth's: the hidden scenes confined to the entries the cover's stored grid reaches.
    pub fn confined_to(mut self, to: ConfineTo) -> Self {
        self.confine_to = to;
        self
    }

    /// `train --robust` without `--stealth`: confinement to the reachable entries alone.
    pub fn robust(layout: NerfLayout, keys: &[Key]) -> Result<Self> {
        let parts = StealthParts {
            confine: true,
            ..StealthParts::none()
        };
        Ok(Self::with_parts(layout, keys, parts)?.confined_to(ConfineTo::Reachable))
    }
}

impl TrainPolicy for Stealth {
    fn reads(&self) -> PolicyReads {
        PolicyReads {
            grid: self.left.is_some() || self.parts.density_cap.is_some(),
            published: !self.keyed.is_empty() || self.left.is_some(),
        }
    }

    fn updates_weights(&self, scenes: &[usize]) -> bool {
        !self.parts.pace || scenes.contains(&0)
    }

    fn indices(&mut self, grid: &OccupancyGrid, published: &[f32]) -> Vec<(usize, LevelIndices)> {
        if self.keyed.is_empty() {
            return Vec::new();
        }
        self.entries = match self.confine_to {
            ConfineTo::Moved => cover_entries(&self.layout, published),
            // The grid a reader of the file rebuilds (fp16 densities), so that the key
            // holder's map is training's last.
            ConfineTo::Reachable => reachable_cover_entries(&self.layout, &grid.as_stored()),
        };
        self.confined_indices()
    }

    fn grid_updated(
        &mut self,
        grid: Option<&OccupancyGrid>,
        published: Option<&[f32]>,
        ops: &mut dyn PolicyOps,
    ) -> Result<()> {
        let Some(grid) = grid else {
            return Ok(());
        };
        if let Some(cap) = &self.parts.density_cap {
            self.cap_cells = cap.cells(grid);
        }
        if let (Some(left), Some(published)) = (&self.left, published) {
            let layout = &self.layout;
            let table = &published[layout.grid_offset..];
            ops.update_bounds(&mut |bounds| {
                left.update(bounds, &layout.grid, grid, layout.config.aabb_scale, table)
            })?;
        }
        Ok(())
    }

    fn after_scene(&mut self, scene: usize, step: StepInfo, ops: &mut dyn PolicyOps) -> Result<()> {
        if scene != 0 {
            return Ok(());
        }
        if let Some(cap) = &self.parts.density_cap {
            let points = cap.points(&self.cap_cells, step.seed, step.weight_steps);
            let n = points.len();
            ops.density_loss(0, &points, &|ld| cap_gradient(cap, ld, n).0)?;
        }
        if self.parts.pace {
            ops.open_gate()?;
        }
        if self.parts.cover_only_mlp {
            ops.keep_mlp()?;
        }
        Ok(())
    }

    fn before_update(&mut self, _step: StepInfo, ops: &mut dyn PolicyOps) -> Result<()> {
        if self.parts.pace {
            ops.hold_back()?;
        }
        if self.parts.cover_only_mlp {
            ops.restore_mlp()?;
        }
        Ok(())
    }

    /// The parts (to refuse a state saved with other options), the cover's entries of the
    /// last confinement and the density cap's cells; the keys' indices and the bound rule
    /// are rebuilt from the keys and the layout.
    fn save_state(&self) -> Result<Option<Vec<u8>>> {
        use ngp::train::state::{encode, map, u32s, u64s};
        use rmpv::Value;
        let entries = self
            .entries
            .iter()
            .map(|set| map(vec![("words", u64s(set.words()))]))
            .collect();
        let mut fields = vec![
            ("format", Value::from(STATE_FORMAT)),
            ("parts", Value::from(format!("{:?}", self.parts))),
            ("entries", Value::Array(entries)),
            ("cap_cells", u32s(&self.cap_cells)),
        ];
        if self.confine_to != ConfineTo::Moved {
            fields.push(("confine_to", Value::from(self.confine_to.name())));
        }
        Ok(Some(encode(&map(fields))))
    }

    fn restore_state(
        &mut self,
        bytes: Option<&[u8]>,
        origin: &std::path::Path,
    ) -> Result<Vec<(usize, LevelIndices)>> {
        use ngp::train::state::{Fields, open};
        let Some(bytes) = bytes else {
            return Err(Error::format(origin, "holds no stealth state"));
        };
        let doc = open(origin, bytes)?;
        let f = Fields::top(origin, &doc)?;
        f.expect_format(STATE_FORMAT, "a stealth state")?;
        if f.str("parts")? != format!("{:?}", self.parts) {
            return Err(f.err(
                "parts",
                "saved with other stealth options (--cover-only-mlp, --density-cap)",
            ));
        }
        let saved_to = if f.has("confine_to") {
            f.str("confine_to")?
        } else {
            ConfineTo::Moved.name()
        };
        if saved_to != self.confine_to.name() {
            return Err(f.err(
                "confine_to",
                format!(
                    "saved confining the hidden scenes to the cover's {saved_to} entries, \
                     resumed with {} (--robust)",
                    self.confine_to.name()
                ),
            ));
        }
        let levels = &self.layout.grid.levels;
        // Confinement records its entries from its installation on, and only it does.
        let n_saved = if self.keyed.is_empty() {
            0
        } else {
            levels.len()
        };
        let saved = f.maps("entries", n_saved)?;
        let mut entries = Vec::with_capacity(saved.len());
        for (lv, ef) in levels.iter().zip(&saved) {
            let mut words = vec![0u64; (lv.size as usize).div_ceil(64)];
            ef.u64s_into("words", &mut words)?;
            entries.push(
                EntrySet::from_words(lv.size, words)
                    .ok_or_else(|| ef.err("words", "a bit past the level's last entry"))?,
            );
        }
        let cells =
            ngp::occupancy::N_CELLS * ngp::occupancy::n_cascades(self.layout.config.aabb_scale);
        self.cap_cells = f.u32s("cap_cells", cells)?;
        if let Some(&c) = self.cap_cells.iter().find(|&&c| c as usize >= cells) {
            return Err(f.err("cap_cells", format!("cell {c} past the grid's {cells}")));
        }
        self.entries = entries;
        Ok(self.confined_indices())
    }
}

/// A stealth policy's state document (inside a training state).
const STATE_FORMAT: &str = "stegongp-stealth-state";

impl Stealth {
    /// The hidden scenes' index functions: the keys', confined to [`Self::entries`]; none
    /// without confinement.
    fn confined_indices(&self) -> Vec<(usize, LevelIndices)> {
        if self.keyed.is_empty() {
            return Vec::new();
        }
        let maps: Vec<std::sync::Arc<[u32]>> = self
            .entries
            .iter()
            .map(|s| std::sync::Arc::from(confinement_map(s)))
            .collect();
        self.keyed
            .iter()
            .enumerate()
            .map(|(i, k)| (i + 1, confine::confine_indices(k, &maps)))
            .collect()
    }
}

#[cfg(test)]
mod tests;
