//! An attack as written on the command line: `NAME` or `NAME=VALUE`.

use crate::AttackContext;
use ngp::error::{Error, Result};

/// One attack and its strength.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Attack {
    /// Gaussian noise of standard deviation σ on every weight (grid and MLPs): `w + σ·N(0,1)`
    /// (not `σ²·N(0,1)`, which some codebases add).
    Noise { sigma: f32 },
    /// A fraction of the table's entries, drawn at random, set to zero.
    Prune { fraction: f32 },
    /// A fraction of the table's entries, smallest feature-vector norm first, set to zero.
    PruneMagnitude { fraction: f32 },
    /// Every grid level and MLP matrix to `bits`-bit integers (symmetric, absmax scale) and
    /// back.
    Quantise { bits: u32 },
    /// Entries the reference index cannot reach from the stored grid's occupied cells reset
    /// to the initialisation's range: no cover pixel changes.
    Purify,
    /// Entries whose contribution to the cover's renders (transmittance × opacity ×
    /// interpolation weight, a ray's mean over the stored cameras' views) is below ε reset
    /// to the initialisation's range.
    PurifyContribution { epsilon: f32 },
    /// `purify`, then the MLPs re-fitted for N steps on the cover's renders.
    PurifyMlp { steps: u32 },
    /// The MLPs re-fitted for N steps on the cover's renders, the table frozen.
    RefitMlp { steps: u32 },
    /// N steps of plain training on the cover's photos (`--data`), fresh Adam.
    Finetune { steps: u32 },
    /// N steps of plain training on renders of the cover from the stored cameras.
    FinetuneRenders { steps: u32 },
    /// A fresh plain model trained N steps on renders of the cover.
    Redistil { steps: u32 },
}

/// The attacks' names, for messages.
pub const NAMES: &str = "noise=σ, prune=F, prune-magnitude=F, quantise=8|4, purify, \
    purify-contribution=ε, purify-mlp=N, refit-mlp=N, finetune=N, finetune-renders=N, redistil=N";

/// Training steps an attack may ask for: beyond this it is a new model, not an edit.
pub const MAX_STEPS: u32 = 1_000_000;

impl std::str::FromStr for Attack {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        let (name, value) = match s.split_once('=') {
            Some((n, v)) => (n.trim(), Some(v.trim())),
            None => (s.trim(), None),
        };
        let bad = |why: String| Error::Config(format!("attack `{s}`: {why}"));
        let need = || value.ok_or_else(|| bad(format!("give a value: {name}=…")));
        let number = || -> Result<f32> {
            let v = need()?;
            v.parse::<f32>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad(format!("`{v}` is not a number")))
        };
        let fraction = || -> Result<f32> {
            let f = number()?;
            if (0.0..=1.0).contains(&f) {
                Ok(f)
            } else {
                Err(bad(format!("a fraction is between 0 and 1, not {f}")))
            }
        };
        let steps = || -> Result<u32> {
            let v = need()?;
            match v.parse::<u32>() {
                Ok(n) if (1..=MAX_STEPS).contains(&n) => Ok(n),
                _ => Err(bad(format!("`{v}` is not a step count in 1..={MAX_STEPS}"))),
            }
        };
        let no_value = |a: Attack| match value {
            None => Ok(a),
            Some(_) => Err(bad(format!("{name} takes no value"))),
        };
        match name {
            "noise" => {
                let sigma = number()?;
                if sigma < 0.0 {
                    return Err(bad(format!("σ is a standard deviation ≥ 0, not {sigma}")));
                }
                Ok(Attack::Noise { sigma })
            }
            "prune" => Ok(Attack::Prune {
                fraction: fraction()?,
            }),
            "prune-magnitude" => Ok(Attack::PruneMagnitude {
                fraction: fraction()?,
            }),
            "quantise" | "quantize" => match need()? {
                "8" => Ok(Attack::Quantise { bits: 8 }),
                "4" => Ok(Attack::Quantise { bits: 4 }),
                v => Err(bad(format!("quantise to 8 or 4 bits, not `{v}`"))),
            },
            "purify" => no_value(Attack::Purify),
            "purify-contribution" => {
                let epsilon = number()?;
                if epsilon < 0.0 {
                    return Err(bad(format!("ε is a contribution ≥ 0, not {epsilon}")));
                }
                Ok(Attack::PurifyContribution { epsilon })
            }
            "purify-mlp" => Ok(Attack::PurifyMlp { steps: steps()? }),
            "refit-mlp" => Ok(Attack::RefitMlp { steps: steps()? }),
            "finetune" => Ok(Attack::Finetune { steps: steps()? }),
            "finetune-renders" => Ok(Attack::FinetuneRenders { steps: steps()? }),
            "redistil" => Ok(Attack::Redistil { steps: steps()? }),
            _ => Err(bad(format!("unknown attack; one of {NAMES}"))),
        }
    }
}

