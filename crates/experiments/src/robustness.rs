//! What a hidden scene survives (`experiment robustness`): for each cover/hidden pair, a
//! plain model, a default stego model, a `--stealth` one and a `--robust` one, each
//! published (fp16, as its file is) and then attacked as whoever downloads it might
//! ([`attack`]: noise, pruning, quantisation, fine-tuning, purification, re-distillation),
//! every attack at every strength. Each attacked file is scored as a user would: the hidden
//! scene with its key, the cover without, beside the unattacked file's scores, an empty
//! render's and a wrong key's.
//!
//! Jobs: every model is one ([`Ctx::train`]), and so is every attacked file (it waits for
//! its model); the report reads them back. Attacked files are ordinary snapshots with a
//! sidecar, under `OUT/attacked/`.

use super::jobs::{Action, PlannedModel, is_placeholder, placeholder, slug};
use super::pairs::PairSpec;
use super::plot::{Panel, Series, save_panels};
use super::report::{Report, Table};
use super::setup::{
    Ctx, ExpConfig, Experiment, Scene, experiment_key, load_scene, reproducible_setup, setup_json,
};
use super::store::read_stored;
use attack::{Attack, AttackContext, apply};
use dataset::LoadOptions;
use ngp::choice::Choice;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::util::write_atomic;
use score::eval::EvalResult;
use serde_json::{Value, json};
use std::path::Path;
use stego::Key;
use stego::stealth::StealthOptions;
use training::recipe::HiddenOptions;

/// How a model of the experiment hides its scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// No hidden scene: the cover's own cost of each attack.
    Plain,
    Default,
    Stealth,
    Robust,
}

impl Choice for Mode {
    const ALL: &'static [Mode] = &[Mode::Plain, Mode::Default, Mode::Stealth, Mode::Robust];

    fn name(self) -> &'static str {
        match self {
            Mode::Plain => "plain",
            Mode::Default => "default",
            Mode::Stealth => "stealth",
            Mode::Robust => "robust",
        }
    }

    fn help(self) -> &'static str {
        match self {
            Mode::Plain => "no hidden scene: the cover's own cost of each attack",
            Mode::Default => "a hidden scene trained as `train --hidden` trains it",
            Mode::Stealth => "as `train --stealth`",
            Mode::Robust => "as `train --robust`",
        }
    }
}

impl Mode {
    fn hides(self) -> bool {
        self != Mode::Plain
    }

    /// The experiment's hidden options with this mode's stealth and robustness.
    fn training(self, base: &HiddenOptions) -> HiddenOptions {
        HiddenOptions {
            robust: self == Mode::Robust,
            stealth: StealthOptions {
                enabled: self == Mode::Stealth,
                ..base.stealth
            },
            ..*base
        }
    }

    fn colour(self) -> [f32; 3] {
        match self {
            Mode::Plain => [0.45, 0.45, 0.45],
            Mode::Default => [0.85, 0.2, 0.15],
            Mode::Stealth => [0.15, 0.45, 0.85],
            Mode::Robust => [0.1, 0.65, 0.25],
        }
    }
}

/// The experiment's own options.
#[derive(Clone, Debug)]
pub struct RobustnessOptions {
    pub pairs: Vec<PairSpec>,
    /// Every attack at every strength, each applied alone to each model.
    pub attacks: Vec<Attack>,
    pub modes: Vec<Mode>,
    /// The long side of the renders the attacks that train on renders use.
    pub render_side: u32,
}

/// The field's attacks at the strengths the issue and the papers use (Splats-in-Splats'
/// noise, GS-Hider's and SecureGS's pruning fractions), plus ours.
pub fn default_attacks() -> Vec<Attack> {
    let mut a = Vec::new();
    for sigma in [0.0005, 0.001, 0.005, 0.01] {
        a.push(Attack::Noise { sigma });
    }
    for fraction in [0.05, 0.10, 0.15, 0.25, 0.5] {
        a.push(Attack::Prune { fraction });
    }
    for fraction in [0.05, 0.10, 0.15, 0.25, 0.5] {
        a.push(Attack::PruneMagnitude { fraction });
    }
    a.extend([
        Attack::Quantise { bits: 8 },
        Attack::Quantise { bits: 4 },
        Attack::Purify,
    ]);
    for epsilon in [1e-8, 1e-7, 1e-6] {
        a.push(Attack::PurifyContribution { epsilon });
    }
    a.push(Attack::PurifyMlp { steps: 100 });
    for steps in [100, 500, 2000] {
        a.push(Attack::Finetune { steps });
    }
    for steps in [100, 500, 2000] {
        a.push(Attack::FinetuneRenders { steps });
    }
    a.push(Attack::Redistil { steps: 2000 });
    a
}

