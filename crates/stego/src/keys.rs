//! Keys: the `primes` scheme (the paper's) and the `prf` scheme (ours), the level → key
//! group assignment, and the diagnostic variants used by key-sensitivity experiments.

use super::prf::combine_secrets;
use super::primes::{self, is_prime};
use ngp::encoding::GridLayout;
use ngp::encoding::index::REFERENCE_PRIMES;
use ngp::error::{Error, Result};
use ngp::rng::Pcg32;

/// Π, the reference (default) key: tcnn's CoherentPrime constants.
pub const PI: [u64; 3] = [
    REFERENCE_PRIMES[0] as u64,
    REFERENCE_PRIMES[1] as u64,
    REFERENCE_PRIMES[2] as u64,
];

/// Largest number of key groups (the grid has at most 32 levels).
pub const MAX_GROUPS: usize = 32;

/// How a keyed dense level (res³ ≤ T) indexes its table. (The first paragraph of each
/// variant's comment is `keygen --dense`'s help.)
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum DenseMode {
    /// Keyed permutation of the dense levels' slots (no collisions).
    ///
    /// A permutation of the reference dense index: the hidden scene's cells stay
    /// collision-free, as the cover's are.
    #[default]
    Permute,
    /// Keyed hash modulo the dense level size.
    ///
    /// Collides ~37% of the cells and leaves ~37% of the slots unused.
    Hash,
}

impl DenseMode {
    pub fn name(self) -> &'static str {
        match self {
            DenseMode::Permute => "permute",
            DenseMode::Hash => "hash",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "permute" => Some(DenseMode::Permute),
            "hash" => Some(DenseMode::Hash),
            _ => None,
        }
    }
}

/// Which kind of key to make: what `keygen --scheme` and the experiments choose; the key
/// material itself is a [`KeyScheme`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum SchemeKind {
    /// The paper's: m triples of random primes in [1e7, 1e10].
    Primes,
    /// A 256-bit secret and SipHash-2-4 per level (stronger; default).
    Prf,
}

impl SchemeKind {
    pub fn name(self) -> &'static str {
        match self {
            SchemeKind::Prf => "prf",
            SchemeKind::Primes => "primes",
        }
    }
}

/// The secret part of a key. `Debug` never prints key material.
#[derive(Clone, PartialEq, Eq)]
pub enum KeyScheme {
    /// `m = keys.len()` prime triples; level l uses `keys[l mod m]`.
    Primes { keys: Vec<[u64; 3]> },
    /// `m = secrets.len()` independent 256-bit secrets (key file version 2). Every level's
    /// subkey is derived from the master [`combine_secrets`]`(secrets)`, i.e. from all m
    /// together: the index is all-or-nothing, and any m − 1 disclosed secrets leave the
    /// 256 bits of the last one to search.
    Prf { secrets: Vec<[u8; 32]> },
    /// The version-1 layout, read for compatibility only: one 256-bit secret whose m
    /// "keys" are shares of it (share j = bytes `[32j/m, 32(j+1)/m)`), so m − 1 disclosed
    /// keys leave only the last share (16 bits for m = 16) to search. `keygen` never
    /// makes one; [`Key::is_legacy_layout`] flags it.
    PrfShares { secret: [u8; 32], m: usize },
}

impl std::fmt::Debug for KeyScheme {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            KeyScheme::Primes { keys } => f
                .debug_struct("Primes")
                .field("m", &keys.len())
                .field("keys", &"<redacted>")
                .finish(),
            KeyScheme::Prf { secrets } => f
                .debug_struct("Prf")
                .field("m", &secrets.len())
                .field("secrets", &"<redacted>")
                .finish(),
            KeyScheme::PrfShares { m, .. } => f
                .debug_struct("PrfShares")
                .field("m", m)
                .field("secret", &"<redacted>")
                .finish(),
        }
    }
}

