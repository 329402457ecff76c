use super::msgpack::{d, decode, f, map, s, u};
use super::*;
use crate::encoding::layout::GridConfig;
use crate::network::NerfLayout;
use crate::rng::Pcg32;
use rmpv::Value;

fn small_config() -> ModelConfig {
    // Small table keeps the tests fast: 2 levels × 2 features, T = 2^8.
    ModelConfig {
        grid: GridConfig {
            n_levels: 2,
            n_features: 2,
            log2_hashmap_size: 8,
            base_resolution: 4,
        },
        aabb_scale: 1,
    }
}

fn snapshot_for(config: ModelConfig, seed: u64) -> Snapshot {
    let n = NerfLayout::new(config).unwrap().n_params;
    let mut r = Pcg32::new(seed, 1);
    let params = (0..n).map(|_| r.next_f32() * 2.0 - 1.0).collect();
    let cells = DENSITY_GRID_CELLS * n_cascades(config.aabb_scale);
    let grid = (0..cells)
        .map(|i| if i % 7 == 0 { -1.0 } else { r.next_f32() * 0.1 })
        .collect();
    let mut snap = Snapshot::new(config, params, grid);
    snap.training_step = 1234;
    snap.loss = 0.0125;
    snap
}

fn with_dataset(mut snap: Snapshot) -> Snapshot {
    let xf = [
        [1.0, 0.0, 0.0, 0.5],
        [0.0, -1.0, 0.0, 0.2],
        [0.0, 0.0, -1.0, 1.5],
    ];
    let mut im = DatasetImage::new([800, 800], [1111.11, 1111.11], xf);
    im.lens = Lens::OpenCv {
        k1: 0.01,
        k2: -0.002,
        p1: 0.0,
        p2: 0.0001,
    };
    let ims = vec![DatasetImage::new([800, 800], [1111.11, 1111.11], xf), im];
    snap.dataset = Some(SnapshotDataset::new(
        vec!["./train/r_0".into(), "./train/r_1".into()],
        ims,
        snap.config.aabb_scale,
    ));
    snap
}

fn doc(bytes: &[u8]) -> Value {
    let (raw, _) = read::unframe(bytes).unwrap();
    decode(&raw).unwrap()
}

fn field<'a>(v: &'a Value, path: &[&str]) -> &'a Value {
    let mut cur = v;
    for k in path {
        cur = cur
            .as_map()
            .unwrap()
            .iter()
            .find(|(kk, _)| kk.as_str() == Some(k))
            .map(|(_, v)| v)
            .unwrap_or_else(|| panic!("missing {k}"));
    }
    cur
}

#[test]
fn morton_and_cascades() {
    assert_eq!(morton3d(1, 0, 0), 1);
    assert_eq!(morton3d(0, 1, 0), 2);
    assert_eq!(morton3d(0, 0, 1), 4);
    assert_eq!(morton3d(3, 0, 0), 9);
    assert_eq!(morton3d(127, 127, 127), DENSITY_GRID_CELLS as u32 - 1);
    let mut r = Pcg32::new(5, 5);
    for _ in 0..1000 {
        let (x, y, z) = (r.below(1024), r.below(1024), r.below(1024));
        assert_eq!(morton3d_inverse(morton3d(x, y, z)), (x, y, z));
    }
    assert_eq!(n_cascades(1), 1);
    assert_eq!(n_cascades(2), 2);
    assert_eq!(n_cascades(16), 5);
    assert_eq!(n_cascades(128), 8);
}

