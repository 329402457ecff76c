//! Key files: small versioned JSON, created owner-only and never written through a link.
//!
//! Version 2 (what [`save_key`] writes for every key but a version-1 `prf` key):
//! ```json
//! {"format": "stegongp-key", "version": 2, "scheme": "primes", "dense": "permute",
//!  "keys": [[k1, k2, k3], ...]}
//! {"format": "stegongp-key", "version": 2, "scheme": "prf", "dense": "permute", "m": 2,
//!  "secrets": ["<64 hex digits>", "<64 hex digits>"],
//!  "kdf": {"algorithm": "argon2id", "version": 19, "salt": "...", "m_cost_kib": 65536,
//!          "t_cost": 3, "p_cost": 1}}
//! ```
//! A `prf` key holds m independent 256-bit secrets (`m` is optional and must equal their
//! number). Version 1 — still read, and flagged ([`LoadedKey::legacy_layout`], a warning)
//! — has the same `primes` layout and, for `prf`, one `"secret"` whose m keys are shares
//! (see [`KeyScheme::PrfShares`]); a version-1 `prf` key is written back as version 1, the
//! only layout that keeps its index functions.
//!
//! `aabb_scale` (optional, a power of two ≤ 128) is the box the hidden scene fills inside
//! the model's: training confines the scene to it and the key holder's occupancy grid is
//! cut to it (absent: the model's whole box, as in keys made before it existed).
//! `robust` (optional, default false) says the model was trained with `train --robust`:
//! the key holder confines the key's indices to the entries the cover's stored grid
//! reaches, as training did.
//! `dense` is optional (default `permute`); `kdf` records how a passphrase key was made
//! (the salt is not secret: passphrase + salt recreate the key); `reference_groups` (group
//! numbers that fall back to the reference index) appears only in diagnostic partial keys.
//!
//! `primes` entries must be primes in the paper's range [1e7, 1e10], pairwise distinct
//! within a triple, on load and on save; the one exception is an entry equal to Π's at
//! the same position (π1 = 1, π2, π3: the reference and the paper's mixed keys), accepted
//! with a warning.
//!
//! Writing: a temporary file with a random name in the target directory, created with
//! `O_CREAT | O_EXCL` (so never through a symlink) and mode 0600 from the moment it exists,
//! filled and synced, then linked into place — `link(2)` fails if anything, even a
//! dangling symlink, is at the path, so nothing is replaced without `force`; with `force`,
//! `rename(2)` replaces the path itself (a symlink there is replaced, its target untouched).

use super::keys::{DenseMode, KdfInfo, Key, KeyScheme, MAX_GROUPS, PI};
use super::primes::{PRIME_RANGE, is_prime};
use ngp::error::{Error, Result};
use serde_json::{Map, Value, json};
use std::io::Write;
use std::path::{Path, PathBuf};

pub const FORMAT: &str = "stegongp-key";
/// The version [`save_key`] writes.
pub const VERSION: u64 = 2;
/// The previous version: still read; its `prf` layout is flagged as the weaker one.
pub const LEGACY_VERSION: u64 = 1;

/// A key read from a file, with what the caller should tell the user.
#[derive(Debug)]
pub struct LoadedKey {
    pub key: Key,
    /// The file's format version.
    pub version: u64,
    /// True for a version-1 `prf` key (m shares of one secret, not m secrets).
    pub legacy_layout: bool,
    /// Human-readable warnings (file permissions, legacy layout, Π entries, KDF cost), for
    /// the CLI to print on stderr. The library never prints them.
    pub warnings: Vec<String>,
}

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

/// The file format version `key` is written in.
pub fn version_for(key: &Key) -> u64 {
    if key.is_legacy_layout() {
        LEGACY_VERSION
    } else {
        VERSION
    }
}