impl KeyScheme {
    pub fn name(&self) -> &'static str {
        self.kind().name()
    }
    pub fn m(&self) -> usize {
        match self {
            KeyScheme::Primes { keys } => keys.len(),
            KeyScheme::Prf { secrets } => secrets.len(),
            KeyScheme::PrfShares { m, .. } => *m,
        }
    }
    /// Either `prf` layout.
    pub fn is_prf(&self) -> bool {
        !matches!(self, KeyScheme::Primes { .. })
    }
    pub fn kind(&self) -> SchemeKind {
        if self.is_prf() {
            SchemeKind::Prf
        } else {
            SchemeKind::Primes
        }
    }
}

/// Bytes of share `j` of a version-1 (`PrfShares`) secret split into `m` shares.
pub fn share_range(m: usize, j: usize) -> std::ops::Range<usize> {
    32 * j / m..32 * (j + 1) / m
}

/// How a passphrase-derived secret was made (stored in the key file; the salt is not
/// secret, and with the passphrase it recreates the key).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct KdfInfo {
    pub algorithm: String,
    /// Argon2 version (19 = 0x13); 0 where a version-1 file did not record it (then it
    /// is not written back either).
    #[serde(skip_serializing_if = "is_zero")]
    pub version: u32,
    pub salt: String,
    pub m_cost_kib: u32,
    pub t_cost: u32,
    pub p_cost: u32,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

impl KdfInfo {
    /// The recorded Argon2id cost.
    pub fn cost(&self) -> Argon2Cost {
        Argon2Cost {
            m_cost_kib: self.m_cost_kib,
            t_cost: self.t_cost,
            p_cost: self.p_cost,
        }
    }
}

/// Argon2id cost parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Argon2Cost {
    pub m_cost_kib: u32,
    pub t_cost: u32,
    pub p_cost: u32,
}

impl Argon2Cost {
    /// `keygen`'s cost: 64 MiB, 3 passes, 1 lane — above both OWASP minimums.
    pub const DEFAULT: Argon2Cost = Argon2Cost {
        m_cost_kib: 64 * 1024,
        t_cost: 3,
        p_cost: 1,
    };

    /// OWASP's Argon2id minimum (Password Storage Cheat Sheet): m = 19 MiB (19456 KiB)
    /// with t = 2, or m = 46 MiB (47104 KiB) with t = 1 (p = 1 in both).
    pub fn meets_owasp(self) -> bool {
        self.p_cost >= 1
            && ((self.m_cost_kib >= 19_456 && self.t_cost >= 2)
                || (self.m_cost_kib >= 47_104 && self.t_cost >= 1))
    }
}

/// The key of one level group, as the index builder sees it.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum GroupKey {
    Reference,
    Primes([u64; 3]),
    Prf([u8; 32]),
}

/// Which primes of Π a mixed key keeps (the paper's key-sensitivity figure).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mixed {
    /// {π1, k2, k3}
    Pi1K2K3,
    /// {π1, π2, k3}
    Pi1Pi2K3,
}

/// A key: scheme, dense-level mode, (for diagnostic partial keys) the groups that fall
/// back to the reference index, and the box its hidden scene fills.
#[derive(Clone, PartialEq, Eq)]
pub struct Key {
    scheme: KeyScheme,
    dense: DenseMode,
    /// Bit j set: group j uses the reference index (a `prf` partial key).
    reference_groups: u32,
    kdf: Option<KdfInfo>,
    /// The aabb_scale of the box the hidden scene is confined to inside a larger model's
    /// (`None`: the model's whole box, as keys made before boxes existed).
    scene_box: Option<u32>,
    /// The model was trained with `train --robust`: the key's indices are confined to the
    /// entries the cover's stored grid reaches ([`crate::stealth::robust_indices`]).
    robust: bool,
}

impl std::fmt::Debug for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Key")
            .field("scheme", &self.scheme)
            .field("dense", &self.dense)
            .field("reference_groups", &self.reference_group_list())
            .field("scene_box", &self.scene_box)
            .field("robust", &self.robust)
            .finish()
    }
}