#[test]
fn round_trip_is_byte_identical_both_containers() {
    let dir = tempfile::tempdir().unwrap();
    for (i, cfg) in [
        small_config(),
        ModelConfig {
            aabb_scale: 4,
            ..small_config()
        },
    ]
    .into_iter()
    .enumerate()
    {
        let snap = with_dataset(snapshot_for(cfg, i as u64));
        for ext in ["ingp", "msgpack"] {
            let p1 = dir.path().join(format!("a{i}.{ext}"));
            let p2 = dir.path().join(format!("b{i}.{ext}"));
            save(&p1, &snap).unwrap();
            let back = load(&p1).unwrap();
            assert_eq!(back.config, cfg);
            assert_eq!(back.training_step, 1234);
            assert_eq!(back.loss, 0.0125);
            assert_eq!(
                back.dataset.as_ref().unwrap().images[1].lens,
                snap.dataset.as_ref().unwrap().images[1].lens
            );
            assert_eq!(
                back.dataset.as_ref().unwrap().images,
                snap.dataset.as_ref().unwrap().images
            );
            // fp16 quantisation only.
            for (a, b) in snap.params.iter().zip(&back.params) {
                assert!((a - b).abs() <= a.abs() * 1e-3 + 1e-7, "{a} vs {b}");
            }
            assert_eq!(back.density_grid.len(), snap.density_grid.len());
            assert_eq!(back.density_grid[0], -1.0);
            save(&p2, &back).unwrap();
            assert_eq!(std::fs::read(&p1).unwrap(), std::fs::read(&p2).unwrap());
        }
    }
    let bad = dir.path().join("x.json");
    assert!(save(&bad, &snapshot_for(small_config(), 0)).is_err());
}

#[test]
fn ingp_is_gzip_of_the_msgpack() {
    let snap = snapshot_for(small_config(), 3);
    let gz = to_bytes(&snap, true).unwrap();
    let raw = to_bytes(&snap, false).unwrap();
    assert_eq!(&gz[..4], &[0x1f, 0x8b, 0x08, 0x00]);
    assert_eq!(&gz[4..8], &[0, 0, 0, 0], "mtime 0 as zlib writes it");
    assert_eq!(gz[9], 3, "OS byte unix as zlib writes it");
    let (un, framing) = read::unframe(&gz).unwrap();
    assert_eq!(framing, read::Framing::Gzip);
    assert_eq!(un, raw);
    // Top level is a map whose keys come sorted.
    assert_eq!(raw[0], 0x89, "fixmap of 9 keys");
    let d = doc(&raw);
    let keys: Vec<&str> = d
        .as_map()
        .unwrap()
        .iter()
        .map(|(k, _)| k.as_str().unwrap())
        .collect();
    assert_eq!(
        keys,
        [
            "dir_encoding",
            "distortion_map",
            "encoding",
            "envmap",
            "loss",
            "network",
            "optimizer",
            "rgb_network",
            "snapshot"
        ]
    );
}

/// The body is zlib's own deflate (level 6, 15-bit window, memLevel 8), byte for byte, as
/// instant-ngp writes it through zstr: a stego file must not compress differently. The
/// expected length and CRC-32 are what CPython's `zlib.compressobj(6, DEFLATED, 31, 8)`
/// gives on this input (zlib 1.2.13; also when fed in 4 KiB pieces).
#[test]
fn ingp_compression_is_zlibs_byte_for_byte() {
    let mut x: u32 = 1;
    let mut raw = Vec::new();
    for i in 0..200_000 {
        x = (x.wrapping_mul(1_103_515_245).wrapping_add(12_345)) & 0x7fff_ffff;
        raw.push(if i % 3 != 0 { (x >> 16) as u8 } else { 0x3c });
    }
    raw.extend(b"instant-ngp snapshot ".repeat(2000));
    let gz = super::gzip_bytes(&raw).unwrap();
    let mut crc = flate2::Crc::new();
    crc.update(&gz);
    assert_eq!((gz.len(), crc.sum()), (158_502, 0x7692_aa1e));
}