/// One file's scores: the cover without a key, and with a hidden scene its key's view
/// and a wrong key's.
struct Scores {
    cover: EvalResult,
    hidden: Option<EvalResult>,
    wrong: Option<EvalResult>,
    /// The hidden scene's render of the first held-out view.
    hidden_view: Vec<f32>,
}

impl Scores {
    /// One line for the log.
    fn summary(&self) -> String {
        let hidden = self
            .hidden
            .as_ref()
            .map_or("-".into(), |h| format!("{:.2} dB", h.psnr));
        format!("cover {:.2} dB, hidden {hidden}", self.cover.psnr)
    }
}

fn score(ctx: &Ctx, model: &Model, key: Option<&Key>) -> Result<Scores> {
    let (cover, _) = ctx.score(model, &Key::reference(), &ctx.cover)?;
    let Some(key) = key else {
        return Ok(Scores {
            cover,
            hidden: None,
            wrong: None,
            hidden_view: Vec::new(),
        });
    };
    let (hidden, hidden_view) = ctx.score(model, key, ctx.hidden(0))?;
    let (wrong, _) = ctx.score(model, &Key::wrong(ctx.cfg.seed ^ 0x77, key), ctx.hidden(0))?;
    Ok(Scores {
        cover,
        hidden: Some(hidden),
        wrong: Some(wrong),
        hidden_view,
    })
}

/// A model of `ctx`'s scenes as this run has it: trained here, read back from its job's
/// file, or (for a job that attacks it) read from the file its own job wrote.
fn model_of(ctx: &Ctx, key: Option<&Key>, label: &str) -> Result<(Model, String)> {
    let reference = Key::reference();
    let mut scenes: Vec<(&Scene, &Key)> = vec![(&ctx.cover, &reference)];
    if let Some(k) = key {
        scenes.push((ctx.hidden(0), k));
    }
    let trained = ctx.train(ctx.cfg.grid, &scenes, label)?;
    let id = format!("{}-{}", ctx.name, slug(label));
    let mut model = trained.model;
    if is_placeholder(&model) && matches!(*ctx.cfg.jobs, super::jobs::JobMode::One(_)) {
        // This process runs another job (an attack on this model): its file, if written.
        let path = ctx
            .cfg
            .out
            .join("models")
            .join(format!("{}.ingp", slug(label)));
        if path.exists() {
            model = Model::load(&path)?;
        }
    }
    Ok((model, id))
}

/// The attacked file of `source` (the published model of job `source_id`), as the run's
/// jobs say: made here, made as a job into `OUT/attacked/`, or read back.
fn attacked(
    ctx: &Ctx,
    source: &Model,
    source_id: &str,
    attack: &Attack,
    actx: &AttackContext,
) -> Result<Model> {
    let name = slug(&format!("{source_id} {attack}"));
    let path = ctx.cfg.out.join("attacked").join(format!("{name}.ingp"));
    let id = format!("{}-attack-{name}", ctx.name);
    let planned = PlannedModel {
        id: id.clone(),
        label: format!("{source_id} after {attack}"),
        output: path.clone(),
        inputs: actx.data.iter().cloned().collect(),
        after: vec![source_id.to_string()],
        steps: attack.trains().then_some(attack.strength() as u64),
        samples: attack
            .trains()
            .then_some(attack.strength() as u64 * actx.batch as u64),
        seconds: None,
    };
    let action = ctx.cfg.jobs.action(planned);
    let run = || -> Result<Model> {
        if is_placeholder(source) {
            return Err(Error::Other(format!(
                "{id} attacks the model of job {source_id}, which has not finished"
            )));
        }
        // As its file reads back (fp16), whether this process keeps it or a job stores it.
        apply(source.published()?, attack, actx)?.0.published()
    };
    if ctx.cfg.jobs.in_process() {
        return run();
    }
    let sidecar = json!({"format": 1, "experiment": ctx.name.name(), "source": source_id,
        "attack": attack.to_string(), "setup": reproducible_setup(ctx.cfg),
        "render_side": actx.render_side, "render_views": actx.render_views});
    match action {
        Action::PassOver => placeholder(source.config, &ctx.cover.train),
        Action::Train => {
            if read_stored(&path, &sidecar).is_none() {
                let m = run()?;
                std::fs::create_dir_all(path.parent().unwrap_or(Path::new(".")))
                    .map_err(|e| Error::io(&path, e))?;
                m.save(&path)?;
                let side = json!({"config": sidecar});
                let text =
                    serde_json::to_string_pretty(&side).map_err(|e| Error::Other(e.to_string()))?;
                write_atomic(&path.with_extension("json"), text.as_bytes())?;
            }
            placeholder(source.config, &ctx.cover.train)
        }
        Action::Read => match read_stored(&path, &sidecar) {
            Some(_) => Model::load(&path),
            None => {
                ctx.cfg.jobs.missing(&id, &path)?;
                placeholder(source.config, &ctx.cover.train)
            }
        },
    }
}