/// The JSON document of a key (contains the secret).
pub fn key_to_json(key: &Key) -> Value {
    let mut o = Map::new();
    o.insert("format".into(), json!(FORMAT));
    o.insert("version".into(), json!(version_for(key)));
    o.insert("scheme".into(), json!(key.scheme().name()));
    o.insert("dense".into(), json!(key.dense().name()));
    match key.scheme() {
        KeyScheme::Primes { keys } => {
            o.insert("keys".into(), json!(keys));
        }
        KeyScheme::Prf { secrets } => {
            o.insert("m".into(), json!(secrets.len()));
            let hexes: Vec<String> = secrets.iter().map(|s| hex(s)).collect();
            o.insert("secrets".into(), json!(hexes));
        }
        KeyScheme::PrfShares { secret, m } => {
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
    if let Some(b) = key.scene_box() {
        o.insert("aabb_scale".into(), json!(b));
    }
    if key.robust() {
        o.insert("robust".into(), json!(true));
    }
    Value::Object(o)
}

/// Checks one triple of a key file: each entry a prime in [1e7, 1e10], the three
/// distinct. An entry equal to Π's at its position is allowed (returned as a note).
/// `Err` names the position (0-based) and the value.
fn check_file_triple(t: &[u64; 3]) -> std::result::Result<Vec<usize>, (usize, String)> {
    let mut pi_entries = Vec::new();
    for (i, &k) in t.iter().enumerate() {
        if k == PI[i] {
            pi_entries.push(i);
            continue;
        }
        if !(PRIME_RANGE.0..=PRIME_RANGE.1).contains(&k) {
            return Err((
                i,
                format!(
                    "{k} is outside the primes' range [{}, {}]",
                    PRIME_RANGE.0, PRIME_RANGE.1
                ),
            ));
        }
        if !is_prime(k) {
            return Err((i, format!("{k} is not prime")));
        }
    }
    for i in 0..3 {
        for j in i + 1..3 {
            if t[i] == t[j] {
                return Err((
                    j,
                    format!("{} is repeated in the triple (also at [{i}])", t[j]),
                ));
            }
        }
    }
    Ok(pi_entries)
}

/// Key-file checks of a key's content; `Ok` carries warnings.
fn check_key_content(key: &Key) -> std::result::Result<Vec<String>, (String, String)> {
    let mut warnings = Vec::new();
    match key.scheme() {
        KeyScheme::Primes { keys } => {
            for (j, t) in keys.iter().enumerate() {
                let pi = check_file_triple(t)
                    .map_err(|(i, msg)| (format!("keys[{j}][{i}]"), format!("key {j}: {msg}")))?;
                if !pi.is_empty() && *t != PI {
                    warnings.push(format!(
                        "key {j} has entries of the reference Π at positions {pi:?}: a diagnostic (mixed) key, not a secret one"
                    ));
                }
            }
        }
        KeyScheme::Prf { secrets } => {
            for (j, s) in secrets.iter().enumerate() {
                if *s == [0; 32] && key.reference_group_list().is_empty() {
                    warnings.push(format!(
                        "secret {j} is all zeros: a diagnostic partial key, not a secret one"
                    ));
                }
            }
        }
        KeyScheme::PrfShares { m, .. } => warnings.push(if *m > 1 {
            format!(
                "version-1 prf key (the old, weaker layout): its m = {m} keys are shares of one 256-bit secret, so m − 1 disclosed keys leave only {} bits to search; `stegongp keygen` makes a version-2 key (m independent secrets), which needs the model retrained",
                8 * (32 / m)
            )
        } else {
            "version-1 prf key (the old layout; with m = 1 its one secret is as strong as version 2's): `stegongp keygen` now writes version 2".to_string()
        }),
    }
    if let Some(k) = key.kdf()
        && k.algorithm == "argon2id"
        && !k.cost().meets_owasp()
    {
        warnings.push(format!(
            "passphrase key made with Argon2id m = {} KiB, t = {}, p = {}: below the OWASP minimum (19 MiB with t = 2, or 46 MiB with t = 1)",
            k.m_cost_kib, k.t_cost, k.p_cost
        ));
    }
    Ok(warnings)
}

/// Warnings about a key file's permissions: it should be readable and writable by its
/// owner only. Empty where the file cannot be inspected (loading reports that).
pub fn key_file_warnings(path: &Path) -> Vec<String> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        if let Ok(meta) = std::fs::metadata(path) {
            let mode = meta.permissions().mode() & 0o777;
            if mode & 0o077 != 0 {
                let who = match (mode & 0o070 != 0, mode & 0o007 != 0) {
                    (true, true) => "group and others",
                    (true, false) => "its group",
                    _ => "others",
                };
                return vec![format!(
                    "key file {} has mode {mode:04o}: {who} can access it (run `chmod 600 {}`)",
                    path.display(),
                    path.display()
                )];
            }
        }
    }
    #[cfg(not(unix))]
    let _ = path;
    Vec::new()
}