#[test]
fn fields_names_and_types_match_the_reference() {
    let snap = snapshot_for(small_config(), 4);
    let raw = to_bytes(&snap, false).unwrap();
    let d = doc(&raw);
    let sn = field(&d, &["snapshot"]);
    let keys: Vec<&str> = sn
        .as_map()
        .unwrap()
        .iter()
        .map(|(k, _)| k.as_str().unwrap())
        .collect();
    assert_eq!(
        keys,
        [
            "aabb",
            "background_color",
            "bounding_radius",
            "camera",
            "density_grid_binary",
            "density_grid_size",
            "exposure",
            "loss",
            "mode",
            "n_params",
            "nerf",
            "params_binary",
            "params_type",
            "render_aabb",
            "render_aabb_to_local",
            "sun_dir",
            "training_step",
            "up_dir",
            "version"
        ]
    );
    assert_eq!(field(sn, &["version"]).as_u64(), Some(1));
    assert_eq!(field(sn, &["mode"]).as_str(), Some("nerf"));
    assert_eq!(field(sn, &["params_type"]).as_str(), Some("__half"));
    assert_eq!(field(sn, &["density_grid_size"]).as_u64(), Some(128));
    let n = NerfLayout::new(small_config()).unwrap().n_params;
    assert_eq!(field(sn, &["n_params"]).as_u64(), Some(n as u64));
    assert_eq!(
        field(sn, &["params_binary"]).as_slice().unwrap().len(),
        n * 2
    );
    assert_eq!(
        field(sn, &["density_grid_binary"])
            .as_slice()
            .unwrap()
            .len(),
        DENSITY_GRID_CELLS * 2
    );
    // Culled cell: fp16 −1 = 0xBC00, little-endian.
    assert_eq!(
        &field(sn, &["density_grid_binary"]).as_slice().unwrap()[..2],
        &[0x00, 0xbc]
    );
    let nerf_keys: Vec<&str> = field(sn, &["nerf"])
        .as_map()
        .unwrap()
        .iter()
        .map(|(k, _)| k.as_str().unwrap())
        .collect();
    assert_eq!(
        nerf_keys,
        [
            "aabb_scale",
            "cam_pos_offset",
            "cam_rot_offset",
            "dataset",
            "extra_dims_opt",
            "rgb"
        ]
    );
    assert_eq!(
        field(sn, &["nerf", "rgb", "rays_per_batch"]).as_u64(),
        Some(4096)
    );
    let cam = field(sn, &["camera"]).as_map().unwrap();
    assert_eq!(cam.len(), 10);
    assert!(matches!(field(sn, &["loss"]), Value::F32(_)));
    assert_eq!(
        field(sn, &["aabb", "max"]),
        &Value::Array(vec![Value::F32(1.0); 3])
    );
    // The render aabb of a dataset is empty: ±∞, which only float64 can hold.
    assert_eq!(
        field(sn, &["nerf", "dataset", "render_aabb", "min"]),
        &Value::Array(vec![Value::F64(f64::INFINITY); 3])
    );
    // Adam leaf of the config, with the testbed's flags; 0.95 as float64.
    let adam = field(&d, &["optimizer", "nested", "nested"]);
    assert_eq!(
        field(adam, &["optimize_matrix_params"]),
        &Value::Boolean(true)
    );
    assert_eq!(
        field(adam, &["optimize_non_matrix_params"]),
        &Value::Boolean(true)
    );
    assert_eq!(field(adam, &["learning_rate"]), &Value::F64(0.01));
    assert_eq!(field(&d, &["optimizer", "decay"]), &Value::F64(0.95));
    assert_eq!(field(&d, &["loss", "otype"]).as_str(), Some("Huber"));
    assert_eq!(field(&d, &["encoding", "n_levels"]).as_u64(), Some(2));
}

