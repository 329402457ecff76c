//! The paper's smaller experiments (fidelity, key sensitivity, partial keys, several hidden
//! scenes, table size, key strength), and the dispatch of every experiment by name.

use super::report::{Report, Table};
use super::setup::{Ctx, ExpConfig, Experiment, Scene, experiment_key, load_scene, setup_json};
use ngp::encoding::GridConfig;
use ngp::error::{Error, Result};
use ngp::network::{ModelConfig, NerfLayout};
use serde_json::json;
use stego::{Key, Mixed, SchemeKind, generate_prf, generate_primes, key_strength};

/// Runs experiment `name` and writes its report into `cfg.out`.
pub fn run_experiment(name: Experiment, cfg: &ExpConfig) -> Result<Report> {
    std::fs::create_dir_all(&cfg.out).map_err(|e| Error::io(&cfg.out, e))?;
    if name == Experiment::Detectability {
        // It generates its own population of scenes; the CLI passes its options directly.
        return super::detectability::run_detectability(
            cfg,
            &super::detectability::DetectOptions::default(),
        );
    }
    if name == Experiment::Pairs {
        // The cover with each hidden scene; the CLI passes its own pairs and options.
        let opts = super::pairs::PairsOptions {
            pairs: super::pairs::cover_with_each(&cfg.cover, &cfg.hidden),
            minutes: None,
            lpips: cfg.lpips,
        };
        return super::pairs::run_pairs(cfg, &opts);
    }
    if name == Experiment::Robustness {
        let opts = super::robustness::RobustnessOptions {
            pairs: super::pairs::cover_with_each(&cfg.cover, &cfg.hidden),
            attacks: super::robustness::default_attacks(),
            modes: <super::robustness::Mode as ngp::choice::Choice>::ALL.to_vec(),
            render_side: 200,
        };
        return super::robustness::run_robustness(cfg, &opts);
    }
    let mut report = Report {
        name: name.to_string(),
        setup: setup_json(cfg),
        wall_clock: wall_clock_fields(name),
        ..Default::default()
    };
    if name == Experiment::KeyStrength {
        // Trains no model: a plan has no job but the report, which measures on its node.
        if cfg.jobs.scores() {
            key_strength_report(cfg, &mut report)?;
            report.write(&cfg.out)?;
        }
        return Ok(report);
    }
    if cfg.hidden.is_empty() {
        return Err(Error::Config(
            "this experiment needs at least one hidden scene".into(),
        ));
    }
    let cover = load_scene(&cfg.cover, cfg.downscale, None)?;
    let box_scale = Some(cover.train.aabb_scale);
    let ctx = Ctx {
        cfg,
        name,
        cover,
        hidden: cfg
            .hidden
            .iter()
            .map(|h| load_scene(h, cfg.hidden_downscale, box_scale))
            .collect::<Result<_>>()?,
    };
    match name {
        Experiment::Fidelity => fidelity(&ctx, &mut report)?,
        Experiment::KeySensitivity => key_sensitivity(&ctx, &mut report)?,
        Experiment::PartialKeys => partial_keys(&ctx, &mut report)?,
        Experiment::MultiHidden => multi_hidden(&ctx, &mut report)?,
        Experiment::TableSize => table_size(&ctx, &mut report)?,
        Experiment::KeyStrength
        | Experiment::Detectability
        | Experiment::Pairs
        | Experiment::Robustness => {
            unreachable!("run above")
        }
    }
    if cfg.jobs.scores() {
        report.missing_jobs = cfg.jobs.missing_jobs();
        report.write(&cfg.out)?;
    }
    Ok(report)
}

/// The fields of `name`'s report that are wall-clock or host figures: the machine's, and
/// the times of training (recorded when a model was trained) and of key trials.
fn wall_clock_fields(name: Experiment) -> Vec<String> {
    let mut v: Vec<&str> = super::setup::HOST_FIELDS.to_vec();
    v.extend(match name {
        Experiment::Fidelity => &["train_s", "samples_per_s"][..],
        Experiment::TableSize => &["train_s"],
        Experiment::KeyStrength => &[
            "trial_ms",
            "derive_ms",
            "index_ms",
            "brute_force_years",
            "brute_force_years_index_only",
            "brute_force_years_log10",
            "oracle_years",
        ],
        _ => &[],
    });
    v.into_iter().map(String::from).collect()
}

