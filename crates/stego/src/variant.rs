//! Diagnostic variants of a key, for experiments by hand (`render` and `eval
//! --key-variant`): part of the key, leaked level subkeys, the paper's mixed keys, or a
//! wrong key of the same shape. Written `partial:P`, `levels:P` (P a fraction in [0, 1] or
//! a percentage), `mixed:pi1k2k3`, `mixed:pi1pi2k3`, `wrong[:SEED]`.

use super::keys::{Key, Mixed};
use ngp::error::{Error, Result};

/// A diagnostic variant of a key; [`KeyVariant::apply`] makes it from the key.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum KeyVariant {
    /// `partial:P`: [`Key::partial`], the first P of the m keys (for `prf` the first P of
    /// the m secrets), the rest Π (zero).
    Partial(f64),
    /// `levels:P`: [`Key::disclose_levels`], the subkeys of the first P of the m level
    /// groups, the other levels Π.
    Levels(f64),
    /// `mixed:pi1k2k3` or `mixed:pi1pi2k3`: [`Key::mixed`].
    Mixed(Mixed),
    /// `wrong[:SEED]` (seed 1 when not given): [`Key::wrong`], a random key of the same
    /// scheme, m and dense mode.
    Wrong(u64),
}

impl KeyVariant {
    /// The variant of `key`.
    pub fn apply(&self, key: &Key) -> Key {
        match *self {
            KeyVariant::Partial(p) => key.partial(p),
            KeyVariant::Levels(p) => key.disclose_levels(p),
            KeyVariant::Mixed(m) => key.mixed(m),
            KeyVariant::Wrong(seed) => Key::wrong(seed, key),
        }
    }
}

impl std::str::FromStr for KeyVariant {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        let bad = |what: String| Error::Config(format!("key variant '{s}': {what}"));
        let (kind, val) = s.split_once(':').unwrap_or((s, ""));
        Ok(match kind {
            "partial" | "levels" => {
                let p: f64 = val.trim_end_matches('%').parse().map_err(|e| {
                    bad(format!(
                        "expected {kind}:FRACTION, e.g. {kind}:0.5 or {kind}:50% ({e})"
                    ))
                })?;
                let p = if val.ends_with('%') { p / 100.0 } else { p };
                if !(0.0..=1.0).contains(&p) {
                    return Err(bad("the fraction must be in [0, 1]".into()));
                }
                if kind == "partial" {
                    KeyVariant::Partial(p)
                } else {
                    KeyVariant::Levels(p)
                }
            }
            "mixed" => match val {
                "pi1k2k3" => KeyVariant::Mixed(Mixed::Pi1K2K3),
                "pi1pi2k3" => KeyVariant::Mixed(Mixed::Pi1Pi2K3),
                _ => return Err(bad("expected mixed:pi1k2k3 or mixed:pi1pi2k3".into())),
            },
            "wrong" if val.is_empty() => KeyVariant::Wrong(1),
            "wrong" => KeyVariant::Wrong(val.parse().map_err(|e| {
                bad(format!(
                    "expected wrong or wrong:SEED (a whole number) ({e})"
                ))
            })?),
            _ => {
                return Err(bad(
                    "expected partial:P, levels:P, mixed:pi1k2k3, mixed:pi1pi2k3 or wrong[:SEED]"
                        .into(),
                ));
            }
        })
    }
}

