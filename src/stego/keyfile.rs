//! Key files: small versioned JSON, written atomically with owner-only permissions.
//!
//! ```json
//! {"format": "stegongp-key", "version": 1, "scheme": "primes", "dense": "permute",
//!  "keys": [[k1, k2, k3], ...]}
//! {"format": "stegongp-key", "version": 1, "scheme": "prf", "dense": "permute", "m": 4,
//!  "secret": "<64 hex digits>",
//!  "kdf": {"algorithm": "argon2id", "salt": "...", "m_cost_kib": 65536, "t_cost": 3, "p_cost": 1}}
//! ```
//! `dense` is optional (default `permute`), `kdf` is informational, `reference_groups`
//! (list of group numbers that fall back to the reference index) appears only in
//! diagnostic partial keys.

use super::keys::{DenseMode, KdfInfo, Key, KeyScheme, MAX_GROUPS, check_triple};
use crate::error::{Error, Result};
use serde_json::{Map, Value, json};
use std::path::Path;

pub const FORMAT: &str = "stegongp-key";
pub const VERSION: u64 = 1;

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) || !s.is_ascii() {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).ok())
        .collect()
}

/// The JSON document of a key (contains the secret).
pub fn key_to_json(key: &Key) -> Value {
    let mut o = Map::new();
    o.insert("format".into(), json!(FORMAT));
    o.insert("version".into(), json!(VERSION));
    o.insert("scheme".into(), json!(key.scheme().name()));
    o.insert("dense".into(), json!(key.dense().name()));
    match key.scheme() {
        KeyScheme::Primes { keys } => {
            o.insert("keys".into(), json!(keys));
        }
        KeyScheme::Prf { secret, m } => {
            o.insert("m".into(), json!(m));
            o.insert("secret".into(), json!(hex(secret)));
        }
    }
    if let Some(k) = key.kdf() {
        o.insert("kdf".into(), json!(k));
    }
    let rg = key.reference_group_list();
    if !rg.is_empty() {
        o.insert("reference_groups".into(), json!(rg));
    }
    Value::Object(o)
}

/// Writes `key` to `path` (mode 0600, atomic). Refuses to replace an existing file unless
/// `force`.
pub fn save_key(path: &Path, key: &Key, force: bool) -> Result<()> {
    if !force && std::fs::symlink_metadata(path).is_ok() {
        return Err(Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "key file exists (use --force to replace it)",
            ),
        ));
    }
    let mut text = serde_json::to_string_pretty(&key_to_json(key))
        .map_err(|e| Error::format(path, format!("serialising key: {e}")))?;
    text.push('\n');
    crate::util::write_atomic_with(path, |f| {
        // Restrict the (still empty) temporary file before any secret reaches it.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            f.set_permissions(std::fs::Permissions::from_mode(0o600))?;
        }
        std::io::Write::write_all(f, text.as_bytes())
    })
}

/// Reads and checks a key file. Errors name the file and the field.
pub fn load_key(path: &Path) -> Result<Key> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_key(path, &text)
}