fn fidelity(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    let key = experiment_key(ctx.cfg.scheme, 1, ctx.cfg.seed, 0, h)?;
    ctx.log("fidelity: plain cover, plain hidden, stego (cover + hidden)");
    let plain_c = ctx.train(ctx.cfg.grid, &[(&ctx.cover, &pi)], "plain cover")?;
    let plain_h = ctx.train(ctx.cfg.grid, &[(h, &pi)], "plain hidden")?;
    let stego = ctx.train(ctx.cfg.grid, &[(&ctx.cover, &pi), (h, &key)], "stego")?;
    let (pc, img_pc) = ctx.score(&plain_c.model, &pi, &ctx.cover)?;
    let (ph, img_ph) = ctx.score(&plain_h.model, &pi, h)?;
    let (sc, img_sc) = ctx.score(&stego.model, &pi, &ctx.cover)?;
    let (sh, img_sh) = ctx.score(&stego.model, &key, h)?;
    let mut t = Table::new("Fidelity at the same per-scene step and sample budget");
    for (model, scene, r, tr) in [
        ("plain", &ctx.cover.name, &pc, &plain_c),
        ("stego (no key)", &ctx.cover.name, &sc, &stego),
        ("plain", &h.name, &ph, &plain_h),
        ("stego (key)", &h.name, &sh, &stego),
    ] {
        t.push(json!({"model": model, "scene": scene, "psnr": r.psnr, "ssim": r.ssim, "lpips": r.lpips, "views": r.n_views,
            "train_s": tr.seconds, "samples_per_s": tr.samples_per_s.round()}));
    }
    report.tables.push(t);
    report.notes.push(format!(
        "Cover: stego − plain = {:+.2} dB. Hidden: stego − plain = {:+.2} dB. Key scheme {}.",
        sc.psnr - pc.psnr,
        sh.psnr - ph.psnr,
        ctx.cfg.scheme.name()
    ));
    let (w, hgt) = ctx.size();
    ctx.save_grid(
        "fidelity.png",
        &[
            ctx.gt(&ctx.cover),
            img_pc,
            img_sc,
            ctx.gt(h),
            img_ph,
            img_sh,
        ],
        w,
        hgt,
        3,
    )?;
    report.figures.push(("fidelity.png".into(), "Rows: cover, hidden. Columns: ground truth, plain model, stego model (cover without key, hidden with key).".into()));
    Ok(())
}

fn key_sensitivity(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    for scheme in [SchemeKind::Primes, SchemeKind::Prf] {
        let key = experiment_key(scheme, 1, ctx.cfg.seed, 0, h)?;
        ctx.log(&format!("key-sensitivity ({}): stego model", scheme.name()));
        let stego = ctx.train(ctx.cfg.grid, &[(&ctx.cover, &pi), (h, &key)], scheme.name())?;
        let variants = [
            ("default Π", pi.clone()),
            ("secret key", key.clone()),
            (
                if scheme == SchemeKind::Primes {
                    "{π1,k2,k3}"
                } else {
                    "1/3 of secret zeroed"
                },
                key.mixed(Mixed::Pi1K2K3),
            ),
            (
                if scheme == SchemeKind::Primes {
                    "{π1,π2,k3}"
                } else {
                    "2/3 of secret zeroed"
                },
                key.mixed(Mixed::Pi1Pi2K3),
            ),
            ("wrong key", Key::wrong(ctx.cfg.seed ^ 0xbad, &key)),
        ];
        let mut t = Table::new(&format!(
            "Key sensitivity, {} scheme: PSNR of each rendering against both scenes",
            scheme.name()
        ));
        let mut tiles = vec![ctx.gt(&ctx.cover), ctx.gt(h)];
        for (label, k) in &variants {
            let (vs_hidden, img) = ctx.score(&stego.model, k, h)?;
            let (vs_cover, _) = ctx.score(&stego.model, k, &ctx.cover)?;
            t.push(json!({"key": label, "psnr_vs_hidden": vs_hidden.psnr, "ssim_vs_hidden": vs_hidden.ssim, "lpips_vs_hidden": vs_hidden.lpips,
                "psnr_vs_cover": vs_cover.psnr, "empty_render_vs_hidden": vs_hidden.blank_psnr}));
            tiles.push(img);
        }
        report.tables.push(t);
        let (w, hgt) = ctx.size();
        let file = format!("key_sensitivity_{}.png", scheme.name());
        ctx.save_grid(&file, &tiles, w, hgt, tiles.len())?;
        report.figures.push((
            file,
            format!(
                "{}: cover GT, hidden GT, then renderings with: {}",
                scheme.name(),
                variants.iter().map(|v| v.0).collect::<Vec<_>>().join(", ")
            ),
        ));
    }
    Ok(())
}