fn num(v: Option<f64>) -> Value {
    v.filter(|x| x.is_finite())
        .map_or(Value::Null, |x| json!(x))
}

/// One row of the full table.
fn row(pair: &str, mode: Mode, attack: &str, s: &Scores, base: &Scores, seconds: f64) -> Value {
    let h = s.hidden.as_ref();
    let hb = base.hidden.as_ref();
    json!({
        "pair": pair, "mode": mode.name(), "attack": attack,
        "cover_psnr": num(Some(s.cover.psnr)), "cover_ssim": num(Some(s.cover.ssim)),
        "cover_lpips": num(s.cover.lpips),
        "cover_loss_db": num(Some(base.cover.psnr - s.cover.psnr)),
        "hidden_psnr": num(h.map(|r| r.psnr)), "hidden_ssim": num(h.map(|r| r.ssim)),
        "hidden_lpips": num(h.and_then(|r| r.lpips)),
        "hidden_loss_db": num(h.zip(hb).map(|(r, b)| b.psnr - r.psnr)),
        "wrong_key_psnr": num(s.wrong.as_ref().map(|r| r.psnr)),
        "empty_psnr": num(h.map(|r| r.blank_psnr)),
        "attack_s": seconds,
    })
}

/// What the runs of one experiment collect: the table's rows and the picture grid's tiles.
#[derive(Default)]
struct Collected {
    rows: Vec<Value>,
    tiles: Vec<Vec<f32>>,
    tile_size: (u32, u32),
}

/// One pair's model of one mode, published and attacked by each attack, scored as this run
/// scores.
fn measure(
    cfg: &ExpConfig,
    opts: &RobustnessOptions,
    pi: usize,
    mode: Mode,
    out: &mut Collected,
) -> Result<()> {
    let pair = &opts.pairs[pi];
    let mcfg = ExpConfig {
        training: mode.training(&cfg.training),
        ..cfg.clone()
    };
    let cover = load_scene(&pair.cover, cfg.downscale, None)?;
    let hidden = load_scene(
        &pair.hidden,
        cfg.hidden_downscale,
        Some(cover.train.aabb_scale),
    )?;
    let pair_name = format!("{}+{}", cover.name, hidden.name);
    let key = experiment_key(cfg.scheme, 1, cfg.seed, pi as u64, &hidden)?
        .with_robust(mode == Mode::Robust);
    let ctx = Ctx {
        cfg: &mcfg,
        name: Experiment::Robustness,
        cover,
        hidden: vec![hidden],
    };
    let key = mode.hides().then_some(&key);
    let label = format!("{} {pair_name}", mode.name());
    let (model, id) = model_of(&ctx, key, &label)?;
    let published = if is_placeholder(&model) {
        model
    } else {
        model.published()?
    };
    let scores = |m: &Model| -> Result<Option<Scores>> {
        if !cfg.jobs.scores() || is_placeholder(m) {
            return Ok(None);
        }
        score(&ctx, m, key).map(Some)
    };
    let base = scores(&published)?;
    if let Some(b) = &base {
        ctx.log(&format!("  {label}: {}", b.summary()));
        out.rows.push(row(&pair_name, mode, "none", b, b, 0.0));
    }
    let actx = AttackContext {
        seed: cfg.seed,
        data: Some(pair.cover.clone()),
        load: LoadOptions {
            downscale: cfg.downscale,
            ..LoadOptions::default()
        },
        render_side: opts.render_side,
        render_views: 64,
        batch: cfg.batch,
    };
    let middle = middle_strengths(&opts.attacks);
    for attack in &opts.attacks {
        let t0 = std::time::Instant::now();
        let m = attacked(&ctx, &published, &id, attack, &actx)?;
        let secs = t0.elapsed().as_secs_f64();
        if let (Some(b), Some(s)) = (&base, scores(&m)?) {
            ctx.log(&format!("  {label} after {attack}: {}", s.summary()));
            out.rows
                .push(row(&pair_name, mode, &attack.to_string(), &s, b, secs));
            if pi == 0 && mode.hides() && middle.contains(attack) && !s.hidden_view.is_empty() {
                out.tiles.push(s.hidden_view);
                let t = &ctx.hidden(0).test;
                out.tile_size = (t.width, t.height);
            }
        }
    }
    Ok(())
}

