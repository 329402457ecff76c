//! Stealth training: the hidden scene lives only in table entries the cover itself trains,
//! a key holder rebuilds the same confinement from the published file alone, and the
//! statistic that gives a default stego model away (entries left at initialisation on the
//! first hashed level) stays where a plain model has it.

use std::sync::Arc;
use stegongp::ngp::data::Dataset;
use stegongp::ngp::encoding::reach::reachable_entries;
use stegongp::ngp::encoding::{GridLayout, reference_indices};
use stegongp::ngp::model::Model;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::{SceneSpec, TrainConfig, Trainer};
use stegongp::score::eval::{evaluate, spread_views};
use stegongp::stego::stealth::{Stealth, StealthParts, cover_entries, hidden_indices};
use stegongp::stego::{Key, generate_prf, open_scene};
use stegongp::synth::SceneKind;
use testkit::scenes::generated;

const RES: u32 = 32;
const STEPS: u32 = 250;

/// A 2^14 table: level 2 (30³ = 27 000 vertices) is the first hashed level, and about a
/// fifth of its slots are the image of no vertex under the reference hash.
fn model_config() -> ModelConfig {
    let mut c = ModelConfig::default();
    c.grid.log2_hashmap_size = 14;
    c
}

fn scene(dir: &std::path::Path, kind: SceneKind, seed: u64) -> (Arc<Dataset>, Dataset) {
    generated(dir, kind, RES, 30, 4, seed).shared()
}

enum Mode {
    Plain,
    Stego,
    Stealth,
}

fn train(mode: Mode, cover: &Arc<Dataset>, hidden: &Arc<Dataset>, key: &Key) -> Trainer {
    let cfg = model_config();
    let layout = NerfLayout::new(cfg).unwrap();
    let mut scenes = vec![SceneSpec {
        dataset: cover.clone(),
        indices: reference_indices(&layout.grid),
    }];
    if !matches!(mode, Mode::Plain) {
        scenes.push(SceneSpec {
            dataset: hidden.clone(),
            indices: key.level_indices(&layout.grid),
        });
    }
    let tc = TrainConfig {
        seed: 3,
        batch_samples: 1 << 14,
        occupancy_fraction: 1.0 / 32.0,
        ..Default::default()
    };
    let mut t = Trainer::new(cfg, scenes, tc).unwrap();
    if matches!(mode, Mode::Stealth) {
        // As `train --stealth` trains, but for the density cap.
        let parts = StealthParts {
            confine: true,
            pace: true,
            bound_left: true,
            ..StealthParts::none()
        };
        let policy = Stealth::with_parts(layout, std::slice::from_ref(key), parts).unwrap();
        t.set_policy(Box::new(policy)).unwrap();
    }
    for _ in 0..STEPS {
        let st = t.train_step().unwrap();
        let cover_loss = st
            .primary_loss
            .expect("mixed batches train the cover every step");
        if matches!(mode, Mode::Plain) {
            assert_eq!(cover_loss, st.loss);
        } else {
            assert!(
                cover_loss < st.loss,
                "the hidden scene's loss is not the cover's"
            );
        }
    }
    t
}

fn psnr(model: &Model, key: Option<&Key>, stealth: bool, test: &Dataset) -> f64 {
    let opened = open_scene(model, key, stealth, 0);
    let which = spread_views(test.frames.len(), 4);
    evaluate(
        &opened.view(model),
        test,
        &RenderOptions::default(),
        Some(&which),
        |_, _, _| {},
    )
    .psnr
}

/// Fraction of level `l`'s entries whose features all kept their ±1e-4 initial values.
fn init_fraction(model: &Model, l: usize) -> f64 {
    let layout = &model.net.layout;
    let f = layout.config.grid.n_features as usize;
    let lv = layout.grid.levels[l];
    let start = layout.grid_offset + lv.offset as usize * f;
    let table = &model.params()[start..start + lv.size as usize * f];
    let at_init = table
        .chunks(f)
        .filter(|e| e.iter().all(|v| v.abs() <= 1.001e-4))
        .count();
    at_init as f64 / lv.size as f64
}

fn first_hashed(layout: &GridLayout) -> usize {
    layout.levels.iter().position(|l| !l.dense).unwrap()
}