impl std::fmt::Display for Attack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Attack::Noise { sigma } => write!(f, "noise={sigma}"),
            Attack::Prune { fraction } => write!(f, "prune={fraction}"),
            Attack::PruneMagnitude { fraction } => write!(f, "prune-magnitude={fraction}"),
            Attack::Quantise { bits } => write!(f, "quantise={bits}"),
            Attack::Purify => write!(f, "purify"),
            Attack::PurifyContribution { epsilon } => write!(f, "purify-contribution={epsilon}"),
            Attack::PurifyMlp { steps } => write!(f, "purify-mlp={steps}"),
            Attack::RefitMlp { steps } => write!(f, "refit-mlp={steps}"),
            Attack::Finetune { steps } => write!(f, "finetune={steps}"),
            Attack::FinetuneRenders { steps } => write!(f, "finetune-renders={steps}"),
            Attack::Redistil { steps } => write!(f, "redistil={steps}"),
        }
    }
}

impl Attack {
    /// The attack's name without its strength (`noise`), a family of a robustness curve.
    pub fn family(&self) -> &'static str {
        match self {
            Attack::Noise { .. } => "noise",
            Attack::Prune { .. } => "prune",
            Attack::PruneMagnitude { .. } => "prune-magnitude",
            Attack::Quantise { .. } => "quantise",
            Attack::Purify => "purify",
            Attack::PurifyContribution { .. } => "purify-contribution",
            Attack::PurifyMlp { .. } => "purify-mlp",
            Attack::RefitMlp { .. } => "refit-mlp",
            Attack::Finetune { .. } => "finetune",
            Attack::FinetuneRenders { .. } => "finetune-renders",
            Attack::Redistil { .. } => "redistil",
        }
    }

    /// The attack's strength as a number (σ, F, bits, ε, steps; 0 for `purify`).
    pub fn strength(&self) -> f64 {
        match *self {
            Attack::Noise { sigma } => sigma as f64,
            Attack::Prune { fraction } | Attack::PruneMagnitude { fraction } => fraction as f64,
            Attack::Quantise { bits } => bits as f64,
            Attack::Purify => 0.0,
            Attack::PurifyContribution { epsilon } => epsilon as f64,
            Attack::PurifyMlp { steps }
            | Attack::RefitMlp { steps }
            | Attack::Finetune { steps }
            | Attack::FinetuneRenders { steps }
            | Attack::Redistil { steps } => steps as f64,
        }
    }

    /// Whether the attack trains (and so costs minutes, not milliseconds).
    pub fn trains(&self) -> bool {
        matches!(
            self,
            Attack::PurifyMlp { .. }
                | Attack::RefitMlp { .. }
                | Attack::Finetune { .. }
                | Attack::FinetuneRenders { .. }
                | Attack::Redistil { .. }
        )
    }

    /// What the attack needs that `ctx` may lack.
    pub fn check(&self, ctx: &AttackContext) -> Result<()> {
        if matches!(self, Attack::Finetune { .. }) && ctx.data.is_none() {
            return Err(Error::Config(format!(
                "attack `{self}` trains on the cover's photos: give them with --data DIR \
                 (finetune-renders=N trains on renders of the cover instead)"
            )));
        }
        if self.trains() && ctx.render_side < 16 {
            return Err(Error::Config(format!(
                "--render-side {} is too small to train on (at least 16)",
                ctx.render_side
            )));
        }
        Ok(())
    }
}