#[test]
fn reference_parameter_counts_and_sizes_16x2_and_8x4() {
    let l = NerfLayout::new(ModelConfig::default()).unwrap();
    assert_eq!(l.n_params, 12_206_480);
    assert_eq!(l.grid_offset, 10_240);
    let l8 = NerfLayout::new(ModelConfig {
        grid: GridConfig::base_json_2023(),
        aabb_scale: 1,
    })
    .unwrap();
    assert_eq!(l8.n_params, 11_692_032);
    // Full-size 16×2 file: its params_binary holds exactly 2 bytes per parameter.
    let snap = Snapshot::new(
        ModelConfig::default(),
        vec![0.0; l.n_params],
        vec![-1.0; DENSITY_GRID_CELLS],
    );
    let raw = to_bytes(&snap, false).unwrap();
    let d = doc(&raw);
    assert_eq!(
        field(&d, &["snapshot", "params_binary"])
            .as_slice()
            .unwrap()
            .len(),
        24_412_960
    );
    assert_eq!(
        field(&d, &["snapshot", "density_grid_binary"])
            .as_slice()
            .unwrap()
            .len(),
        4_194_304
    );
    assert_eq!(field(&d, &["encoding", "n_levels"]).as_u64(), Some(16));
    assert_eq!(
        field(&d, &["encoding", "n_features_per_level"]).as_u64(),
        Some(2)
    );
    println!("16x2 msgpack bytes: {}", raw.len());
    // 8×4 read back stays 8×4.
    let s8 = Snapshot::new(l8.config, vec![0.0; l8.n_params], vec![]);
    let b8 = to_bytes(&s8, false).unwrap();
    let back = read::from_msgpack(&b8).unwrap();
    assert_eq!(back.config.grid, GridConfig::base_json_2023());
    assert_eq!(to_bytes(&back, false).unwrap(), b8);
}

/// A snapshot laid out as the reference writes it, built by hand from the spec (not by our
/// writer): 8×4 config with a `per_level_scale`-free encoding, fp32 params, aabb_scale 2,
/// optimizer state, and a few params at known positions.
fn hand_built(params_type: &str, with_optimizer: bool) -> (Vec<u8>, usize) {
    hand_built_with(params_type, with_optimizer, &[])
}

/// [`hand_built`] with `extra` (index, value) parameters set on top of its three.
fn hand_built_with(
    params_type: &str,
    with_optimizer: bool,
    extra: &[(usize, f32)],
) -> (Vec<u8>, usize) {
    let grid = GridConfig {
        n_levels: 2,
        n_features: 4,
        log2_hashmap_size: 10,
        base_resolution: 8,
    };
    let n = NerfLayout::new(ModelConfig {
        grid,
        aabb_scale: 2,
    })
    .unwrap()
    .n_params;
    let elem = if params_type == "float" { 4 } else { 2 };
    let mut params = vec![0u8; n * elem];
    // Param 0 = 0.5, param 3072 (in the colour MLP's first matrix) = −2, last = 1.
    let put = |p: &mut Vec<u8>, i: usize, v: f32| {
        if elem == 4 {
            p[i * 4..i * 4 + 4].copy_from_slice(&v.to_le_bytes());
        } else {
            p[i * 2..i * 2 + 2].copy_from_slice(&half::f16::from_f32(v).to_le_bytes());
        }
    };
    put(&mut params, 0, 0.5);
    put(&mut params, 3072, -2.0);
    put(&mut params, n - 1, 1.0);
    for &(i, v) in extra {
        put(&mut params, i, v);
    }
    let grid_bin = vec![0u8; DENSITY_GRID_CELLS * 2 * 2];
    let mlp = |h: u64| {
        map(vec![
            ("otype", s("FullyFusedMLP")),
            ("activation", s("ReLU")),
            ("output_activation", s("None")),
            ("n_neurons", u(64)),
            ("n_hidden_layers", u(h)),
        ])
    };
    let mut snap = vec![
        ("n_params", u(n as u64)),
        ("params_type", s(params_type)),
        ("params_binary", Value::Binary(params)),
        ("version", u(1)),
        ("mode", s("nerf")),
        ("density_grid_size", u(128)),
        ("density_grid_binary", Value::Binary(grid_bin)),
        (
            "nerf",
            map(vec![
                ("aabb_scale", Value::from(2i64)),
                (
                    "rgb",
                    map(vec![
                        ("rays_per_batch", u(65536)),
                        ("measured_batch_size", u(262000)),
                        ("measured_batch_size_before_compaction", u(1_000_000)),
                    ]),
                ),
            ]),
        ),
        ("training_step", u(35000)),
        ("loss", Value::F32(0.003)),
        ("camera", map(vec![("zoom", f(2.0))])),
    ];
    if with_optimizer {
        snap.push((
            "optimizer",
            map(vec![
                ("weights_ema_binary", Value::Binary(vec![0; n * 2])),
                (
                    "nested",
                    map(vec![
                        ("learning_rate", d(0.01)),
                        ("learning_rate_factor", f(1.0)),
                    ]),
                ),
            ]),
        ));
    }
    let top = map(vec![
        ("loss", map(vec![("otype", s("Huber"))])),
        (
            "encoding",
            map(vec![
                ("otype", s("HashGrid")),
                ("n_levels", u(2)),
                ("n_features_per_level", u(4)),
                ("log2_hashmap_size", u(10)),
                ("base_resolution", u(8)),
            ]),
        ),
        ("network", mlp(1)),
        ("rgb_network", mlp(2)),
        (
            "dir_encoding",
            map(vec![
                ("otype", s("Composite")),
                (
                    "nested",
                    Value::Array(vec![
                        map(vec![
                            ("n_dims_to_encode", u(3)),
                            ("otype", s("SphericalHarmonics")),
                            ("degree", u(4)),
                        ]),
                        map(vec![("otype", s("Identity"))]),
                    ]),
                ),
            ]),
        ),
        ("snapshot", map(snap)),
    ]);
    let mut out = Vec::new();
    rmpv::encode::write_value(&mut out, &top).unwrap();
    (out, n)
}