/// A way of giving part of a key: `Key::partial` or `Key::disclose_levels`.
type Disclose = fn(&Key, f64) -> Key;

fn partial_keys(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    let fractions = [0.0, 0.25, 0.5, 0.75, 1.0];
    let mut t = Table::new(
        "Partial key disclosure: hidden-scene PSNR when the first p % of the m keys are given (the rest replaced by Π)",
    );
    let (w, hgt) = ctx.size();
    for scheme in [SchemeKind::Primes, SchemeKind::Prf] {
        for m in [4usize, 8, 16] {
            if m > ctx.cfg.grid.n_levels as usize {
                continue;
            }
            let key = experiment_key(scheme, m, ctx.cfg.seed, 0, h)?;
            ctx.log(&format!("partial-keys: {} m = {m}", scheme.name()));
            let stego = ctx.train(
                ctx.cfg.grid,
                &[(&ctx.cover, &pi), (h, &key)],
                &format!("{} m={m}", scheme.name()),
            )?;
            let (wrong, _) = ctx.score(&stego.model, &Key::wrong(ctx.cfg.seed ^ 0x77, &key), h)?;
            // prf: partial key material (all-or-nothing), then leaked level subkeys (the
            // paper's per-level substitution); primes: the two are the same.
            let variants: Vec<(&str, Disclose)> = match scheme {
                SchemeKind::Primes => vec![("keys", Key::partial)],
                SchemeKind::Prf => vec![
                    ("secret shares", Key::partial),
                    ("level subkeys", Key::disclose_levels),
                ],
            };
            for (given, disclose) in variants {
                let mut row = serde_json::Map::new();
                row.insert("scheme".into(), json!(scheme.name()));
                row.insert("m".into(), json!(m));
                row.insert("given".into(), json!(given));
                let mut tiles = vec![];
                for &p in &fractions {
                    let (r, img) = ctx.score(&stego.model, &disclose(&key, p), h)?;
                    row.insert(format!("{}%", (p * 100.0) as u32), json!(r.psnr));
                    if p == 1.0 {
                        row.insert("LPIPS 100%".into(), json!(r.lpips));
                    }
                    tiles.push(img);
                }
                row.insert("wrong key".into(), json!(wrong.psnr));
                row.insert("LPIPS wrong key".into(), json!(wrong.lpips));
                row.insert("empty render".into(), json!(wrong.blank_psnr));
                t.push(serde_json::Value::Object(row));
                let file = format!(
                    "partial_{}_{}_m{m}.png",
                    scheme.name(),
                    given.replace(' ', "_")
                );
                ctx.save_grid(&file, &tiles, w, hgt, tiles.len())?;
                report.figures.push((
                    file,
                    format!(
                        "{} m = {m}, {given} given: 0, 25, 50, 75, 100 %",
                        scheme.name()
                    ),
                ));
            }
        }
    }
    report.tables.push(t);
    report.notes.push("`primes`: the first p % of the m prime triples are given, the rest replaced by Π (the paper's ablation). `prf`, secret shares: the first p % of the secret's m equal shares are given, the rest zero; every level's subkey depends on the whole secret, so a partial key should score like a wrong key. `prf`, level subkeys: the subkeys of the first p % of the level groups leak (a side channel the key file never offers), the other levels use Π — the paper's substitution applied to `prf`. 0 % is no key at all (the cover) in every row. `empty render` is the score of an image of background colour only: a rendering that tells nothing about the hidden scene scores near it (a wrong key renders a faint haze, so it scores near the empty render rather than near the cover, an opaque object).".into());
    Ok(())
}