/// Checks one triple; `Err` carries the offending position (0-based) and reason.
pub(crate) fn check_triple(t: &[u64; 3]) -> std::result::Result<(), (usize, String)> {
    for (i, &k) in t.iter().enumerate() {
        // π1 = 1 is not prime; Π's own entries are allowed so that Π and mixed keys can be
        // written down.
        if k != PI[i] && !is_prime(k) {
            return Err((i, format!("{k} is not prime")));
        }
    }
    Ok(())
}

fn check_m(m: usize) -> Result<()> {
    if !(1..=MAX_GROUPS).contains(&m) {
        return Err(Error::Key(format!(
            "m = {m} key groups, expected 1..={MAX_GROUPS}"
        )));
    }
    Ok(())
}

impl Key {
    pub fn new(scheme: KeyScheme, dense: DenseMode) -> Result<Key> {
        check_m(scheme.m())?;
        if let KeyScheme::Primes { keys } = &scheme {
            for (j, t) in keys.iter().enumerate() {
                check_triple(t).map_err(|(i, msg)| Error::Key(format!("keys[{j}][{i}]: {msg}")))?;
            }
        }
        Ok(Key {
            scheme,
            dense,
            reference_groups: 0,
            kdf: None,
            scene_box: None,
            robust: false,
        })
    }

    /// Π on every level (primes, m = 1): exactly the reference index, dense levels included.
    pub fn reference() -> Key {
        Key {
            scheme: KeyScheme::Primes { keys: vec![PI] },
            dense: DenseMode::default(),
            reference_groups: 0,
            kdf: None,
            scene_box: None,
            robust: false,
        }
    }

    pub fn scheme(&self) -> &KeyScheme {
        &self.scheme
    }
    pub fn dense(&self) -> DenseMode {
        self.dense
    }
    pub fn m(&self) -> usize {
        self.scheme.m()
    }
    pub fn kdf(&self) -> Option<&KdfInfo> {
        self.kdf.as_ref()
    }
    /// A version-1 `prf` key: its m keys are shares of one secret (see
    /// [`KeyScheme::PrfShares`]); disclosing m − 1 of them leaves only the last share.
    pub fn is_legacy_layout(&self) -> bool {
        matches!(self.scheme, KeyScheme::PrfShares { .. })
    }
    pub fn with_dense(mut self, dense: DenseMode) -> Key {
        self.dense = dense;
        self
    }
    /// The box (an aabb_scale) the hidden scene fills inside the model's box, if the key
    /// says: training confines the scene to it, and the key holder's grid is cut to it.
    pub fn scene_box(&self) -> Option<u32> {
        self.scene_box
    }
    /// This key confining its scene to the box of `aabb_scale` (a power of two ≤ 128).
    pub fn with_scene_box(mut self, scene_box: Option<u32>) -> Result<Key> {
        if let Some(b) = scene_box
            && !((1..=128).contains(&b) && b.is_power_of_two())
        {
            return Err(Error::Key(format!(
                "scene box {b} is not a power of two between 1 and 128"
            )));
        }
        self.scene_box = scene_box;
        Ok(self)
    }
    /// Whether the model this key opens was trained with `train --robust` (its hidden
    /// scene confined to the entries the cover's stored grid reaches): the key file records
    /// it, so that reading a robust model needs the key alone.
    pub fn robust(&self) -> bool {
        self.robust
    }
    /// This key, recording (or not) that its scene trains and reads robustly.
    pub fn with_robust(mut self, robust: bool) -> Key {
        self.robust = robust;
        self
    }
    /// Whether both keys give every level the same index functions (their boxes and how
    /// they were made aside): two hidden scenes under such keys would overwrite each other.
    pub fn same_index(&self, other: &Key) -> bool {
        self.scheme == other.scheme
            && self.dense == other.dense
            && self.reference_groups == other.reference_groups
    }
    pub(crate) fn with_kdf(mut self, kdf: Option<KdfInfo>) -> Key {
        self.kdf = kdf;
        self
    }
    pub(crate) fn with_reference_groups(mut self, groups: &[usize]) -> Result<Key> {
        for &j in groups {
            if j >= self.m() {
                return Err(Error::Key(format!(
                    "reference group {j} ≥ m = {}",
                    self.m()
                )));
            }
            self.reference_groups |= 1 << j;
        }
        Ok(self)
    }
    /// Groups that use the reference index although the key has material for them.
    pub fn reference_group_list(&self) -> Vec<usize> {
        (0..self.m())
            .filter(|&j| self.reference_groups >> j & 1 == 1)
            .collect()
    }