#[test]
fn hand_built_reference_snapshot_loads() {
    for (ptype, opt) in [("float", true), ("__half", false)] {
        let (bytes, n) = hand_built(ptype, opt);
        let s = read::from_msgpack(&bytes).unwrap();
        assert_eq!(s.config.aabb_scale, 2);
        assert_eq!(s.config.grid.n_levels, 2);
        assert_eq!(s.config.grid.n_features, 4);
        assert_eq!(s.config.grid.log2_hashmap_size, 10);
        assert_eq!(s.params.len(), n);
        assert_eq!(s.params[0], 0.5);
        assert_eq!(s.params[3072], -2.0);
        assert_eq!(s.params[n - 1], 1.0);
        assert_eq!(s.params.iter().filter(|&&x| x != 0.0).count(), 3);
        assert_eq!(s.density_grid.len(), 2 * DENSITY_GRID_CELLS);
        assert_eq!(s.training_step, 35000);
        assert_eq!(s.rays_per_batch, 65536);
        assert_eq!(s.camera.zoom, 2.0);
        assert_eq!(s.view.aabb, Aabb::for_scale(2));
        assert_eq!(s.view.aabb.min, [-0.5; 3]);
        assert_eq!(s.has_optimizer_state(), opt);
        // Written back: the file's own config is kept, weights as fp16, optimizer kept.
        let again = to_bytes(&s, false).unwrap();
        let d = doc(&again);
        assert_eq!(
            field(&d, &["snapshot", "params_type"]).as_str(),
            Some("__half")
        );
        assert_eq!(
            field(&d, &["snapshot", "params_binary"])
                .as_slice()
                .unwrap()
                .len(),
            n * 2
        );
        assert!(
            field(&d, &["snapshot"])
                .as_map()
                .unwrap()
                .iter()
                .any(|(k, _)| k.as_str() == Some("optimizer"))
                == opt
        );
        assert_eq!(read::from_msgpack(&again).unwrap().params, s.params);
    }
}