/// Runs the experiment and writes its report into `cfg.out`.
pub fn run_robustness(cfg: &ExpConfig, opts: &RobustnessOptions) -> Result<Report> {
    if opts.pairs.is_empty() {
        return Err(Error::Config(
            "robustness needs at least one cover/hidden pair".into(),
        ));
    }
    if opts.attacks.is_empty() || opts.modes.is_empty() {
        return Err(Error::Config(
            "robustness needs at least one attack and one mode".into(),
        ));
    }
    std::fs::create_dir_all(&cfg.out).map_err(|e| Error::io(&cfg.out, e))?;
    let mut report = Report {
        name: Experiment::Robustness.name().into(),
        setup: setup_json(cfg),
        wall_clock: vec!["attack_s".into(), "threads".into(), "device".into()],
        ..Default::default()
    };
    let mut got = Collected::default();
    for pi in 0..opts.pairs.len() {
        for &mode in &opts.modes {
            measure(cfg, opts, pi, mode, &mut got)?;
        }
    }
    if !cfg.jobs.scores() {
        return Ok(report);
    }
    let mut table =
        Table::new("Every attack: the cover without a key, the hidden scene with its key");
    for r in &got.rows {
        table.push(r.clone());
    }
    report.tables.push(headlines(&got.rows, &opts.modes));
    report.tables.push(middle_table(&got.rows, &opts.attacks));
    report.tables.push(table);
    report.notes.push(NOTE.into());
    report.missing_jobs = cfg.jobs.missing_jobs();
    let curves = cfg.out.join("curves.png");
    save_curves(&curves, &got.rows, &opts.attacks, &opts.modes)?;
    if !got.tiles.is_empty() {
        let cols = middle_strengths(&opts.attacks).len();
        let (w, h) = got.tile_size;
        let grid = cfg.out.join("hidden_after_attacks.png");
        super::report::save_grid(&grid, &got.tiles, w, h, cols)?;
    }
    report.write(&cfg.out)?;
    Ok(report)
}

const NOTE: &str = "Each attack is applied alone to the published (fp16) file. Noise is \
    w + σ·N(0,1) (σ the standard deviation). `cover_loss_db` and `hidden_loss_db` are the \
    unattacked file's PSNR minus the attacked one's. The hidden scene is erased when its \
    PSNR falls to the wrong key's; `curves.png` has every strength, \
    `hidden_after_attacks.png` the hidden scene's first held-out view after each attack at \
    its middle strength (rows: modes, first pair).";

/// Each family's middle strength (the list's middle element for that family).
fn middle_strengths(attacks: &[Attack]) -> Vec<Attack> {
    let mut fams: Vec<&str> = Vec::new();
    for a in attacks {
        if !fams.contains(&a.family()) {
            fams.push(a.family());
        }
    }
    fams.iter()
        .map(|f| {
            let of: Vec<&Attack> = attacks.iter().filter(|a| a.family() == *f).collect();
            *of[of.len() / 2]
        })
        .collect()
}

fn f(v: &Value, k: &str) -> Option<f64> {
    v[k].as_f64()
}

