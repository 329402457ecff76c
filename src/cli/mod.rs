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
pub mod video;
pub mod view;

use anyhow::{Context, Result, bail};
use std::path::Path;
use stegongp::backend::Device;
use stegongp::ngp::model::Model;
use stegongp::stego::{KeyVariant, OpenedScene, open_scene_on};

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