/// The hand-built file's network evaluated at two inputs. Weights are placed at positions
/// worked out from the spec alone (§2.5: [density MLP][colour MLP][grid], row-major
/// out × in, inputs padded to 16, outputs to 16; §1.3/§1.5: dense level 0, hashed level 1,
/// entry-major features), and the outputs are worked out by hand. A transposed matrix, a
/// wrong block offset, a used padding row or a wrong corner index changes them.
#[test]
fn hand_built_reference_snapshot_gives_expected_outputs() {
    // 2 levels × 4 features = 8 inputs, padded to 16: density 64·16 + 16·64 = 2048 params.
    const D_W0: usize = 0; // 64 × 16
    const D_W1: usize = 1024; // 16 × 64
    // Colour input [16 density outputs, 16 SH] = 32: 64·32 + 64·64 + 16·64 = 7168 params.
    const C_W0: usize = 2048; // 64 × 32
    const C_W1: usize = C_W0 + 64 * 32; // 64 × 64
    const C_W2: usize = C_W1 + 64 * 64; // 16 × 64, rows 3..15 padding
    const GRID: usize = C_W2 + 16 * 64;
    // Level 0: scale 8 − 1 = 7, resolution 8, 8³ = 512 ≤ 2^10 → dense, 512 entries.
    // Level 1: per_level_scale = 2048·aabb_scale/8 = 512, scale 4095 → hashed, 1024 entries.
    const L1: usize = GRID + 512 * 4;
    let mut puts = vec![
        (D_W0 + 1, 2.0),            // hidden 0 ← input 1 (level 0, feature 1)
        (D_W0 + 16 + 4, 1.0),       // hidden 1 ← input 4 (level 1, feature 0)
        (D_W1, 1.5),                // output 0 (log-density) ← hidden 0
        (D_W1 + 1, 1.0),            // output 0 ← hidden 1
        (D_W1 + 5 * 64, 1.0),       // output 5 ← hidden 0
        (C_W0 + 3 * 32 + 5, 0.5),   // colour hidden 3 ← density output 5
        (C_W0 + 3 * 32 + 16, 1.0),  // colour hidden 3 ← SH 0
        (C_W0 + 4 * 32 + 17, 1.0),  // colour hidden 4 ← SH 1 (−0.4886·y)
        (C_W1 + 7 * 64 + 3, 1.0),   // second hidden 7 ← 3
        (C_W1 + 8 * 64 + 4, 1.0),   // second hidden 8 ← 4
        (C_W2 + 8, 1.0),            // r ← 8
        (C_W2 + 64 + 7, 1.0),       // g ← 7
        (C_W2 + 2 * 64 + 7, -1.0),  // b ← 7
        (C_W2 + 5 * 64 + 7, 100.0), // a padding row: must never reach an output
    ];
    // Feature 1 of every level-0 entry = 1: the interpolated value is 1 anywhere.
    puts.extend((0..512).map(|e| (GRID + e * 4 + 1, 1.0)));
    // Level 1 at x = 0: p = 0.5, all 8 corners weigh 1/8; corner (1,1,1) hashes to
    // 1 ⊕ (2654435761 mod 2^10 = 433) ⊕ (805459861 mod 2^10 = 917) = 549.
    assert_eq!(1 ^ (2654435761u32 & 1023) ^ (805459861u32 & 1023), 549);
    puts.push((L1 + 549 * 4, 8.0));
    for ptype in ["float", "__half"] {
        // The base file sets param 0 (density W0[0][0], input 0 is zero here), param 3072
        // (colour hidden 32 ← density output 0; hidden 32 feeds nothing) and the last param
        // (level-1 entry 1023, feature 3: unused input 7): none of them moves the outputs.
        let (bytes, n) = hand_built_with(ptype, false, &puts);
        assert_eq!(n, L1 + 1024 * 4);
        let s = read::from_msgpack(&bytes).unwrap();
        let net = crate::network::nerf::NerfNetwork::new(s.config).unwrap();
        let idx = crate::encoding::reference_indices(&net.layout.grid);
        let mut ws = net.workspace();
        let pos = [[0.0f32; 3], [0.5; 3]];
        let dir = [[0.0f32, -1.0, 0.0], [0.0, 1.0, 0.0]];
        let mut out = [[0.0f32; 4]; 2];
        net.forward(&s.params, &idx, &pos, &dir, &mut ws, &mut out);
        let (sh0, sh1) = (0.282_094_8f32, 0.488_602_5f32);
        // x = 0: density hidden (2, 1) → log-density 1.5·2 + 1 = 4, output 5 = 2; colour
        // hidden 3 = 0.5·2 + SH0, hidden 4 = SH1 at y = −1. x = 0.5: level 1 reads corner
        // (2048,2048,2048) → entry 0, which is zero: log-density 3; SH1 < 0 at y = +1.
        let want = [
            [sh1, 1.0 + sh0, -(1.0 + sh0), 4.0],
            [0.0, 1.0 + sh0, -(1.0 + sh0), 3.0],
        ];
        for (got, want) in out.iter().zip(&want) {
            for c in 0..4 {
                assert!(
                    (got[c] - want[c]).abs() < 1e-5,
                    "{ptype}: got {got:?}, want {want:?}"
                );
            }
        }
    }
}

