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
use stegongp::ngp::data::{Dataset, LoadOptions, Split};
use stegongp::ngp::model::Model;
use stegongp::ngp::network::NerfLayout;
use stegongp::ngp::train::SceneSpec;
use stegongp::stego::{Key, Mixed, OpenedScene, open_scene};

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
        if let Some((_, other)) = loaded.iter().find(|(k, _)| *k == key) {
            bail!(
                "{} and {}: two hidden scenes share one key and would overwrite each other",
                kp.display(),
                other.display()
            );
        }
        let mut data = Dataset::load(h, Split::Train, opts)?;
        data.fit_into_box(aabb_scale)?;
        out.push(SceneSpec {
            dataset: Arc::new(data),
            indices: key.level_indices(&layout.grid),
        });
        loaded.push((key, kp));
    }
    Ok((out, loaded.into_iter().map(|(k, _)| k).collect()))
}

/// Diagnostic variants of a key, for experiments by hand.
#[derive(Clone, Debug)]
pub enum KeyVariant {
    Partial(f64),
    Levels(f64),
    Mixed(Mixed),
    Wrong(u64),
}

pub fn parse_key_variant(s: &str) -> Result<KeyVariant> {
    let (kind, val) = s.split_once(':').unwrap_or((s, ""));
    Ok(match kind {
        "partial" | "levels" => {
            let p: f64 = val.trim_end_matches('%').parse().with_context(|| {
                format!(
                    "--key-variant {s}: expected {kind}:FRACTION, e.g. {kind}:0.5 or {kind}:50%"
                )
            })?;
            let p = if val.ends_with('%') { p / 100.0 } else { p };
            if !(0.0..=1.0).contains(&p) {
                bail!("--key-variant {s}: the fraction must be in [0, 1]");
            }
            if kind == "partial" {
                KeyVariant::Partial(p)
            } else {
                KeyVariant::Levels(p)
            }
        }
        "mixed" => match val {
            "pi1k2k3" => KeyVariant::Mixed(Mixed::Pi1K2K3),
            "pi1pi2k3" => KeyVariant::Mixed(Mixed::Pi1Pi2K3),
            _ => bail!("--key-variant {s}: expected mixed:pi1k2k3 or mixed:pi1pi2k3"),
        },
        "wrong" if val.is_empty() => KeyVariant::Wrong(1),
        "wrong" => KeyVariant::Wrong(val.parse().with_context(|| {
            format!("--key-variant {s}: expected wrong or wrong:SEED (a whole number)")
        })?),
        _ => bail!(
            "--key-variant {s}: expected partial:P, levels:P, mixed:pi1k2k3, mixed:pi1pi2k3 or wrong[:SEED]"
        ),
    })
}

/// What renders a model: without a key the cover; with a key (or one of its diagnostic
/// variants) the hidden scene it unlocks, confined as the model was trained when `stealth`.
pub fn scene_for_key(
    model: &Model,
    key: Option<&Path>,
    variant: Option<&str>,
    stealth: bool,
) -> Result<OpenedScene> {
    let Some(kp) = key else {
        if variant.is_some() {
            bail!("--key-variant needs --key");
        }
        if stealth {
            bail!("--stealth needs --key (it says how the hidden scene's key is applied)");
        }
        return Ok(open_scene(model, None, false, 0));
    };
    let mut key = keygen::load_key_reporting(kp)?;
    key.validate_for(&model.net.layout.grid)
        .with_context(|| format!("{}: key does not fit this model", kp.display()))?;
    if let Some(v) = variant {
        key = match parse_key_variant(v)? {
            KeyVariant::Partial(p) => key.partial(p),
            KeyVariant::Levels(p) => key.disclose_levels(p),
            KeyVariant::Mixed(m) => key.mixed(m),
            KeyVariant::Wrong(seed) => Key::wrong(seed, &key),
        };
    }
    Ok(open_scene(model, Some(&key), stealth, 0))
}

#[cfg(test)]
mod tests {
    use super::{KeyVariant, parse_key_variant};
    use stegongp::stego::Mixed;

    #[test]
    fn key_variants_parse_and_bad_ones_are_refused() {
        assert!(matches!(parse_key_variant("partial:0.5"), Ok(KeyVariant::Partial(p)) if p == 0.5));
        assert!(
            matches!(parse_key_variant("partial:75%"), Ok(KeyVariant::Partial(p)) if p == 0.75)
        );
        assert!(matches!(parse_key_variant("levels:25%"), Ok(KeyVariant::Levels(p)) if p == 0.25));
        assert!(matches!(
            parse_key_variant("mixed:pi1k2k3"),
            Ok(KeyVariant::Mixed(Mixed::Pi1K2K3))
        ));
        assert!(matches!(
            parse_key_variant("wrong:7"),
            Ok(KeyVariant::Wrong(7))
        ));
        assert!(matches!(
            parse_key_variant("wrong"),
            Ok(KeyVariant::Wrong(1))
        ));
        for bad in [
            "wrong:x",
            "partial:25",
            "partial:x",
            "levels:-1",
            "mixed:k1",
            "half",
            "partial",
        ] {
            assert!(parse_key_variant(bad).is_err(), "{bad}");
        }
    }
}