fn multi_hidden(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let mut t = Table::new("Several hidden scenes in one model (Φ), each with its own key");
    let (w, hgt) = ctx.size();
    let mut tiles = vec![];
    for phi in 1..=4usize {
        let keys: Vec<Key> = (0..phi)
            .map(|i| experiment_key(ctx.cfg.scheme, 1, ctx.cfg.seed, i as u64, ctx.hidden(i)))
            .collect::<Result<_>>()?;
        let mut scenes: Vec<(&Scene, &Key)> = vec![(&ctx.cover, &pi)];
        for (i, k) in keys.iter().enumerate() {
            scenes.push((ctx.hidden(i), k));
        }
        ctx.log(&format!("multi-hidden: Φ = {phi}"));
        let m = ctx.train(ctx.cfg.grid, &scenes, &format!("Φ={phi}"))?;
        let (c, img_c) = ctx.score(&m.model, &pi, &ctx.cover)?;
        let mut row = serde_json::Map::new();
        row.insert("phi".into(), json!(phi));
        row.insert("cover".into(), json!(c.psnr));
        row.insert("cover LPIPS".into(), json!(c.lpips));
        tiles.push(img_c);
        let (mut hs, mut hl) = (vec![], vec![]);
        for (i, k) in keys.iter().enumerate() {
            let (r, img) = ctx.score(&m.model, k, ctx.hidden(i))?;
            row.insert(format!("hidden {}", i + 1), json!(r.psnr));
            hs.push(r.psnr);
            hl.extend(r.lpips);
            if i == 0 {
                tiles.push(img);
            }
        }
        row.insert(
            "hidden mean".into(),
            json!(hs.iter().sum::<f64>() / hs.len() as f64),
        );
        row.insert(
            "hidden mean LPIPS".into(),
            json!((!hl.is_empty()).then(|| hl.iter().sum::<f64>() / hl.len() as f64)),
        );
        t.push(serde_json::Value::Object(row));
    }
    report.tables.push(t);
    ctx.save_grid("multi_hidden.png", &tiles, w, hgt, 2)?;
    report.figures.push((
        "multi_hidden.png".into(),
        "Rows Φ = 1..4: the cover without key, hidden scene 1 with its key".into(),
    ));
    Ok(())
}

fn table_size(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    let key = experiment_key(ctx.cfg.scheme, 1, ctx.cfg.seed, 0, h)?;
    let mut t = Table::new("Hash table size T");
    for log2_t in 18..=21u32 {
        let grid = GridConfig {
            log2_hashmap_size: log2_t,
            ..ctx.cfg.grid
        };
        ctx.log(&format!("table-size: T = 2^{log2_t}"));
        let m = ctx.train(
            grid,
            &[(&ctx.cover, &pi), (h, &key)],
            &format!("T=2^{log2_t}"),
        )?;
        let (c, _) = ctx.score(&m.model, &pi, &ctx.cover)?;
        let (hs, _) = ctx.score(&m.model, &key, h)?;
        t.push(json!({"T": format!("2^{log2_t}"), "params": m.model.net.layout.n_params, "cover_psnr": c.psnr,
            "cover_lpips": c.lpips, "hidden_psnr": hs.psnr, "hidden_lpips": hs.lpips, "train_s": m.seconds}));
    }
    report.tables.push(t);
    Ok(())
}

