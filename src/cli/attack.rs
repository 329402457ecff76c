//! `stegongp attack MODEL --out ATTACKED ATTACK…`: what whoever downloads a model can do to
//! it (noise, pruning, quantisation, fine-tuning, purification, re-distillation), applied
//! left to right and written as an ordinary snapshot, so that `eval`, `render`, `detect`,
//! `view` and `mesh` read the result unchanged. A creator tests their own file with it
//! before publishing; the robustness experiment runs every attack through the same library.

use super::common::{check_model_path, progress};
use anyhow::{Context, Result, bail};
use serde::Serialize;
use std::path::PathBuf;
use stegongp::attack::{Applied, Attack, AttackContext, apply_all};
use stegongp::dataset::LoadOptions;
use stegongp::ngp::model::Model;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The model to attack (.ingp or .msgpack).
    pub model: PathBuf,
    /// The attacked model to write (.ingp or .msgpack): a plain snapshot.
    #[arg(long)]
    pub out: PathBuf,
    /// Attacks, applied left to right: noise=σ (standard deviation of w + σ·N(0,1) on the
    /// grid and MLPs), prune=F and prune-magnitude=F (zero a fraction F of the table's
    /// entries, at random or smallest first), quantise=8|4 (symmetric absmax per grid level
    /// and per MLP matrix, and back), purify (reset the entries the cover's stored grid
    /// cannot reach: no cover pixel changes), purify-contribution=ε (reset entries whose
    /// mean contribution to a ray of the cover's renders is below ε), purify-mlp=N (purify,
    /// then N steps re-fitting the MLPs on renders), refit-mlp=N, finetune=N (N steps on the
    /// cover's photos, --data), finetune-renders=N (on renders of the cover from the file's
    /// cameras), redistil=N (a fresh model trained N steps on renders).
    #[arg(required = true, value_parser = parse_attack, value_name = "ATTACK")]
    pub attacks: Vec<Attack>,
    /// The cover's photos, for finetune=N.
    #[arg(long, value_name = "DIR")]
    pub data: Option<PathBuf>,
    /// Integer downscale factor of --data's images.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// COLMAP / LLFF --data: the image folder to read (e.g. images_4).
    #[arg(long)]
    pub images: Option<String>,
    /// Seeds every random draw (noise, the entries pruned, the values purification
    /// resets to, the fine-tuning's rays).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The long side, in pixels, of the renders of the cover that finetune-renders,
    /// refit-mlp, purify-mlp, redistil and purify-contribution use (at most the stored
    /// cameras' size).
    #[arg(long, default_value_t = 200)]
    pub render_side: u32,
    /// The stored cameras rendered for them (at most; spread over the stored ones).
    #[arg(long, default_value_t = 64)]
    pub render_views: usize,
    /// Samples a training step of the attacks that train (the recipe's default).
    #[arg(long, default_value_t = 1 << 18)]
    pub batch: u32,
    /// Print what each attack did as JSON.
    #[arg(long)]
    pub json: bool,
}

/// clap's parser of an attack (`noise=0.001`), for `attack` and `experiment robustness`.
pub fn parse_attack(s: &str) -> std::result::Result<Attack, String> {
    s.parse().map_err(|e: stegongp::Error| e.to_string())
}

#[derive(Serialize)]
struct Report<'a> {
    model: &'a PathBuf,
    out: &'a PathBuf,
    seed: u64,
    attacks: Vec<Applied>,
}

pub fn run(a: Args) -> Result<()> {
    check_model_path(&a.out)?;
    if a.out.exists() && std::fs::canonicalize(&a.out).ok() == std::fs::canonicalize(&a.model).ok()
    {
        bail!(
            "{}: --out is the model being attacked; write the attacked model elsewhere",
            a.out.display()
        );
    }
    if a.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    let ctx = AttackContext {
        seed: a.seed,
        data: a.data.clone(),
        load: LoadOptions {
            downscale: a.downscale,
            images: a.images.clone(),
            aabb_scale: None,
        },
        render_side: a.render_side,
        render_views: a.render_views,
        batch: a.batch,
    };
    for attack in &a.attacks {
        attack.check(&ctx)?;
    }
    if let Some(d) = &a.data
        && !d.is_dir()
    {
        bail!("--data {}: not a folder", d.display());
    }
    let model = Model::load(&a.model)
        .with_context(|| format!("{}: cannot read the model", a.model.display()))?;
    let bar = progress(
        a.attacks.len() as u64,
        "{elapsed_precise} [{bar:30}] {pos}/{len} {msg}",
    );
    if a.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let chain: Vec<String> = a.attacks.iter().map(|x| x.to_string()).collect();
    bar.set_message(chain.join(" "));
    let (model, reports) = apply_all(model, &a.attacks, &ctx, |r| {
        if !a.json {
            bar.suspend(|| {
                eprintln!(
                    "{:<24} {:>10} weights changed, {:>9} of {} table entries, {:.1} s",
                    r.attack, r.params_changed, r.entries_changed, r.entries_total, r.seconds
                )
            });
        }
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    model
        .save(&a.out)
        .with_context(|| format!("{}: cannot write the attacked model", a.out.display()))?;
    if a.json {
        let report = Report {
            model: &a.model,
            out: &a.out,
            seed: a.seed,
            attacks: reports,
        };
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("wrote {}", a.out.display());
    }
    Ok(())
}