/// Writes `key` to `path`: owner-only (0600) from creation, atomic, never through a
/// symlink. Refuses to replace an existing file (or link) unless `force`; refuses a
/// `primes` key that [`load_key`] would refuse.
pub fn save_key(path: &Path, key: &Key, force: bool) -> Result<()> {
    check_key_content(key).map_err(|(field, msg)| {
        Error::format(path, format!("field `{field}`: {msg} (not written)"))
    })?;
    let mut text = serde_json::to_string_pretty(&key_to_json(key))
        .map_err(|e| Error::format(path, format!("serialising key: {e}")))?;
    text.push('\n');
    let mut random_name = || -> Result<String> {
        let r = super::primes::os_u64()?;
        Ok(format!("{r:016x}"))
    };
    write_private(path, text.as_bytes(), force, &mut random_name)
}

/// Writes a secret file other than a key (a stego run's training state, which describes
/// its hidden scenes) as [`save_key`] writes a key: owner-only from creation, atomic, never
/// through a symlink; an existing file is replaced.
pub fn write_secret(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut random_name = || -> Result<String> {
        let r = super::primes::os_u64()?;
        Ok(format!("{r:016x}"))
    };
    write_private(path, bytes, true, &mut random_name)
}

/// The writer behind [`save_key`], with the temporary names' random part supplied (tests
/// plant a symlink at a chosen name). Tries up to 8 names: a name that exists — file or
/// link — is skipped, never opened.
#[doc(hidden)]
pub fn write_private(
    path: &Path,
    bytes: &[u8],
    force: bool,
    random_name: &mut dyn FnMut() -> Result<String>,
) -> Result<()> {
    let exists_err = || {
        Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "key file exists (use --force to replace it)",
            ),
        )
    };
    if !force && std::fs::symlink_metadata(path).is_ok() {
        return Err(exists_err());
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .ok_or_else(|| Error::format(path, "not a file path"))?
        .to_string_lossy()
        .into_owned();
    let mut opened = None;
    for _ in 0..8 {
        let tmp = dir.join(format!(".{name}.{}.tmp", random_name()?));
        match create_private(&tmp) {
            Ok(f) => {
                opened = Some((tmp, f));
                break;
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(Error::io(path, e)),
        }
    }
    let Some((tmp, mut f)) = opened else {
        return Err(Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "could not create a fresh temporary file next to it",
            ),
        ));
    };
    let result = (|| {
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        if force {
            std::fs::rename(&tmp, path)
        } else {
            match std::fs::hard_link(&tmp, path) {
                Ok(()) => std::fs::remove_file(&tmp),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(e),
                // No hard links on this file system: check, then rename (a narrow race).
                Err(_) if std::fs::symlink_metadata(path).is_ok() => Err(std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    "exists",
                )),
                Err(_) => std::fs::rename(&tmp, path),
            }
        }
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        if e.kind() == std::io::ErrorKind::AlreadyExists {
            return Err(exists_err());
        }
        return Err(Error::io(path, e));
    }
    ngp::util::sync_folder_of(path)
}

/// A new file, created exclusively (fails if anything, a symlink included, is there),
/// owner-only from the start.
fn create_private(p: &Path) -> std::io::Result<std::fs::File> {
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(0o600);
    }
    o.open(p)
}

/// Reads and checks a key file. Errors name the file and the field. Warnings are dropped:
/// the CLI uses [`load_key_with_warnings`].
pub fn load_key(path: &Path) -> Result<Key> {
    Ok(load_key_with_warnings(path)?.key)
}

/// Reads and checks a key file, with its version, layout flag and warnings (including
/// [`key_file_warnings`]).
pub fn load_key_with_warnings(path: &Path) -> Result<LoadedKey> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut loaded = parse_key_with_warnings(path, &text)?;
    let mut w = key_file_warnings(path);
    w.append(&mut loaded.warnings);
    loaded.warnings = w;
    Ok(loaded)
}

/// Parses key-file text (`path` only names the source in errors).
pub fn parse_key(path: &Path, text: &str) -> Result<Key> {
    Ok(parse_key_with_warnings(path, text)?.key)
}