fn key_strength_report(cfg: &ExpConfig, report: &mut Report) -> Result<()> {
    use stego::strength::{PROBE_POINTS, brute_force_years_log10, format_pow10, key_trial_cost};
    use stego::{DenseMode, KeyScheme};
    let layout = NerfLayout::new(ModelConfig {
        grid: cfg.grid,
        aabb_scale: 1,
    })?;
    let levels = cfg.grid.n_levels as usize;
    // Strength depends on the scheme, m and the grid, not on the key's values.
    let legacy = |m: usize| {
        Key::new(
            KeyScheme::PrfShares {
                secret: [0x5a; 32],
                m,
            },
            DenseMode::default(),
        )
    };
    let mut t = Table::new("Effective key space, from the index arithmetic actually used");
    let mut costs = Table::new(&format!(
        "Cost of one key trial on this machine, one core ({PROBE_POINTS} probe points × {levels} levels × 8 corners; median of 7 warm runs)"
    ));
    // The paper's brute-force column (RTX 5090 at 20 FPS): a figure for the basic model
    // (m = 1), "computationally infeasible" for the multi-key one (m = 16), nothing else.
    let paper_years = |scheme: &str, m: usize| match (scheme, m) {
        ("primes", 1) => json!("7.43e16"),
        ("primes", 16) => json!("infeasible"),
        _ => json!(null),
    };
    for (label, key) in [
        ("primes m=1", generate_primes(1)?),
        ("primes m=4", generate_primes(4)?),
        ("primes m=16", generate_primes(16.min(levels))?),
        ("prf", generate_prf(1)?),
        ("prf m=16", generate_prf(16.min(levels))?),
    ] {
        let s = key_strength(&key, &layout.grid);
        let c = key_trial_cost(key.scheme().kind(), s.m, &layout.grid, PROBE_POINTS, 7, 2)?;
        let years = |bits: f64, secs: f64| brute_force_years_log10(bits, secs).map(format_pow10);
        t.push(
            json!({"key": label, "scheme": s.scheme, "m": s.m, "total_bits": s.total_bits,
            "per_level_oracle_bits": s.oracle_bits, "paper_claim_bits": s.paper_claim_bits,
            "trial_ms": round2(c.trial_seconds * 1e3),
            "brute_force_years": years(s.total_bits, c.trial_seconds),
            "paper_brute_force_years": paper_years(&s.scheme, s.m),
            "oracle_years": years(s.oracle_bits, c.trial_seconds)}),
        );
        costs.push(
            json!({"key": label, "trial_ms": round2(c.trial_seconds * 1e3),
            "derive_ms": round2(c.derive_seconds * 1e3),
            "index_ms": round2(c.index_seconds * 1e3),
            "brute_force_years": years(s.total_bits, c.trial_seconds),
            "brute_force_years_index_only": years(s.total_bits, c.index_seconds),
            "brute_force_years_log10": brute_force_years_log10(s.total_bits, c.trial_seconds)
                .map(round2)}),
        );
    }
    report.tables.push(t);
    report.tables.push(costs);
    report.notes.push(format!(
        "Brute-force time: 2^(bits−1) trials (half the space on average) × the measured seconds of one trial, in Julian years (3.156e7 s). \
         A trial derives the candidate key's index functions (per-level subkeys, the dense levels' keyed permutation tables) and indexes {PROBE_POINTS} fixed probe points on every level (8 corners each), compared with the true key's indices: the fewest points that tell a scene from noise (a few dozen rays' samples); the MLP, which a real test also needs, is left out, so a real trial costs more. \
         index_ms is the trial without the derivation (index functions already built): no trial costs less, so brute_force_years_index_only, which uses it, is a lower bound (an attacker who permutes only the probes' dense-level corners, lazily, pays between index_ms and trial_ms). \
         The figures are for one CPU core of this machine: n cores, or a GPU running n trials at once, divide them by n. \
         paper_brute_force_years: the paper's table (RTX 5090 at 20 rendered frames a second, an ideal classifier): 7.43e16 years for the basic model (86.3 bits), 'computationally infeasible' for m = 16; it has no prf. \
         oracle_years: the same trial cost at per_level_oracle_bits (each group, or level, searched on its own)."
    ));
    let mut d =
        Table::new("Bits left when j of the m keys are disclosed (worst case over which j)");
    let mut ms: Vec<usize> = [1, 4, 8, 16].into_iter().filter(|&m| m <= levels).collect();
    ms.dedup();
    for (scheme, make) in [
        ("primes", &generate_primes as &dyn Fn(usize) -> Result<Key>),
        ("prf", &generate_prf),
        ("prf v1 (old shares)", &legacy),
    ] {
        for &m in &ms {
            let s = key_strength(&make(m)?, &layout.grid);
            for x in &s.after_disclosure {
                d.push(json!({"scheme": scheme, "m": m, "disclosed": x.disclosed,
                    "left": m - x.disclosed, "brute_force_bits": round2(x.brute_force_bits),
                    "oracle_bits": round2(x.oracle_bits)}));
            }
        }
    }
    report.tables.push(d);
    report.notes.push("total_bits: brute-force work for the whole key set; per_level_oracle_bits: work when each level group can be attacked on its own (the paper's partial-key table shows PSNR rises with each correct key, which is such an oracle for `primes`).".into());
    report.notes.push(format!(
        "Disclosure table ({levels} levels, T = 2^{}): `disclosed` of the m keys are known, the worst case over which (the attacker gets the most valuable: with cyclic assignment, the first groups, which hold the dense levels 0-4). \
         primes: brute_force_bits is the product of the undisclosed triples' spaces (sum of their bits: 54 per triple where a group has only hashed levels, because only k mod 2^19 matters and primes are odd; 3·log2(454 387 932) = 86.28 where it has a dense level). \
         oracle_bits is the realistic figure for primes: a correct triple raises PSNR on its own levels, so each undisclosed group is searched separately and the work is the sum 2^b1 + 2^b2 + …, not the product (within a group: residues on a hashed level, 2^54, then the remaining 32.28 bits on a dense level). \
         prf (version 2): m independent 256-bit secrets and every level's subkey needs all of them, so any j < m leaves 256 bits (the master, or the missing secret) and partial keys give no oracle; oracle_bits = 132 is a per-level side channel (a level's 128-bit subkey recognised alone, 16 levels), independent of j. \
         prf v1 (the old layout, still readable): the m keys were shares of one secret, so j disclosed leave only the undisclosed shares' bits — 16 for m = 16, j = 15.",
        cfg.grid.log2_hashmap_size
    ));
    Ok(())
}

fn round2(x: f64) -> f64 {
    (x * 100.0).round() / 100.0
}