/// Parses key-file text (`path` only names the source in errors).
pub fn parse_key(path: &Path, text: &str) -> Result<Key> {
    let bad = |field: &str, msg: String| Error::format(path, format!("field `{field}`: {msg}"));
    let v: Value = serde_json::from_str(text)
        .map_err(|e| Error::format(path, format!("malformed JSON: {e}")))?;
    let o = v
        .as_object()
        .ok_or_else(|| Error::format(path, "key file is not a JSON object"))?;
    let get = |field: &str| o.get(field).ok_or_else(|| bad(field, "missing".into()));
    let str_field = |field: &str| -> Result<&str> {
        get(field)?
            .as_str()
            .ok_or_else(|| bad(field, "expected a string".into()))
    };
    if let Some(f) = o.get("format")
        && f.as_str() != Some(FORMAT)
    {
        return Err(bad("format", format!("expected \"{FORMAT}\", got {f}")));
    }
    let version = get("version")?
        .as_u64()
        .ok_or_else(|| bad("version", "expected a non-negative integer".into()))?;
    if version != VERSION {
        return Err(bad(
            "version",
            format!("unsupported version {version} (this build reads version {VERSION})"),
        ));
    }
    let dense = match o.get("dense") {
        None => DenseMode::default(),
        Some(d) => d.as_str().and_then(DenseMode::parse).ok_or_else(|| {
            bad(
                "dense",
                format!("expected \"permute\" or \"hash\", got {d}"),
            )
        })?,
    };
    let scheme = match str_field("scheme")? {
        "primes" => {
            let arr = get("keys")?
                .as_array()
                .ok_or_else(|| bad("keys", "expected a list of prime triples".into()))?;
            if !(1..=MAX_GROUPS).contains(&arr.len()) {
                return Err(bad(
                    "keys",
                    format!("m = {} triples, expected 1..={MAX_GROUPS}", arr.len()),
                ));
            }
            let mut keys = Vec::with_capacity(arr.len());
            for (j, t) in arr.iter().enumerate() {
                let f = format!("keys[{j}]");
                let t = t
                    .as_array()
                    .filter(|t| t.len() == 3)
                    .ok_or_else(|| bad(&f, "expected 3 integers".into()))?;
                let mut triple = [0u64; 3];
                for (i, x) in t.iter().enumerate() {
                    triple[i] = x
                        .as_u64()
                        .ok_or_else(|| bad(&format!("{f}[{i}]"), format!("{x} is not a u64")))?;
                }
                check_triple(&triple).map_err(|(i, msg)| bad(&format!("{f}[{i}]"), msg))?;
                keys.push(triple);
            }
            KeyScheme::Primes { keys }
        }
        "prf" => {
            let m = get("m")?
                .as_u64()
                .ok_or_else(|| bad("m", "expected a positive integer".into()))?;
            if !(1..=MAX_GROUPS as u64).contains(&m) {
                return Err(bad("m", format!("m = {m}, expected 1..={MAX_GROUPS}")));
            }
            let s = str_field("secret")?;
            if s.len() != 64 {
                return Err(bad(
                    "secret",
                    format!(
                        "expected 64 hex digits (256 bits), got {} characters",
                        s.len()
                    ),
                ));
            }
            let bytes = unhex(s).ok_or_else(|| bad("secret", "not hexadecimal".into()))?;
            let mut secret = [0u8; 32];
            secret.copy_from_slice(&bytes);
            KeyScheme::Prf {
                secret,
                m: m as usize,
            }
        }
        other => {
            return Err(bad(
                "scheme",
                format!("unknown scheme \"{other}\" (expected \"primes\" or \"prf\")"),
            ));
        }
    };
    let kdf = match o.get("kdf") {
        None => None,
        Some(k) => {
            let ko = k
                .as_object()
                .ok_or_else(|| bad("kdf", "expected an object".into()))?;
            let s = |f: &str| {
                ko.get(f)
                    .and_then(Value::as_str)
                    .unwrap_or_default()
                    .to_string()
            };
            let n = |f: &str| ko.get(f).and_then(Value::as_u64).unwrap_or(0) as u32;
            Some(KdfInfo {
                algorithm: s("algorithm"),
                salt: s("salt"),
                m_cost_kib: n("m_cost_kib"),
                t_cost: n("t_cost"),
                p_cost: n("p_cost"),
            })
        }
    };
    let groups: Vec<usize> = match o.get("reference_groups") {
        None => vec![],
        Some(g) => g
            .as_array()
            .and_then(|a| a.iter().map(|x| x.as_u64().map(|v| v as usize)).collect())
            .ok_or_else(|| {
                bad(
                    "reference_groups",
                    "expected a list of group numbers".into(),
                )
            })?,
    };
    let key = Key::new(scheme, dense).map_err(|e| Error::format(path, e.to_string()))?;
    key.with_kdf(kdf)
        .with_reference_groups(&groups)
        .map_err(|e| bad("reference_groups", e.to_string()))
}