fn expect_err(bytes: &[u8], needle: &str) {
    match from_bytes(bytes) {
        Ok(_) => panic!("accepted a bad file (wanted '{needle}')"),
        Err(e) => assert!(e.contains(needle), "error '{e}' lacks '{needle}'"),
    }
}

fn replace_in(v: &mut Value, path: &[&str], new: Option<Value>) {
    let m = match v {
        Value::Map(m) => m,
        _ => panic!(),
    };
    let pos = m
        .iter()
        .position(|(k, _)| k.as_str() == Some(path[0]))
        .unwrap();
    if path.len() == 1 {
        match new {
            Some(n) => m[pos].1 = n,
            None => {
                m.remove(pos);
            }
        }
    } else {
        replace_in(&mut m[pos].1, &path[1..], new);
    }
}

fn mutated(path: &[&str], new: Option<Value>) -> Vec<u8> {
    let (bytes, _) = hand_built("__half", false);
    let mut v = decode(&bytes).unwrap();
    replace_in(&mut v, path, new);
    let mut out = Vec::new();
    rmpv::encode::write_value(&mut out, &v).unwrap();
    out
}

#[test]
fn unsupported_and_broken_files_are_refused_clearly() {
    expect_err(&[], "empty");
    expect_err(b"hello world", "msgpack");
    expect_err(&[0x1f, 0x8b, 0x08, 0, 1, 2, 3], "gzip");
    let mut foreign = Vec::new();
    rmpv::encode::write_value(&mut foreign, &Value::Array(vec![u(1), u(2)])).unwrap();
    expect_err(&foreign, "not a map");
    let mut cfg_only = Vec::new();
    rmpv::encode::write_value(&mut cfg_only, &map(vec![("loss", u(1))])).unwrap();
    expect_err(&cfg_only, "no 'snapshot'");
    expect_err(&mutated(&["snapshot", "mode"], Some(s("sdf"))), "'sdf'");
    expect_err(&mutated(&["snapshot", "version"], None), "older");
    expect_err(&mutated(&["snapshot", "version"], Some(u(2))), "newer");
    expect_err(
        &mutated(&["encoding", "otype"], Some(s("Frequency"))),
        "'Frequency'",
    );
    expect_err(
        &mutated(&["network", "n_neurons"], Some(u(128))),
        "128 neurons",
    );
    expect_err(
        &mutated(&["network", "otype"], Some(s("CutlassMLP"))),
        "CutlassMLP",
    );
    expect_err(
        &mutated(&["dir_encoding", "otype"], Some(s("OneBlob"))),
        "dir_encoding",
    );
    expect_err(
        &mutated(&["encoding", "n_levels"], Some(u(3))),
        "snapshot.n_params",
    );
    expect_err(
        &mutated(
            &["snapshot", "params_binary"],
            Some(Value::Binary(vec![0; 10])),
        ),
        "params_binary",
    );
    expect_err(
        &mutated(&["snapshot", "params_type"], Some(s("double"))),
        "params_type",
    );
    expect_err(
        &mutated(
            &["snapshot", "density_grid_binary"],
            Some(Value::Binary(vec![0; 6])),
        ),
        "density_grid_binary",
    );
    expect_err(
        &mutated(&["snapshot", "density_grid_size"], Some(u(64))),
        "density_grid_size",
    );
    expect_err(
        &mutated(&["snapshot", "nerf", "aabb_scale"], Some(u(3))),
        "aabb_scale",
    );
    expect_err(
        &mutated(&["snapshot", "training_step"], Some(s("x"))),
        "snapshot.training_step",
    );
    expect_err(
        &mutated(&["snapshot", "nerf", "rgb"], None),
        "snapshot.nerf.rgb",
    );
    // Truncations of a valid file, raw and gzip, never load.
    let good = to_bytes(&snapshot_for(small_config(), 9), true).unwrap();
    for cut in [1, 10, good.len() / 2, good.len() - 1] {
        assert!(from_bytes(&good[..cut]).is_err());
    }
    let raw = to_bytes(&snapshot_for(small_config(), 9), false).unwrap();
    for cut in [1, 5, raw.len() / 3, raw.len() - 1] {
        assert!(from_bytes(&raw[..cut]).is_err());
    }
    // Load names the file.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.ingp");
    std::fs::write(&p, b"\x00garbage").unwrap();
    let e = load(&p).unwrap_err().to_string();
    assert!(e.contains("bad.ingp"), "{e}");
}

