//! `stegongp keygen` end to end: files, permissions, primes, salts, links, nothing secret
//! printed; and the CLI's warnings when it loads an old or readable key file.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

fn keygen(args: &[&str], stdin: Option<&str>) -> (bool, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_stegongp"))
        .arg("keygen")
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    if let Some(s) = stdin {
        // A keygen that refuses its arguments exits without reading: the pipe may be closed
        // already (EPIPE). Its exit status and message are what the tests check.
        let _ = child.stdin.take().unwrap().write_all(s.as_bytes());
    }
    drop(child.stdin.take());
    let out = child.wait_with_output().unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

fn trial_division(n: u64) -> bool {
    n >= 2
        && (2..)
            .take_while(|d| d * d <= n)
            .all(|d| !n.is_multiple_of(d))
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn secrets(p: &Path) -> Vec<String> {
    json(p)["secrets"]
        .as_array()
        .unwrap_or_else(|| panic!("no secrets in {}", p.display()))
        .iter()
        .map(|s| s.as_str().unwrap().to_string())
        .collect()
}

fn mode(p: &Path) -> u32 {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).unwrap().permissions().mode() & 0o777
}

#[test]
fn keygen_primes_and_prf() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.json"), dir.path().join("b.json"));
    let mut primes = vec![];
    for p in [&a, &b] {
        let (ok, out) = keygen(
            &[
                "--scheme",
                "primes",
                "--m",
                "2",
                "--out",
                p.to_str().unwrap(),
            ],
            None,
        );
        assert!(ok, "{out}");
        assert_eq!(mode(p), 0o600);
        let v = json(p);
        assert_eq!(v["scheme"], "primes");
        for t in v["keys"].as_array().unwrap() {
            for k in t.as_array().unwrap() {
                let k = k.as_u64().unwrap();
                assert!(
                    (10_000_000..=10_000_000_000).contains(&k) && trial_division(k),
                    "{k}"
                );
                assert!(!out.contains(&k.to_string()), "printed a prime: {out}");
                primes.push(k);
            }
        }
    }
    let n = primes.len();
    primes.sort_unstable();
    primes.dedup();
    assert_eq!(primes.len(), n, "repeated primes across calls");

    // No overwrite without --force.
    let before = std::fs::read(&a).unwrap();
    let (ok, out) = keygen(&["--scheme", "prf", "--out", a.to_str().unwrap()], None);
    assert!(!ok && out.contains("a.json"), "{out}");
    assert_eq!(std::fs::read(&a).unwrap(), before);
    let (ok, _) = keygen(
        &[
            "--scheme",
            "prf",
            "--force",
            "--json",
            "--out",
            a.to_str().unwrap(),
        ],
        None,
    );
    assert!(ok);
    assert_eq!(json(&a)["scheme"], "prf");
    assert_eq!(json(&a)["version"], 2);
    assert_eq!(mode(&a), 0o600);

    // Passphrase from stdin: deterministic, secret not printed.
    let (c, d) = (dir.path().join("c.json"), dir.path().join("d.json"));
    for p in [&c, &d] {
        let (ok, out) = keygen(
            &[
                "--passphrase",
                "--salt",
                "demo",
                "--m",
                "4",
                "--out",
                p.to_str().unwrap(),
            ],
            Some("a long passphrase\n"),
        );
        assert!(ok, "{out}");
        for secret in secrets(p) {
            assert_eq!(secret.len(), 64);
            assert!(!out.contains(&secret[..8]), "{out}");
        }
    }
    assert_eq!(secrets(&c), secrets(&d));
    assert_eq!(secrets(&c).len(), 4);
    assert_eq!(json(&c)["m"], 4);
    assert_eq!(json(&c)["kdf"]["salt"], "demo");

    // Bad arguments.
    let x = dir.path().join("x.json");
    assert!(!keygen(&["--scheme", "aes", "--out", x.to_str().unwrap()], None).0);
    assert!(!keygen(&["--m", "17", "--out", x.to_str().unwrap()], None).0);
    assert!(
        !keygen(
            &[
                "--scheme",
                "primes",
                "--passphrase",
                "--out",
                x.to_str().unwrap()
            ],
            Some("pw12345678\n")
        )
        .0
    );
    assert!(!x.exists());
}

/// The salt `keygen` printed: the word after "passphrase salt: ".
fn printed_salt(out: &str) -> String {
    let at = out.find("passphrase salt: ").expect(out) + "passphrase salt: ".len();
    out[at..].split_whitespace().next().unwrap().to_string()
}