#[test]
fn stealth_keeps_the_hidden_scene_inside_the_covers_entries() {
    let dir = tempfile::tempdir().unwrap();
    let (ctrain, ctest) = scene(&dir.path().join("cover"), SceneKind::Object, 5);
    let (htrain, htest) = scene(&dir.path().join("hidden"), SceneKind::Text("HI".into()), 6);
    let key = generate_prf(4).unwrap();

    let stealth_t = train(Mode::Stealth, &ctrain, &htrain, &key);
    // The key holder has only the file: save, reload, rebuild the confinement from it.
    let path = dir.path().join("stealth.msgpack");
    Model::from_trainer(&stealth_t, 0.0).save(&path).unwrap();
    let stealth = Model::load(&path).unwrap();
    let layout = stealth.net.layout.grid.clone();
    let holder = hidden_indices(&key, &stealth.net.layout, stealth.params(), true);
    let reach = reachable_entries(&layout, &stealth.grid, 1, &reference_indices(&layout));
    let moved = cover_entries(&stealth.net.layout, stealth.params());
    let trained = stealth_t.indices(1);
    let left = stealth_t.table_bounds().unwrap();
    let (mut same, mut total, mut in_left, mut unbounded) = (0u32, 0u32, 0u32, 0u32);
    for (l, lv) in layout.levels.iter().enumerate() {
        let r = lv.resolution;
        for i in 0..4000u32 {
            let (x, y, z) = (i * 7 % r, i * 13 % r, i * 29 % r);
            let h = holder[l].index(x, y, z);
            same += (h == trained[l].index(x, y, z)) as u32;
            total += 1;
            // Entries the cover left are shared too, within their bounds (below).
            if !reach[l].contains(h) {
                in_left += 1;
                unbounded += !left.is_bounded((lv.offset + h) as usize) as u32;
            }
            assert!(
                moved[l].contains(h),
                "level {l}: hidden index {h} is not the cover's"
            );
        }
    }

    // The key holder's map is the trainer's last one but for entries the cover first moved
    // after the last grid update (none or a handful).
    eprintln!("key holder's index = trainer's for {same} of {total} vertices");
    assert!(same as f64 >= 0.999 * total as f64, "{same} of {total}");
    // The hidden scene shares entries the cover left, and they kept within their bounds.
    eprintln!(
        "{in_left} of {total} hidden vertices in entries the cover left ({unbounded} not left in training)"
    );
    assert!(in_left as f64 > 0.01 * total as f64, "{in_left} of {total}");
    // Exactly none: training bounds what the stored grid (fp16, which the key holder
    // reads) leaves, not what its own f32 grid leaves (cells near the threshold differ).
    assert_eq!(unbounded, 0);
    let table = &stealth_t.params[stealth_t.net.layout.grid_offset..];
    let n_left = (0..layout.n_entries as usize)
        .filter(|&e| left.is_bounded(e))
        .inspect(|&e| {
            for v in &table[2 * e..2 * e + 2] {
                assert!(
                    v.abs() <= left.bound(e),
                    "entry {e}: {v} past {}",
                    left.bound(e)
                );
            }
        })
        .count();
    assert!(n_left > 0);

    let plain_t = train(Mode::Plain, &ctrain, &htrain, &key);
    let plain_path = dir.path().join("plain.msgpack");
    Model::from_trainer(&plain_t, 0.0)
        .save(&plain_path)
        .unwrap();
    let plain = Model::load(&plain_path).unwrap();
    let stego = Model::from_trainer(&train(Mode::Stego, &ctrain, &htrain, &key), 0.0);

    // Same byte length as a plain model of the same configuration (uncompressed msgpack).
    assert_eq!(
        std::fs::metadata(&path).unwrap().len(),
        std::fs::metadata(&plain_path).unwrap().len()
    );

    let l = first_hashed(&layout);
    let (p, d, s) = (
        init_fraction(&plain, l),
        init_fraction(&stego, l),
        init_fraction(&stealth, l),
    );
    let cover = [
        psnr(&plain, None, false, &ctest),
        psnr(&stego, None, false, &ctest),
        psnr(&stealth, None, false, &ctest),
    ];
    let hidden_default = psnr(&stego, Some(&key), false, &htest);
    let hidden_stealth = psnr(&stealth, Some(&key), true, &htest);
    let hidden_unconfined = psnr(&stealth, Some(&key), false, &htest);
    eprintln!(
        "level {l} entries at init: plain {p:.3}, stego {d:.3}, stealth {s:.3}; cover PSNR plain/stego/stealth {cover:.2?}; hidden default {hidden_default:.2}, stealth {hidden_stealth:.2}, stealth model opened without --stealth {hidden_unconfined:.2}"
    );
    // Measured (32 px, 250 steps): plain 0.279, default stego 0.041, stealth 0.279; cover
    // 21.68 / 20.94 / 19.63 dB; hidden default 24.46, stealth 21.63 dB. (Before stealth
    // paced the table on the cover: cover 21.23, hidden 23.11 dB. With the cover-only MLP
    // as well: cover 21.21, hidden 20.16 dB.)
    // The default stego model trains the slots no cover vertex maps to; stealth leaves them.
    assert!(p > 0.1, "plain {p:.3}");
    assert!(d < 0.5 * p, "default stego {d:.3} vs plain {p:.3}");
    assert!((s - p).abs() < 0.15 * p, "stealth {s:.3} vs plain {p:.3}");
    // And the hidden scene is still there for the key holder, and only with the right map.
    assert!(
        hidden_stealth > 18.0,
        "hidden (stealth) {hidden_stealth:.2}"
    );
    assert!(
        hidden_stealth > hidden_default - 4.0,
        "hidden stealth {hidden_stealth:.2} vs default {hidden_default:.2}"
    );
    // (Opened without the confinement, only the indices that landed on unreachable slots
    // differ, so it shows most of the scene too: nothing to assert there.)
    // The stealth cover measured 2.05 dB under plain on CI and 1.76 dB on an earlier
    // session's machine (same seed, other numbers: gemm picks its kernels by CPU, the likely
    // cause): the bound leaves room for that spread and still fails a stealth mode that
    // costs the cover its scene.
    assert!(cover[2] > cover[0] - 3.0, "cover {cover:.2?}");
}
