//! `stegongp keygen` end to end: files, permissions, primes, nothing secret printed.

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
        child.stdin.take().unwrap().write_all(s.as_bytes()).unwrap();
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
        let secret = json(p)["secret"].as_str().unwrap().to_string();
        assert_eq!(secret.len(), 64);
        assert!(!out.contains(&secret[..8]), "{out}");
    }
    assert_eq!(json(&c)["secret"], json(&d)["secret"]);
    assert_eq!(json(&c)["m"], 4);

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