#[test]
fn random_mutations_never_panic() {
    let snap = with_dataset(snapshot_for(small_config(), 11));
    let raw = to_bytes(&snap, false).unwrap();
    let gz = to_bytes(&snap, true).unwrap();
    let mut r = Pcg32::new(2024, 7);
    let mut n_err = 0;
    for iter in 0..2400 {
        let base = if iter % 4 == 3 { &gz } else { &raw };
        let mut b = base.clone();
        match r.below(4) {
            0 => {
                // Flip a few bytes, biased towards the small header area where lengths live.
                for _ in 0..1 + r.below(4) {
                    let at = if r.below(2) == 0 {
                        r.below(b.len().min(4096) as u32)
                    } else {
                        r.below(b.len() as u32)
                    } as usize;
                    b[at] = r.next_u32() as u8;
                }
            }
            1 => {
                let at = r.below(b.len() as u32) as usize;
                b.truncate(at);
            }
            2 => {
                // Overwrite with a large length marker (str32/bin32/array32/map32).
                let at = r.below(b.len().min(4096) as u32) as usize;
                let marker = [0xdb, 0xc6, 0xdd, 0xdf][r.below(4) as usize];
                b[at] = marker;
                for k in 1..5 {
                    if at + k < b.len() {
                        b[at + k] = 0xff;
                    }
                }
            }
            _ => {
                let at = r.below(b.len() as u32) as usize;
                let junk: Vec<u8> = (0..1 + r.below(16)).map(|_| r.next_u32() as u8).collect();
                b.splice(at..at, junk);
            }
        }
        if from_bytes(&b).is_err() {
            n_err += 1;
        }
    }
    assert!(n_err > 1000, "only {n_err} mutations were rejected");
}

#[test]
fn inspect_reports_config() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("m.ingp");
    save(&p, &snapshot_for(small_config(), 1)).unwrap();
    let info = inspect(&p).unwrap();
    assert_eq!(info.format, "ingp (gzip msgpack)");
    assert_eq!(info.n_levels, 2);
    assert_eq!(info.training_step, 1234);
    assert_eq!(
        info.n_params,
        NerfLayout::new(small_config()).unwrap().n_params
    );
    assert_eq!(info.grid_offset, 10240 - 2048 + 1024);
    assert_eq!(info.params_bytes, info.n_params * 2);
    assert_eq!(info.density_grid_cells, DENSITY_GRID_CELLS);
    assert!(
        serde_json::to_string(&info)
            .unwrap()
            .contains("\"dense_levels\"")
    );
}
