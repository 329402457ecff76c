//! One module per subcommand, plus what they share.

pub mod common;
pub mod convert;
pub mod demo;
pub mod detect;
pub mod eval;
pub mod experiment;
pub mod inspect;
pub mod keygen;
pub mod render;
pub mod synth;
pub mod train;

use anyhow::{Context, Result, bail};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use stegongp::backend::Device;
use stegongp::ngp::data::{Dataset, LoadOptions, Split};
use stegongp::ngp::model::Model;
use stegongp::ngp::network::NerfLayout;
use stegongp::ngp::train::SceneSpec;
use stegongp::stego::{Key, KeyVariant, OpenedScene, open_scene_on};

/// The hidden scenes of a `train --hidden … --key …` call, each with its key's indices.
pub fn stego_scenes(
    hidden: &[PathBuf],
    keys: &[PathBuf],
    layout: &NerfLayout,
    opts: &LoadOptions,
    aabb_scale: u32,
) -> Result<(Vec<SceneSpec>, Vec<Key>)> {
    if hidden.len() != keys.len() {
        bail!(
            "{} --hidden scene(s) but {} --key file(s): each hidden scene needs its own key",
            hidden.len(),
            keys.len()
        );
    }
    let mut loaded: Vec<(Key, &PathBuf)> = Vec::new();
    let mut out = Vec::new();
    for (h, kp) in hidden.iter().zip(keys) {
        let key = keygen::load_key_reporting(kp)?;
        key.validate_for(&layout.grid)
            .with_context(|| format!("{}: key does not fit this model", kp.display()))?;
        if key.is_reference() {
            bail!(
                "{}: this key is the reference index Π, which is the cover's: the hidden scene would overwrite it",
                kp.display()
            );
        }
        if let Some((_, other)) = loaded.iter().find(|(k, _)| k.same_index(&key)) {
            bail!(
                "{} and {}: two hidden scenes share one key and would overwrite each other",
                kp.display(),
                other.display()
            );
        }
        let mut data = Dataset::load(h, Split::Train, opts)?;
        data.fit_into_box(aabb_scale, key.scene_box())
            .with_context(|| format!("placing it with its key {}", kp.display()))?;
        out.push(SceneSpec {
            dataset: Arc::new(data),
            indices: key.level_indices(&layout.grid),
        });
        loaded.push((key, kp));
    }
    Ok((out, loaded.into_iter().map(|(k, _)| k).collect()))
}

/// What renders a model: without a key the cover; with a key (or one of its diagnostic
/// variants) the hidden scene it unlocks, confined as the model was trained when `stealth`.
pub fn scene_for_key(
    device: &Device,
    model: &Model,
    key: Option<&Path>,
    variant: Option<KeyVariant>,
    stealth: bool,
) -> Result<OpenedScene> {
    let Some(kp) = key else {
        if variant.is_some() {
            bail!("--key-variant needs --key");
        }
        if stealth {
            bail!("--stealth needs --key (it says how the hidden scene's key is applied)");
        }
        return Ok(open_scene_on(device, model, None, false, 0)?);
    };
    let mut key = keygen::load_key_reporting(kp)?;
    key.validate_for(&model.net.layout.grid)
        .with_context(|| format!("{}: key does not fit this model", kp.display()))?;
    if let Some(v) = variant {
        key = v.apply(&key);
    }
    Ok(open_scene_on(device, model, Some(&key), stealth, 0)?)
}