/// The variant as [`KeyVariant::from_str`](std::str::FromStr) reads it back (fractions as
/// fractions, not percentages).
impl std::fmt::Display for KeyVariant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            KeyVariant::Partial(p) => write!(f, "partial:{p}"),
            KeyVariant::Levels(p) => write!(f, "levels:{p}"),
            KeyVariant::Mixed(Mixed::Pi1K2K3) => f.write_str("mixed:pi1k2k3"),
            KeyVariant::Mixed(Mixed::Pi1Pi2K3) => f.write_str("mixed:pi1pi2k3"),
            KeyVariant::Wrong(seed) => write!(f, "wrong:{seed}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::KeyVariant;
    use crate::{Key, Mixed, generate_prf};

    fn parse(s: &str) -> KeyVariant {
        s.parse().unwrap_or_else(|e| panic!("{s}: {e}"))
    }

    #[test]
    fn every_form_parses() {
        assert_eq!(parse("partial:0.5"), KeyVariant::Partial(0.5));
        assert_eq!(parse("partial:0"), KeyVariant::Partial(0.0));
        assert_eq!(parse("partial:1"), KeyVariant::Partial(1.0));
        assert_eq!(parse("levels:0.25"), KeyVariant::Levels(0.25));
        assert_eq!(parse("mixed:pi1k2k3"), KeyVariant::Mixed(Mixed::Pi1K2K3));
        assert_eq!(parse("mixed:pi1pi2k3"), KeyVariant::Mixed(Mixed::Pi1Pi2K3));
        assert_eq!(parse("wrong"), KeyVariant::Wrong(1));
        assert_eq!(parse("wrong:7"), KeyVariant::Wrong(7));
    }

    #[test]
    fn percentages_are_fractions() {
        assert_eq!(parse("partial:75%"), KeyVariant::Partial(0.75));
        assert_eq!(parse("levels:25%"), KeyVariant::Levels(0.25));
        assert_eq!(parse("levels:100%"), KeyVariant::Levels(1.0));
        assert_eq!(parse("partial:0%"), KeyVariant::Partial(0.0));
    }

    #[test]
    fn out_of_range_fractions_are_refused() {
        for bad in [
            "partial:25",
            "partial:1.01",
            "levels:-1",
            "levels:150%",
            "partial:-5%",
            "partial:NaN",
            "levels:inf",
        ] {
            let e = bad.parse::<KeyVariant>().unwrap_err().to_string();
            assert!(e.contains(&format!("'{bad}'")), "{bad}: {e}");
            assert!(e.contains("the fraction must be in [0, 1]"), "{bad}: {e}");
        }
    }

    #[test]
    fn garbage_is_refused_naming_the_input() {
        for (bad, says) in [
            ("half", "expected partial:P, levels:P, mixed:pi1k2k3"),
            ("", "expected partial:P"),
            (
                "partial",
                "expected partial:FRACTION, e.g. partial:0.5 or partial:50%",
            ),
            ("partial:x", "expected partial:FRACTION"),
            ("levels:", "expected levels:FRACTION"),
            ("mixed:k1", "expected mixed:pi1k2k3 or mixed:pi1pi2k3"),
            ("mixed", "expected mixed:pi1k2k3 or mixed:pi1pi2k3"),
            ("wrong:x", "expected wrong or wrong:SEED (a whole number)"),
            ("wrong:-1", "expected wrong or wrong:SEED"),
            ("Partial:0.5", "expected partial:P"),
        ] {
            let e = bad.parse::<KeyVariant>().unwrap_err().to_string();
            assert!(e.contains(&format!("key variant '{bad}'")), "{bad}: {e}");
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn display_reads_back() {
        for v in [
            KeyVariant::Partial(0.5),
            KeyVariant::Partial(1.0 / 3.0),
            KeyVariant::Levels(0.0),
            KeyVariant::Levels(1.0),
            KeyVariant::Mixed(Mixed::Pi1K2K3),
            KeyVariant::Mixed(Mixed::Pi1Pi2K3),
            KeyVariant::Wrong(1),
            KeyVariant::Wrong(u64::MAX),
        ] {
            assert_eq!(parse(&v.to_string()), v, "{v}");
        }
    }

    #[test]
    fn apply_is_the_key_method() {
        let key = generate_prf(4).unwrap();
        assert_eq!(KeyVariant::Partial(0.5).apply(&key), key.partial(0.5));
        assert_eq!(
            KeyVariant::Levels(0.25).apply(&key),
            key.disclose_levels(0.25)
        );
        assert_eq!(
            KeyVariant::Mixed(Mixed::Pi1Pi2K3).apply(&key),
            key.mixed(Mixed::Pi1Pi2K3)
        );
        assert_eq!(KeyVariant::Wrong(7).apply(&key), Key::wrong(7, &key));
        assert_ne!(KeyVariant::Wrong(7).apply(&key), key);
    }
}