/// Parses key-file text, with the version, layout flag and content warnings.
pub fn parse_key_with_warnings(path: &Path, text: &str) -> Result<LoadedKey> {
    let v: Value = serde_json::from_str(text)
        .map_err(|e| Error::format(path, format!("malformed JSON: {e}")))?;
    let o = v
        .as_object()
        .ok_or_else(|| Error::format(path, "key file is not a JSON object"))?;
    let doc = KeyJson { path, o };
    let version = doc.version()?;
    let dense = doc.dense()?;
    let scheme = doc.scheme(version)?;
    let kdf = doc.kdf()?;
    let groups = doc.reference_groups()?;
    let scene_box = doc.scene_box()?;
    let robust = doc.robust()?;
    let key = Key::new(scheme, dense).map_err(|e| Error::format(path, e.to_string()))?;
    let key = key
        .with_robust(robust)
        .with_kdf(kdf)
        .with_reference_groups(&groups)
        .map_err(|e| doc.bad("reference_groups", e.to_string()))?
        .with_scene_box(scene_box)
        .map_err(|e| doc.bad("aabb_scale", e.to_string()))?;
    let warnings = check_key_content(&key).map_err(|(field, msg)| doc.bad(&field, msg))?;
    Ok(LoadedKey {
        legacy_layout: key.is_legacy_layout(),
        key,
        version,
        warnings,
    })
}

/// A key file's top-level object, read field by field; errors name the file and the field.
struct KeyJson<'a> {
    path: &'a Path,
    o: &'a Map<String, Value>,
}

impl<'a> KeyJson<'a> {
    fn bad(&self, field: &str, msg: String) -> Error {
        Error::format(self.path, format!("field `{field}`: {msg}"))
    }