    /// Key group of level `l` (0-based): `l mod m` (the paper's j = ((l−1) mod m) + 1).
    pub fn group_of_level(&self, l: usize) -> usize {
        l % self.m()
    }

    /// What group `j` indexes with.
    pub fn group(&self, j: usize) -> GroupKey {
        if self.reference_groups >> j & 1 == 1 {
            return GroupKey::Reference;
        }
        match &self.scheme {
            KeyScheme::Primes { keys } if keys[j] == PI => GroupKey::Reference,
            KeyScheme::Primes { keys } => GroupKey::Primes(keys[j]),
            // Every group's levels are keyed by the master of all m secrets.
            KeyScheme::Prf { secrets } => GroupKey::Prf(combine_secrets(secrets)),
            KeyScheme::PrfShares { secret, .. } => GroupKey::Prf(*secret),
        }
    }

    pub(crate) fn group_for_level(&self, l: usize) -> GroupKey {
        self.group(self.group_of_level(l))
    }

    /// True when every level uses the reference index.
    pub fn is_reference(&self) -> bool {
        (0..self.m()).all(|j| self.group(j) == GroupKey::Reference)
    }

    /// The m keys must fit the grid: 1 ≤ m ≤ L.
    pub fn validate_for(&self, layout: &GridLayout) -> Result<()> {
        let l = layout.levels.len();
        if !(1..=l).contains(&self.m()) {
            return Err(Error::Key(format!(
                "the key has m = {} key groups but the grid has {l} levels (need 1 ≤ m ≤ {l})",
                self.m()
            )));
        }
        Ok(())
    }

    /// Partial disclosure (paper §Multi-Key ablation): the first `round(p·m)` of the m keys
    /// are known, the rest replaced by the default. For `primes` the missing triples become Π,
    /// literally, and the levels they cover fall back to the reference index. For `prf` the
    /// m keys are the m independent secrets and a missing one is replaced by zero bytes
    /// (the "default secret"); every level's subkey is derived from all m together, so any
    /// missing secret changes every level: all-or-nothing. (A version-1 key's shares of its
    /// one secret are zeroed the same way.) p = 0 is no key at all (the reference index,
    /// i.e. the cover), as for `primes`. What the paper's per-level substitution would do
    /// to `prf` — subkeys of some levels leaked — is [`Key::disclose_levels`].
    pub fn partial(&self, fraction: f64) -> Key {
        let m = self.m();
        let keep = (fraction.clamp(0.0, 1.0) * m as f64).round() as usize;
        let mut k = self.clone();
        match &mut k.scheme {
            KeyScheme::Primes { keys } => {
                for t in keys.iter_mut().skip(keep) {
                    *t = PI;
                }
            }
            _ if keep == 0 => return self.disclose_levels(0.0),
            KeyScheme::Prf { secrets } => {
                for s in secrets.iter_mut().skip(keep) {
                    *s = [0; 32];
                }
            }
            KeyScheme::PrfShares { secret, .. } => {
                for b in secret.iter_mut().skip(32 * keep / m) {
                    *b = 0;
                }
            }
        }
        if keep < m && k.scheme.is_prf() {
            k.kdf = None;
        }
        k
    }