#[test]
fn passphrase_keys_are_salted_by_default_and_recreated_with_the_printed_salt() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let pass = Some("correct horse battery staple\n");
    let mut salts = vec![];
    for name in ["a.json", "b.json"] {
        let (ok, out) = keygen(
            &[
                "--passphrase",
                "--m",
                "4",
                "--out",
                p(name).to_str().unwrap(),
            ],
            pass,
        );
        assert!(ok, "{out}");
        let salt = printed_salt(&out);
        assert!(
            salt.len() == 32 && salt.bytes().all(|b| b.is_ascii_hexdigit()),
            "{out}"
        );
        // Stored in the file with the Argon2id cost, which meets OWASP's minimum.
        let kdf = &json(&p(name))["kdf"];
        assert_eq!(kdf["salt"], salt.as_str());
        assert_eq!(
            (kdf["algorithm"].as_str(), kdf["version"].as_u64()),
            (Some("argon2id"), Some(19))
        );
        let (m, t) = (
            kdf["m_cost_kib"].as_u64().unwrap(),
            kdf["t_cost"].as_u64().unwrap(),
        );
        assert!((m >= 19_456 && t >= 2) || (m >= 47_104 && t >= 1), "{kdf}");
        assert!(kdf["p_cost"].as_u64().unwrap() >= 1);
        for secret in secrets(&p(name)) {
            assert!(!out.contains(&secret[..8]), "{out}");
        }
        salts.push(salt);
    }
    // Same passphrase, no --salt: different salts, different keys.
    assert_ne!(salts[0], salts[1]);
    let (a, b) = (secrets(&p("a.json")), secrets(&p("b.json")));
    assert!(a.iter().all(|s| !b.contains(s)));
    // The printed salt recreates the first key exactly.
    let (ok, out) = keygen(
        &[
            "--passphrase",
            "--salt",
            &salts[0],
            "--m",
            "4",
            "--out",
            p("again.json").to_str().unwrap(),
        ],
        pass,
    );
    assert!(ok, "{out}");
    assert_eq!(printed_salt(&out), salts[0]);
    assert_eq!(secrets(&p("again.json")), a);
    assert_eq!(json(&p("again.json"))["kdf"], json(&p("a.json"))["kdf"]);
    // An empty salt is refused.
    let (ok, out) = keygen(
        &[
            "--passphrase",
            "--salt",
            "",
            "--out",
            p("e.json").to_str().unwrap(),
        ],
        pass,
    );
    assert!(!ok && out.contains("salt"), "{out}");
    assert!(!p("e.json").exists());
}

/// A key file in a folder that does not exist: refused with the folder named, before a
/// passphrase is read, and nothing created.
#[test]
fn keygen_into_a_missing_folder_names_the_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("keys").join("k.json");
    for args in [vec![], vec!["--passphrase"]] {
        let mut a = args.clone();
        a.extend(["--out", out.to_str().unwrap()]);
        let (ok, text) = keygen(&a, Some("a passphrase long enough\n"));
        assert!(!ok, "{text}");
        assert!(
            text.contains("does not exist") && text.contains("keys"),
            "{text}"
        );
        assert!(!text.contains("Passphrase"), "{text}");
        assert!(!dir.path().join("keys").exists());
    }
}

#[test]
fn keygen_never_writes_through_a_link_at_the_output_path() {
    use std::os::unix::fs::symlink;
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("precious.txt");
    std::fs::write(&target, "precious").unwrap();
    let link = dir.path().join("key.json");
    symlink(&target, &link).unwrap();
    let (ok, out) = keygen(&["--out", link.to_str().unwrap()], None);
    assert!(!ok && out.contains("--force"), "{out}");
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink()
    );
    // --force replaces the link itself; the file it pointed to keeps its content.
    let (ok, out) = keygen(&["--force", "--out", link.to_str().unwrap()], None);
    assert!(ok, "{out}");
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_file()
    );
    assert_eq!(mode(&link), 0o600);
    assert_eq!(secrets(&link).len(), 1);
    // A dangling link: refused, and its target is not created.
    let dangling = dir.path().join("d.json");
    let nowhere = dir.path().join("nowhere");
    symlink(&nowhere, &dangling).unwrap();
    let (ok, _) = keygen(
        &["--scheme", "primes", "--out", dangling.to_str().unwrap()],
        None,
    );
    assert!(!ok);
    assert!(!nowhere.exists());
    // Nothing but the files above (no temporary left behind).
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["d.json", "key.json", "precious.txt"]);
}

