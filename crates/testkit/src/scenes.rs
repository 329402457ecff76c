//! Generated scenes, written into a folder and loaded back as the trainer and the
//! evaluation read them.

use dataset::LoadOptions;
use ngp::data::{Dataset, Split};
use std::path::Path;
use std::sync::Arc;
use synth::{SceneKind, SynthOptions, generate};

/// A generated scene's splits: the training images and the held-out views.
pub struct Generated {
    pub train: Dataset,
    pub test: Dataset,
}

impl Generated {
    /// The training images shared, as a trainer takes them, and the held-out views.
    pub fn shared(self) -> (Arc<Dataset>, Dataset) {
        (Arc::new(self.train), self.test)
    }

    pub fn pair(self) -> (Dataset, Dataset) {
        (self.train, self.test)
    }
}

/// `kind` ray-traced at `res` px into `dir` (`n_train` training and `n_test` held-out views,
/// no validation split, in the unit box) from `seed`, then loaded at full size.
pub fn generated(
    dir: &Path,
    kind: SceneKind,
    res: u32,
    n_train: usize,
    n_test: usize,
    seed: u64,
) -> Generated {
    generate(
        &SynthOptions {
            scene: kind,
            resolution: res,
            n_train,
            n_val: 0,
            n_test,
            seed,
            aabb_scale: 1,
            ..Default::default()
        },
        dir,
    )
    .unwrap_or_else(|e| panic!("generating {}: {e}", dir.display()));
    let o = LoadOptions::default();
    let load = |split| {
        dataset::load(dir, split, &o).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()))
    };
    Generated {
        train: load(Split::Train),
        test: load(Split::Test),
    }
}