    /// Leaked level subkeys: the first `round(p·m)` groups of levels (l mod m < round(p·m))
    /// keep this key's index, the others use the reference index. For `primes` this equals
    /// [`Key::partial`]; for `prf` it models a side channel that leaks derived per-level
    /// subkeys, which the key file never exposes (the scenario the paper's table measures).
    pub fn disclose_levels(&self, fraction: f64) -> Key {
        let m = self.m();
        let keep = (fraction.clamp(0.0, 1.0) * m as f64).round() as usize;
        let mut k = self.clone();
        for j in keep..m {
            k.reference_groups |= 1 << j;
        }
        k
    }

    /// Mixed keys. `primes`: {π1,k2,k3} / {π1,π2,k3} in every triple. `prf` analogue: the
    /// first ⌊32/3⌋ / ⌊64/3⌋ bytes of every secret are replaced by zeros (the "default
    /// secret"), i.e. a third / two thirds of the key material is wrong.
    pub fn mixed(&self, which: Mixed) -> Key {
        let n = match which {
            Mixed::Pi1K2K3 => 1,
            Mixed::Pi1Pi2K3 => 2,
        };
        let mut k = self.clone();
        match &mut k.scheme {
            KeyScheme::Primes { keys } => {
                for t in keys.iter_mut() {
                    t[..n].copy_from_slice(&PI[..n]);
                }
            }
            KeyScheme::Prf { secrets } => {
                for s in secrets.iter_mut() {
                    s[..32 * n / 3].fill(0);
                }
            }
            KeyScheme::PrfShares { secret, .. } => secret[..32 * n / 3].fill(0),
        }
        k.kdf = None;
        k
    }

    /// A random key of the same scheme, m and dense mode (deterministic in `seed`).
    pub fn wrong(seed: u64, like: &Key) -> Key {
        let mut rng = Pcg32::new(seed, 0x5717_6e67);
        let mut next = move || Ok((rng.next_u32() as u64) << 32 | rng.next_u32() as u64);
        let scheme = match &like.scheme {
            KeyScheme::Primes { keys } => KeyScheme::Primes {
                // A PCG stream never fails, so the fallback is unreachable.
                keys: primes::random_prime_triples(keys.len(), &mut next)
                    .unwrap_or_else(|_| vec![PI; keys.len()]),
            },
            KeyScheme::Prf { secrets } => KeyScheme::Prf {
                secrets: (0..secrets.len())
                    .map(|_| random_secret(&mut next).unwrap_or([0; 32]))
                    .collect(),
            },
            KeyScheme::PrfShares { m, .. } => KeyScheme::PrfShares {
                secret: random_secret(&mut next).unwrap_or([0; 32]),
                m: *m,
            },
        };
        // Same box and mode: a wrong key is tried where, and as, the hidden scene is read.
        Key {
            scheme,
            dense: like.dense,
            reference_groups: 0,
            kdf: None,
            scene_box: like.scene_box,
            robust: like.robust,
        }
    }
}

/// `m` random triples of distinct primes in [1e7, 1e10] from the OS CSPRNG.
pub fn generate_primes(m: usize) -> Result<Key> {
    generate_with(SchemeKind::Primes, m, primes::os_u64)
}

/// `m` independent random 256-bit secrets from the OS CSPRNG (key file version 2).
pub fn generate_prf(m: usize) -> Result<Key> {
    generate_with(SchemeKind::Prf, m, primes::os_u64)
}

/// A key of `kind` drawn from `next_u64`. The OS CSPRNG for real keys; a seeded generator
/// only for experiments whose reports must be reproducible.
pub fn generate_with(
    kind: SchemeKind,
    m: usize,
    mut next_u64: impl FnMut() -> Result<u64>,
) -> Result<Key> {
    check_m(m)?;
    let scheme = if kind == SchemeKind::Prf {
        KeyScheme::Prf {
            secrets: (0..m)
                .map(|_| random_secret(&mut next_u64))
                .collect::<Result<_>>()?,
        }
    } else {
        KeyScheme::Primes {
            keys: primes::random_prime_triples(m, next_u64)?,
        }
    };
    Key::new(scheme, DenseMode::default())
}