#[test]
fn strength_after_disclosure_in_the_keygen_report() {
    let dir = tempfile::tempdir().unwrap();
    let run = |scheme: &str, m: &str| {
        let p = dir.path().join(format!("{scheme}{m}.json"));
        let (ok, out) = keygen(
            &[
                "--scheme",
                scheme,
                "--m",
                m,
                "--json",
                "--out",
                p.to_str().unwrap(),
            ],
            None,
        );
        assert!(ok, "{out}");
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        v["strength"]["after_disclosure"]
            .as_array()
            .unwrap()
            .clone()
    };
    // prf, m = 4, 3 keys disclosed: the last secret's 256 bits (per-level oracle 128 + 4).
    let d = run("prf", "4");
    assert_eq!(d.len(), 4);
    assert_eq!(d[3]["disclosed"], 3);
    assert_eq!(d[3]["brute_force_bits"], 256.0);
    assert_eq!(d[3]["oracle_bits"], 132.0);
    // primes, m = 4, 3 disclosed: one triple. Its group has dense levels, where all of
    // every prime counts: 3·log2(454 387 932) = 86.28 bits; with the per-group oracle the
    // residues mod 2^19 go first (3 × 18 = 54 bits), then 32.28 more: log2(2^54 + 2^32.28).
    let d = run("primes", "4");
    let brute = d[3]["brute_force_bits"].as_f64().unwrap();
    let oracle = d[3]["oracle_bits"].as_f64().unwrap();
    assert!((brute - 86.28).abs() < 0.005, "{brute}");
    assert!((oracle - 54.0).abs() < 1e-6, "{oracle}");
    // primes, m = 16, 15 disclosed (the 5 dense-level groups among them): one hashed-only
    // triple, 54 bits either way.
    let d = run("primes", "16");
    assert_eq!(d[15]["brute_force_bits"], 54.0);
    assert_eq!(d[15]["oracle_bits"], 54.0);
}

/// A `prf` key file exactly as the previous build wrote it (format version 1): one
/// 256-bit secret whose m = 4 keys are 8-byte shares.
const V1_FIXTURE: &str = r#"{
  "format": "stegongp-key",
  "version": 1,
  "scheme": "prf",
  "dense": "permute",
  "m": 4,
  "secret": "0b30557a9fc4e90e33587da2c7ec11365b80a5caef14395e83a8cdf2173c6186"
}
"#;

#[test]
fn old_key_files_load_flagged_and_the_cli_warns() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let old = dir.path().join("old.json");
    std::fs::write(&old, V1_FIXTURE).unwrap();
    std::fs::set_permissions(&old, std::fs::Permissions::from_mode(0o644)).unwrap();
    let loaded = stegongp::stego::load_key_with_warnings(&old).unwrap();
    assert!(loaded.legacy_layout && loaded.key.is_legacy_layout() && loaded.version == 1);
    let all = loaded.warnings.join("\n");
    assert!(
        all.contains("0644") && all.contains("version-1") && all.contains("64 bits"),
        "{all}"
    );
    assert_eq!(loaded.key.m(), 4);
    // A new file round-trips through the public API, as version 2, unflagged.
    let new = dir.path().join("new.json");
    let key = stegongp::stego::generate_prf(3).unwrap();
    stegongp::stego::save_key(&new, &key, false).unwrap();
    let back = stegongp::stego::load_key_with_warnings(&new).unwrap();
    assert_eq!(back.key, key);
    assert!(!back.legacy_layout && back.version == 2 && back.warnings.is_empty());
    assert_eq!(json(&new)["secrets"].as_array().unwrap().len(), 3);

    // The CLI prints the loader's warnings on stderr when it uses the key (train).
    let exe = env!("CARGO_BIN_EXE_stegongp");
    let p = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    for (scene, out) in [("object", p("cover")), ("text", p("text"))] {
        let o = Command::new(exe)
            .args([
                "synth", "--scene", scene, "--res", "16", "--train", "2", "--test", "1", "--out",
                &out,
            ])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let o = Command::new(exe)
        .args([
            "train",
            &p("cover"),
            "--hidden",
            &p("text"),
            "--key",
            old.to_str().unwrap(),
            "--steps",
            "1",
            "--batch",
            "1024",
            "--log2-t",
            "14",
            "--out",
            &p("m.ingp"),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("warning:") && err.contains("old.json"),
        "{err}"
    );
    assert!(err.contains("version-1") && err.contains("0644"), "{err}");
}
