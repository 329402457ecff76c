//! Training states (`train --resume`): a fresh tiny trainer takes back each case, plain
//! (`run.state`) or a cover and a hidden scene under stealth (`stealth.state`: the policy's
//! own state and its mechanisms'). A state holds the grid of every scene, so a case is
//! megabytes; CI runs fewer of them.

use crate::seeds::{self, Case};
use dataset::LoadOptions;
use ngp::data::{Dataset, Split};
use ngp::encoding::reference_indices;
use ngp::network::NerfLayout;
use ngp::train::{SceneSpec, Schedule, TrainConfig, Trainer};
use std::path::Path;
use std::sync::{Arc, OnceLock};
use stego::keys::SchemeKind;
use stego::stealth::{Stealth, StealthOptions};

static DATA: OnceLock<Result<Arc<Dataset>, String>> = OnceLock::new();

fn dataset() -> Result<Arc<Dataset>, String> {
    DATA.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("stegongp-fuzz-state-{}", std::process::id()));
        crate::runner::write_case(&dir, &seeds::transforms()[0]).map_err(|e| e.to_string())?;
        let opts = LoadOptions {
            aabb_scale: Some(1),
            ..Default::default()
        };
        dataset::load(&dir, Split::Train, &opts)
            .map(Arc::new)
            .map_err(|e| e.to_string())
    })
    .clone()
}

/// The tiny trainer, with a stealth policy and a hidden scene (the same images under a
/// fixed key) when `stealth`.
fn trainer(stealth: bool) -> Result<Trainer, String> {
    let model = seeds::tiny_config(1);
    let layout = NerfLayout::new(model).map_err(|e| e.to_string())?;
    let spec = || -> Result<SceneSpec, String> {
        Ok(SceneSpec {
            dataset: dataset()?,
            indices: reference_indices(&layout.grid),
        })
    };
    let scenes = if stealth {
        vec![spec()?, spec()?]
    } else {
        vec![spec()?]
    };
    let config = TrainConfig {
        seed: 1,
        batch_samples: 1 << 10,
        occupancy_fraction: 0.01,
        workers: 1,
        schedule: Schedule::RandomScene,
        ..Default::default()
    };
    let mut t = Trainer::new(model, scenes, config).map_err(|e| e.to_string())?;
    if stealth {
        let mut n = 0u64;
        let key = stego::keys::generate_with(SchemeKind::Prf, 4, || {
            n += 1;
            Ok(n.wrapping_mul(0x9e37_79b9_7f4a_7c15))
        })
        .map_err(|e| e.to_string())?;
        let options = StealthOptions {
            enabled: true,
            ..Default::default()
        };
        let policy = Stealth::new(layout, &[key], &options).map_err(|e| e.to_string())?;
        t.set_policy(Box::new(policy)).map_err(|e| e.to_string())?;
    }
    Ok(t)
}

pub fn seeds() -> Vec<Case> {
    let mut cases = Vec::new();
    for (name, stealth) in [("run.state", false), ("stealth.state", true)] {
        let mut t = trainer(stealth).expect("the tiny trainer");
        for steps in [1, 3] {
            while t.step < steps {
                t.train_step().expect("a step of the tiny trainer");
            }
            cases.push(vec![(name.to_string(), t.save_state().expect("a state"))]);
        }
    }
    cases
}

pub fn run(dir: &Path) -> Result<(), String> {
    let stealth = dir.join("stealth.state");
    let (path, stealth) = if stealth.exists() {
        (stealth, true)
    } else {
        (dir.join("run.state"), false)
    };
    let bytes = std::fs::read(&path).map_err(|e| e.to_string())?;
    let mut t = trainer(stealth)?;
    t.restore_state(&bytes, &path).map_err(|e| e.to_string())?;
    // What a resumed run does next: a step that fails says so, never panics.
    t.train_step().map_err(|e| e.to_string())?;
    Ok(())
}
