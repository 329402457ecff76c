//! Training states (`train --resume`): a fresh tiny trainer takes back each case. A state
//! holds the grid of every scene, so a case is megabytes; CI runs fewer of them.

use crate::seeds::{self, Case};
use ngp::data::{Dataset, LoadOptions, Split};
use ngp::encoding::reference_indices;
use ngp::network::NerfLayout;
use ngp::train::{SceneSpec, TrainConfig, Trainer};
use std::path::Path;
use std::sync::{Arc, OnceLock};

static DATA: OnceLock<Result<Arc<Dataset>, String>> = OnceLock::new();

fn dataset() -> Result<Arc<Dataset>, String> {
    DATA.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("stegongp-fuzz-state-{}", std::process::id()));
        crate::runner::write_case(&dir, &seeds::transforms()[0]).map_err(|e| e.to_string())?;
        let opts = LoadOptions {
            aabb_scale: Some(1),
            ..Default::default()
        };
        Dataset::load(&dir, Split::Train, &opts)
            .map(Arc::new)
            .map_err(|e| e.to_string())
    })
    .clone()
}

fn trainer() -> Result<Trainer, String> {
    let model = seeds::tiny_config(1);
    let layout = NerfLayout::new(model).map_err(|e| e.to_string())?;
    let spec = SceneSpec {
        dataset: dataset()?,
        indices: reference_indices(&layout.grid),
    };
    let config = TrainConfig {
        seed: 1,
        batch_samples: 1 << 10,
        occupancy_fraction: 0.01,
        workers: 1,
        ..Default::default()
    };
    Trainer::new(model, vec![spec], config).map_err(|e| e.to_string())
}

pub fn seeds() -> Vec<Case> {
    let mut t = trainer().expect("the tiny trainer");
    t.train_step();
    let a = t.save_state().expect("a state");
    t.train_step();
    let b = t.save_state().expect("a state");
    vec![
        vec![("run.state".to_string(), a)],
        vec![("run.state".to_string(), b)],
    ]
}

pub fn run(dir: &Path) -> Result<(), String> {
    let path = dir.join("run.state");
    let bytes = std::fs::read(&path).map_err(|e| e.to_string())?;
    let mut t = trainer()?;
    t.restore_state(&bytes, &path).map_err(|e| e.to_string())?;
    // What a resumed run does next.
    t.train_step();
    Ok(())
}
