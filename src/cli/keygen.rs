//! `stegongp keygen`: make a key file. Prints only the path, scheme, m, the passphrase
//! salt (not secret) and key strength — never key material.

use anyhow::bail;
use std::io::{BufRead, IsTerminal};
use std::path::{Path, PathBuf};
use stegongp::ngp::encoding::{GridConfig, GridLayout};
use stegongp::stego::{self, DenseMode, Key, SchemeKind, key_strength};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Key scheme.
    #[arg(long, value_enum, default_value_t = SchemeKind::Prf)]
    pub scheme: SchemeKind,
    /// Number of keys (groups of levels; level l uses key l mod m), 1 ≤ m ≤ levels.
    #[arg(long, default_value_t = 1)]
    pub m: usize,
    /// Derive the prf secret from a passphrase with Argon2id (read without echo, or from
    /// stdin when stdin is not a terminal).
    #[arg(long)]
    pub passphrase: bool,
    /// Salt for --passphrase; without it a random one is drawn, stored in the key file and
    /// printed (a salt is not secret). The same passphrase, salt and m give the same key.
    #[arg(long, requires = "passphrase")]
    pub salt: Option<String>,
    /// How dense (coarse) levels are keyed.
    #[arg(long, value_enum, default_value_t = DenseMode::Permute)]
    pub dense: DenseMode,
    /// The box (an aabb_scale) the hidden scene fills: 1 for an object (NeRF-synthetic,
    /// the generated scenes), a capture's own aabb_scale to hide a capture (fox 4, COLMAP
    /// and LLFF 16). In a cover with a larger box the hidden scene is confined to this one,
    /// so its key holder's grid, and a wrong key's, are empty outside it; `train` refuses
    /// a hidden scene larger than its key's box.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub aabb_scale: u32,
    /// Grid levels the key is meant for (checks m, and the strength report).
    #[arg(long, default_value_t = 16)]
    pub levels: u32,
    /// log2 of the hash table size T (for the strength report).
    #[arg(long, default_value_t = 19)]
    pub log2_hashmap_size: u32,
    /// Replace an existing key file (or a link at its path; the link's target is untouched).
    #[arg(long)]
    pub force: bool,
    /// Key file to write (created with mode 0600).
    #[arg(long)]
    pub out: PathBuf,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

fn read_passphrase() -> anyhow::Result<String> {
    if std::io::stdin().is_terminal() {
        let a = rpassword::prompt_password("Passphrase: ")?;
        let b = rpassword::prompt_password("Repeat passphrase: ")?;
        if a != b {
            bail!("the passphrases differ");
        }
        Ok(a)
    } else {
        let mut line = String::new();
        std::io::stdin().lock().read_line(&mut line)?;
        Ok(line.trim_end_matches(['\n', '\r']).to_string())
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    // Before a passphrase is asked for: a missing folder is the user's to make (we do not
    // choose where keys live, nor that folder's permissions).
    super::common::check_parent_dir(&args.out)?;
    let config = GridConfig {
        n_levels: args.levels,
        log2_hashmap_size: args.log2_hashmap_size,
        ..GridConfig::default()
    };
    let layout = GridLayout::new(config, 1)?;
    if !(1..=args.levels as usize).contains(&args.m) {
        bail!(
            "--m {} out of range: need 1 ≤ m ≤ {} levels",
            args.m,
            args.levels
        );
    }
    let key = match (args.scheme, args.passphrase) {
        (SchemeKind::Primes, true) => bail!("--passphrase applies to --scheme prf only"),
        (SchemeKind::Primes, false) => stego::generate_primes(args.m)?,
        (SchemeKind::Prf, false) => stego::generate_prf(args.m)?,
        (SchemeKind::Prf, true) => {
            let salt = match &args.salt {
                Some(s) if s.is_empty() => bail!("--salt must not be empty"),
                Some(s) => s.clone(),
                None => stego::random_salt()?,
            };
            let pass = read_passphrase()?;
            if pass.chars().count() < 8 {
                bail!("passphrase too short (at least 8 characters)");
            }
            stego::derive_prf_from_passphrase(&pass, &salt, args.m)?
        }
    };
    let key = key
        .with_dense(args.dense)
        .with_scene_box(Some(args.aabb_scale))
        .map_err(|e| anyhow::anyhow!("--aabb-scale: {e}"))?;
    key.validate_for(&layout)?;
    // The error already names the file.
    stego::save_key(&args.out, &key, args.force)?;
    let strength = key_strength(&key, &layout);
    let last = strength.after_disclosure.last();
    if args.json {
        let report = serde_json::json!({
            "path": args.out,
            "version": stego::keyfile::version_for(&key),
            "scheme": key.scheme().name(),
            "m": key.m(),
            "dense": key.dense().name(),
            "aabb_scale": key.scene_box(),
            "salt": key.kdf().map(|k| k.salt.clone()),
            "kdf": key.kdf(),
            "strength": strength,
        });
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "wrote {} (mode 0600): scheme {}, m = {}, dense levels: {}, scene box: aabb {}",
            args.out.display(),
            key.scheme().name(),
            key.m(),
            key.dense().name(),
            args.aabb_scale
        );
        println!(
            "key strength on {} levels, T = 2^{}: {:.1} bits brute force, {:.1} bits with a per-{} oracle",
            args.levels,
            args.log2_hashmap_size,
            strength.total_bits,
            strength.oracle_bits,
            if key.scheme().is_prf() {
                "level"
            } else {
                "key"
            }
        );
        if let (Some(d), true) = (last, key.m() > 1) {
            println!(
                "with {} of the {} keys disclosed: {:.1} bits brute force, {:.1} bits with the oracle",
                d.disclosed,
                key.m(),
                d.brute_force_bits,
                d.oracle_bits
            );
        }
        if let Some(p) = strength.paper_claim_bits {
            println!("(the paper counts {p:.1} bits for this m)");
        }
        if let Some(k) = key.kdf() {
            println!(
                "passphrase salt: {} (not secret; the passphrase with `--salt {} --m {}` recreates this key; Argon2id m = {} KiB, t = {}, p = {})",
                k.salt,
                k.salt,
                key.m(),
                k.m_cost_kib,
                k.t_cost,
                k.p_cost
            );
        }
    }
    Ok(())
}

/// Loads a key file for the CLI: prints the loader's warnings (permissions readable by
/// others, the old version-1 layout, diagnostic entries, weak KDF cost) on stderr.
pub fn load_key_reporting(path: &Path) -> anyhow::Result<Key> {
    let loaded = stego::load_key_with_warnings(path)?;
    for w in &loaded.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    Ok(loaded.key)
}