    fn get(&self, field: &str) -> Result<&'a Value> {
        self.o
            .get(field)
            .ok_or_else(|| self.bad(field, "missing".into()))
    }

    fn str_field(&self, field: &str) -> Result<&'a str> {
        self.get(field)?
            .as_str()
            .ok_or_else(|| self.bad(field, "expected a string".into()))
    }

    /// The file's version, once its `format` (optional) says it is a key file.
    fn version(&self) -> Result<u64> {
        if let Some(f) = self.o.get("format")
            && f.as_str() != Some(FORMAT)
        {
            return Err(self.bad("format", format!("expected \"{FORMAT}\", got {f}")));
        }
        let version = self
            .get("version")?
            .as_u64()
            .ok_or_else(|| self.bad("version", "expected a non-negative integer".into()))?;
        if version != VERSION && version != LEGACY_VERSION {
            return Err(self.bad(
                "version",
                format!(
                    "unsupported version {version} (this build reads versions {LEGACY_VERSION} and {VERSION})"
                ),
            ));
        }
        Ok(version)
    }

    fn dense(&self) -> Result<DenseMode> {
        Ok(match self.o.get("dense") {
            None => DenseMode::default(),
            Some(d) => d.as_str().and_then(DenseMode::parse).ok_or_else(|| {
                self.bad(
                    "dense",
                    format!("expected \"permute\" or \"hash\", got {d}"),
                )
            })?,
        })
    }

    /// The optional `m` of a `prf` key.
    fn m(&self) -> Result<Option<usize>> {
        let Some(m) = self.o.get("m") else {
            return Ok(None);
        };
        let m = m
            .as_u64()
            .ok_or_else(|| self.bad("m", "expected a positive integer".into()))?;
        if !(1..=MAX_GROUPS as u64).contains(&m) {
            return Err(self.bad("m", format!("m = {m}, expected 1..={MAX_GROUPS}")));
        }
        Ok(Some(m as usize))
    }

    /// The key itself, as `scheme` says and `version` lays it out.
    fn scheme(&self, version: u64) -> Result<KeyScheme> {
        match self.str_field("scheme")? {
            "primes" => self.primes(),
            "prf" if version == LEGACY_VERSION => {
                let m = self.m()?.ok_or_else(|| self.bad("m", "missing".into()))?;
                let secret = self.secret(self.get("secret")?, "secret")?;
                Ok(KeyScheme::PrfShares { secret, m })
            }
            "prf" => self.prf(),
            other => Err(self.bad(
                "scheme",
                format!("unknown scheme \"{other}\" (expected \"primes\" or \"prf\")"),
            )),
        }
    }

    /// `keys`: m checked prime triples.
    fn primes(&self) -> Result<KeyScheme> {
        let arr = self
            .get("keys")?
            .as_array()
            .ok_or_else(|| self.bad("keys", "expected a list of prime triples".into()))?;
        if !(1..=MAX_GROUPS).contains(&arr.len()) {
            return Err(self.bad(
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
                .ok_or_else(|| self.bad(&f, format!("key {j}: expected 3 integers")))?;
            let mut triple = [0u64; 3];
            for (i, x) in t.iter().enumerate() {
                triple[i] = x.as_u64().ok_or_else(|| {
                    self.bad(&format!("{f}[{i}]"), format!("key {j}: {x} is not a u64"))
                })?;
            }
            check_file_triple(&triple)
                .map_err(|(i, msg)| self.bad(&format!("{f}[{i}]"), format!("key {j}: {msg}")))?;
            keys.push(triple);
        }
        Ok(KeyScheme::Primes { keys })
    }

    /// A version-2 `prf` key: `secrets`, as many as `m` says where it is given.
    fn prf(&self) -> Result<KeyScheme> {
        let arr = self
            .get("secrets")?
            .as_array()
            .ok_or_else(|| self.bad("secrets", "expected a list of 64-hex-digit strings".into()))?;
        if !(1..=MAX_GROUPS).contains(&arr.len()) {
            return Err(self.bad(
                "secrets",
                format!("m = {} secrets, expected 1..={MAX_GROUPS}", arr.len()),
            ));
        }
        if let Some(m) = self.m()?
            && m != arr.len()
        {
            return Err(self.bad(
                "m",
                format!("m = {m} but the file has {} secrets", arr.len()),
            ));
        }
        let secrets = arr
            .iter()
            .enumerate()
            .map(|(j, s)| self.secret(s, &format!("secrets[{j}]")))
            .collect::<Result<Vec<_>>>()?;
        Ok(KeyScheme::Prf { secrets })
    }

    /// Parses 64 hex digits.
    fn secret(&self, v: &Value, field: &str) -> Result<[u8; 32]> {
        let s = v
            .as_str()
            .ok_or_else(|| self.bad(field, "expected a string of 64 hex digits".into()))?;
        if s.len() != 64 {
            return Err(self.bad(
                field,
                format!(
                    "expected 64 hex digits (256 bits), got {} characters",
                    s.len()
                ),
            ));
        }
        let bytes = unhex(s).ok_or_else(|| self.bad(field, "not hexadecimal".into()))?;
        let mut secret = [0u8; 32];
        secret.copy_from_slice(&bytes);
        Ok(secret)
    }

    /// How a passphrase key was made, if it was: missing entries read as empty or 0.
    fn kdf(&self) -> Result<Option<KdfInfo>> {
        let Some(k) = self.o.get("kdf") else {
            return Ok(None);
        };
        let ko = k
            .as_object()
            .ok_or_else(|| self.bad("kdf", "expected an object".into()))?;
        let s = |f: &str| {
            ko.get(f)
                .and_then(Value::as_str)
                .unwrap_or_default()
                .to_string()
        };
        let n = |f: &str| ko.get(f).and_then(Value::as_u64).unwrap_or(0) as u32;
        Ok(Some(KdfInfo {
            algorithm: s("algorithm"),
            version: n("version"),
            salt: s("salt"),
            m_cost_kib: n("m_cost_kib"),
            t_cost: n("t_cost"),
            p_cost: n("p_cost"),
        }))
    }

    fn reference_groups(&self) -> Result<Vec<usize>> {
        Ok(match self.o.get("reference_groups") {
            None => vec![],
            Some(g) => g
                .as_array()
                .and_then(|a| a.iter().map(|x| x.as_u64().map(|v| v as usize)).collect())
                .ok_or_else(|| {
                    self.bad(
                        "reference_groups",
                        "expected a list of group numbers".into(),
                    )
                })?,
        })
    }

    fn scene_box(&self) -> Result<Option<u32>> {
        let Some(b) = self.o.get("aabb_scale") else {
            return Ok(None);
        };
        let b = b
            .as_u64()
            .filter(|&b| (1..=128).contains(&b) && b.is_power_of_two())
            .ok_or_else(|| {
                self.bad(
                    "aabb_scale",
                    format!("expected a power of two between 1 and 128, got {b}"),
                )
            })?;
        Ok(Some(b as u32))
    }

    fn robust(&self) -> Result<bool> {
        match self.o.get("robust") {
            None => Ok(false),
            Some(v) => v
                .as_bool()
                .ok_or_else(|| self.bad("robust", format!("expected true or false, got {v}"))),
        }
    }
}
