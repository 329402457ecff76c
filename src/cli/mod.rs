//! One module per subcommand, plus what they share.

pub mod attack;
pub mod common;
pub mod convert;
pub mod demo;
pub mod detect;
pub mod devices;
pub mod eval;
pub mod experiment;
pub mod inspect;
pub mod keygen;
pub mod mesh;
pub mod process;
pub mod render;
pub mod synth;
pub mod train;
pub mod video;
pub mod view;

use anyhow::{Context, Result, bail};
use std::path::PathBuf;
use stegongp::backend::Device;
use stegongp::ngp::model::Model;
use stegongp::stego::{Key, KeyVariant, OpenedScene, open_scene_on};

/// How a subcommand that renders sees a model: through an optional key.
#[derive(clap::Args, Debug, Clone)]
pub struct KeyArgs {
    /// Key file: the hidden scene it unlocks instead of the cover.
    #[arg(long)]
    pub key: Option<PathBuf>,
    /// Diagnostic variant of --key: partial:P (the first P of the m keys, the rest Π; for
    /// prf the first P of the secret's m shares, the rest zero), levels:P (the subkeys of the
    /// first P of the m level groups, the other levels Π), mixed:pi1k2k3, mixed:pi1pi2k3,
    /// wrong[:SEED].
    #[arg(long)]
    pub key_variant: Option<KeyVariant>,
    /// The model was trained with `train --stealth`: apply --key as stealth training did
    /// (confined to the cover's reachable table entries, computed from the stored grid).
    #[arg(long)]
    pub stealth: bool,
    /// The model was trained with `train --robust`: apply --key confined to the entries the
    /// cover's stored grid reaches. A key file that training used records it already
    /// (`"robust": true`); this is for a copy made before.
    #[arg(long)]
    pub robust: bool,
}

impl KeyArgs {
    /// The key asked for (its variant applied), checked against `model`; None for the cover.
    pub fn load(&self, model: &Model) -> Result<Option<Key>> {
        let Some(kp) = &self.key else {
            if self.key_variant.is_some() {
                bail!("--key-variant needs --key");
            }
            if self.stealth || self.robust {
                bail!(
                    "--stealth and --robust need --key (they say how the hidden scene's key is applied)"
                );
            }
            return Ok(None);
        };
        let mut key = keygen::load_key_reporting(kp)?;
        key.validate_for(&model.net.layout.grid)
            .with_context(|| format!("{}: key does not fit this model", kp.display()))?;
        if self.robust {
            key = key.with_robust(true);
        }
        if let Some(v) = self.key_variant {
            key = v.apply(&key);
        }
        Ok(Some(key))
    }

    /// What renders `model`: without a key the cover; with a key (or one of its diagnostic
    /// variants) the hidden scene it unlocks, confined as the model was trained when
    /// `--stealth`.
    pub fn scene(&self, device: &Device, model: &Model) -> Result<OpenedScene> {
        let key = self.load(model)?;
        Ok(open_scene_on(device, model, key.as_ref(), self.stealth, 0)?)
    }
}