/// Per pair and mode: the smallest cover loss at which the hidden scene falls to within
/// 1 dB of the wrong key's PSNR, and the attack that did it.
fn headlines(rows: &[Value], modes: &[Mode]) -> Table {
    let mut t = Table::new(
        "Headline: the cheapest erasure (the smallest cover loss at which the hidden scene falls within 1 dB of a wrong key's PSNR)",
    );
    let mut seen: Vec<(String, String)> = Vec::new();
    for r in rows {
        let key = (
            r["pair"].as_str().unwrap_or("").to_string(),
            r["mode"].as_str().unwrap_or("").to_string(),
        );
        if seen.contains(&key) || !modes.iter().any(|m| m.name() == key.1 && m.hides()) {
            continue;
        }
        seen.push(key.clone());
        let mut best: Option<(f64, String, f64)> = None;
        for s in rows
            .iter()
            .filter(|s| s["pair"] == r["pair"] && s["mode"] == r["mode"])
        {
            let (Some(h), Some(w), Some(c)) = (
                f(s, "hidden_psnr"),
                f(s, "wrong_key_psnr"),
                f(s, "cover_loss_db"),
            ) else {
                continue;
            };
            if h <= w + 1.0 && best.as_ref().is_none_or(|b| c < b.0) {
                best = Some((c, s["attack"].as_str().unwrap_or("").into(), h));
            }
        }
        t.push(match best {
            Some((c, a, h)) => json!({"pair": key.0, "mode": key.1, "cheapest_erasure": a,
                "cover_loss_db": c, "hidden_psnr_after": h}),
            None => json!({"pair": key.0, "mode": key.1, "cheapest_erasure": "none of the attacks",
                "cover_loss_db": null, "hidden_psnr_after": null}),
        });
    }
    t
}

/// The README's table: each mode × attack at its middle strength, hidden and cover PSNR.
fn middle_table(rows: &[Value], attacks: &[Attack]) -> Table {
    let mut t = Table::new(
        "Each attack at its middle strength (first pair): hidden PSNR with the key / cover PSNR",
    );
    let names: Vec<String> = std::iter::once("none".to_string())
        .chain(middle_strengths(attacks).iter().map(|a| a.to_string()))
        .collect();
    let first = rows
        .first()
        .map(|r| r["pair"].clone())
        .unwrap_or(Value::Null);
    for name in &names {
        let mut out = serde_json::Map::new();
        out.insert("attack".into(), json!(name));
        for r in rows
            .iter()
            .filter(|r| r["pair"] == first && r["attack"] == json!(name))
        {
            let mode = r["mode"].as_str().unwrap_or("");
            out.insert(format!("{mode} hidden"), r["hidden_psnr"].clone());
            out.insert(format!("{mode} cover"), r["cover_psnr"].clone());
        }
        t.push(Value::Object(out));
    }
    t
}

/// Hidden PSNR (solid) and cover PSNR (dashed) against strength, a panel per attack
/// family, the first pair.
fn save_curves(path: &Path, rows: &[Value], attacks: &[Attack], modes: &[Mode]) -> Result<()> {
    let first = rows
        .first()
        .map(|r| r["pair"].clone())
        .unwrap_or(Value::Null);
    let mut fams: Vec<&str> = Vec::new();
    for a in attacks {
        if !fams.contains(&a.family()) {
            fams.push(a.family());
        }
    }
    let panels: Vec<Panel> = fams
        .iter()
        .map(|fam| {
            let of: Vec<String> = attacks
                .iter()
                .filter(|a| a.family() == *fam)
                .map(|a| a.to_string())
                .collect();
            let xs: Vec<String> = std::iter::once("none".to_string())
                .chain(
                    of.iter()
                        .map(|a| a.split_once('=').map_or("-", |(_, v)| v).to_string()),
                )
                .collect();
            let mut series = Vec::new();
            for &m in modes {
                let ys = |field: &str| -> Vec<Option<f64>> {
                    std::iter::once("none".to_string())
                        .chain(of.iter().cloned())
                        .map(|a| {
                            rows.iter()
                                .find(|r| {
                                    r["pair"] == first
                                        && r["mode"] == m.name()
                                        && r["attack"] == json!(a)
                                })
                                .and_then(|r| f(r, field))
                        })
                        .collect()
                };
                if m.hides() {
                    series.push(Series {
                        label: format!("{} hidden", m.name()),
                        colour: m.colour(),
                        dashed: false,
                        ys: ys("hidden_psnr"),
                    });
                }
                series.push(Series {
                    label: format!("{} cover", m.name()),
                    colour: m.colour(),
                    dashed: true,
                    ys: ys("cover_psnr"),
                });
            }
            Panel {
                title: fam.to_string(),
                xs,
                series,
            }
        })
        .collect();
    save_panels(path, &panels, 4, (5.0, 40.0), 5.0)
}