fn random_secret(next_u64: &mut impl FnMut() -> Result<u64>) -> Result<[u8; 32]> {
    let mut secret = [0u8; 32];
    for c in secret.chunks_mut(8) {
        c.copy_from_slice(&next_u64()?.to_le_bytes());
    }
    Ok(secret)
}

/// A fresh passphrase salt: 128 bits from the OS CSPRNG as 32 hex digits. Salts are not
/// secret; `keygen` stores and prints it so that passphrase + salt recreate the key.
pub fn random_salt() -> Result<String> {
    let (a, b) = (primes::os_u64()?, primes::os_u64()?);
    Ok(format!("{a:016x}{b:016x}"))
}

/// Domain salt prepended to the user's salt, so the same passphrase gives unrelated
/// secrets here and in any other Argon2id use.
pub const PASSPHRASE_DOMAIN: &str = "stegongp/prf-key/v2";

/// Domain label of the per-secret expansion of a passphrase root.
pub const PASSPHRASE_SECRET_DOMAIN: &[u8] = b"stegongp/v2/passphrase-secret";

/// A `prf` key from a passphrase with [`Argon2Cost::DEFAULT`]; see
/// [`derive_prf_from_passphrase_with`].
pub fn derive_prf_from_passphrase(pass: &str, salt: &str, m: usize) -> Result<Key> {
    derive_prf_from_passphrase_with(pass, salt, m, Argon2Cost::DEFAULT)
}

/// A `prf` key from a passphrase: `root = Argon2id(pass, "stegongp/prf-key/v2\0" ‖ salt)`
/// (32 bytes, `cost`), then secret j = `W(root, "stegongp/v2/passphrase-secret" ‖ 0x00 ‖
/// m ‖ j)` (u32 LE; W = [`super::prf::wide_prf`]): m secrets, each with its own index. The
/// same passphrase, salt, m and cost always give the same key. The salt must not be
/// empty (`keygen` draws a random one). A passphrase key is only as strong as the
/// passphrase: anyone holding one of its secrets can test guesses at one Argon2id each.
pub fn derive_prf_from_passphrase_with(
    pass: &str,
    salt: &str,
    m: usize,
    cost: Argon2Cost,
) -> Result<Key> {
    check_m(m)?;
    if pass.is_empty() {
        return Err(Error::Key("empty passphrase".into()));
    }
    if salt.is_empty() {
        return Err(Error::Key("empty passphrase salt".into()));
    }
    let params = argon2::Params::new(cost.m_cost_kib, cost.t_cost, cost.p_cost, Some(32))
        .map_err(|e| Error::Other(format!("argon2 parameters: {e}")))?;
    let a = argon2::Argon2::new(argon2::Algorithm::Argon2id, argon2::Version::V0x13, params);
    let mut full_salt = Vec::from(PASSPHRASE_DOMAIN.as_bytes());
    full_salt.push(0);
    full_salt.extend_from_slice(salt.as_bytes());
    let mut root = [0u8; 32];
    a.hash_password_into(pass.as_bytes(), &full_salt, &mut root)
        .map_err(|e| Error::Other(format!("argon2id: {e}")))?;
    let secrets = (0..m as u32)
        .map(|j| {
            let mut msg = Vec::from(PASSPHRASE_SECRET_DOMAIN);
            msg.push(0);
            msg.extend_from_slice(&(m as u32).to_le_bytes());
            msg.extend_from_slice(&j.to_le_bytes());
            super::prf::wide_prf(&root, &msg)
        })
        .collect();
    let kdf = KdfInfo {
        algorithm: "argon2id".into(),
        version: 0x13,
        salt: salt.into(),
        m_cost_kib: cost.m_cost_kib,
        t_cost: cost.t_cost,
        p_cost: cost.p_cost,
    };
    Ok(Key::new(KeyScheme::Prf { secrets }, DenseMode::default())?.with_kdf(Some(kdf)))
}
