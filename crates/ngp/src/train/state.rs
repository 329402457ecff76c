//! A trainer's whole state between two steps, as bytes: what a run killed at step 49 000
//! needs to go on exactly where it stopped. Restored into a trainer built from the same
//! scenes and options, the next steps are the ones the uninterrupted run would have taken,
//! bit for bit (on the CPU, with the same worker count: the gradient partitions are summed
//! in a fixed order). The GPU trainer writes the same document with `device: gpu` in its
//! fingerprint and what it keeps on the device; a state goes back only into its own kind of
//! trainer, and on the GPU the next steps are the same steps, not bit for bit (its float
//! sums depend on the order its threads add in).
//!
//! The document is msgpack: `format`, `version`, a `fingerprint` of what must not change
//! (layout, scenes, options, workers), then the weights, the optimizer's moments and EMA,
//! the occupancy-update clock and every scene's grid and batch counters, arrays as
//! little-endian binaries. Every length is checked against the trainer before anything is
//! copied, so a damaged or forged file is an error naming the field.

use crate::error::{Error, Result};
use crate::snapshot::msgpack;
/// The document's values, for backends that write their own states (the GPU trainer's).
pub use rmpv::Value;
use std::path::Path;

pub const FORMAT: &str = "stegongp-train-state";
pub const VERSION: u64 = 1;
/// The fingerprint entry naming the kind of trainer that saved a state; a state without it
/// is the CPU trainer's.
pub const DEVICE: &str = "device";

pub fn f32s(v: &[f32]) -> Value {
    Value::Binary(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

pub fn u32s(v: &[u32]) -> Value {
    Value::Binary(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

pub fn map(entries: Vec<(&str, Value)>) -> Value {
    Value::Map(
        entries
            .into_iter()
            .map(|(k, v)| (Value::String(k.into()), v))
            .collect(),
    )
}

pub fn encode(v: &Value) -> Vec<u8> {
    let mut out = Vec::new();
    msgpack::encode(v, &mut out);
    out
}

/// Reads fields of one map of the document; errors name the file and the field's path.
pub struct Fields<'a> {
    origin: &'a Path,
    at: String,
    entries: &'a [(Value, Value)],
}

impl<'a> Fields<'a> {
    pub fn top(origin: &'a Path, v: &'a Value) -> Result<Self> {
        match v {
            Value::Map(m) => Ok(Fields {
                origin,
                at: String::new(),
                entries: m,
            }),
            _ => Err(Error::format(origin, "a training state is a msgpack map")),
        }
    }

    pub fn err(&self, key: &str, msg: impl std::fmt::Display) -> Error {
        Error::format(self.origin, format!("field {}{key}: {msg}", self.at))
    }

    fn get(&self, key: &str) -> Result<&'a Value> {
        self.entries
            .iter()
            .find(|(k, _)| k.as_str() == Some(key))
            .map(|(_, v)| v)
            .ok_or_else(|| self.err(key, "missing"))
    }

    pub fn str(&self, key: &str) -> Result<&'a str> {
        self.get(key)?
            .as_str()
            .ok_or_else(|| self.err(key, "expected a string"))
    }

    pub fn u64(&self, key: &str) -> Result<u64> {
        self.get(key)?
            .as_u64()
            .ok_or_else(|| self.err(key, "expected a whole number"))
    }

    pub fn u32(&self, key: &str) -> Result<u32> {
        u32::try_from(self.u64(key)?).map_err(|_| self.err(key, "larger than 2^32 − 1"))
    }

    pub fn f64(&self, key: &str) -> Result<f64> {
        match self.get(key)? {
            Value::F32(x) => Ok(*x as f64),
            Value::F64(x) => Ok(*x),
            Value::Integer(i) => i.as_f64().ok_or_else(|| self.err(key, "expected a number")),
            _ => Err(self.err(key, "expected a number")),
        }
    }

    /// Binary data of any length (a nested document).
    pub fn binary(&self, key: &str) -> Result<&'a [u8]> {
        match self.get(key)? {
            Value::Binary(b) => Ok(b),
            _ => Err(self.err(key, "expected binary data")),
        }
    }

    /// Whether the field is present and not nil.
    pub fn has(&self, key: &str) -> bool {
        self.get(key).is_ok_and(|v| !v.is_nil())
    }

    pub fn f32(&self, key: &str) -> Result<f32> {
        match self.get(key)? {
            Value::F32(x) => Ok(*x),
            Value::F64(x) => Ok(*x as f32),
            _ => Err(self.err(key, "expected a number")),
        }
    }

    fn bin(&self, key: &str, len: usize, width: usize) -> Result<&'a [u8]> {
        match self.get(key)? {
            Value::Binary(b) if b.len() == len * width => Ok(b),
            Value::Binary(b) => Err(self.err(
                key,
                format!(
                    "{} bytes where this training has {len} values of {width} bytes",
                    b.len()
                ),
            )),
            _ => Err(self.err(key, "expected binary data")),
        }
    }

    /// `len` f32 values into `out` (whose length is `len`).
    pub fn f32s_into(&self, key: &str, out: &mut [f32]) -> Result<()> {
        let b = self.bin(key, out.len(), 4)?;
        for (o, c) in out.iter_mut().zip(b.chunks_exact(4)) {
            *o = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
        Ok(())
    }

    pub fn u32s_into(&self, key: &str, out: &mut [u32]) -> Result<()> {
        let b = self.bin(key, out.len(), 4)?;
        for (o, c) in out.iter_mut().zip(b.chunks_exact(4)) {
            *o = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
        Ok(())
    }

    pub fn bytes_into(&self, key: &str, out: &mut [u8]) -> Result<()> {
        out.copy_from_slice(self.bin(key, out.len(), 1)?);
        Ok(())
    }

    pub fn map(&self, key: &str) -> Result<Fields<'a>> {
        match self.get(key)? {
            Value::Map(m) => Ok(Fields {
                origin: self.origin,
                at: format!("{}{key}.", self.at),
                entries: m,
            }),
            _ => Err(self.err(key, "expected a map")),
        }
    }

    /// The maps of an array that must hold exactly `n`.
    pub fn maps(&self, key: &str, n: usize) -> Result<Vec<Fields<'a>>> {
        let a = match self.get(key)? {
            Value::Array(a) if a.len() == n => a,
            Value::Array(a) => {
                return Err(self.err(
                    key,
                    format!("{} entries where this training has {n}", a.len()),
                ));
            }
            _ => return Err(self.err(key, "expected an array")),
        };
        a.iter()
            .enumerate()
            .map(|(i, v)| match v {
                Value::Map(m) => Ok(Fields {
                    origin: self.origin,
                    at: format!("{}{key}[{i}].", self.at),
                    entries: m,
                }),
                _ => Err(self.err(&format!("{key}[{i}]"), "expected a map")),
            })
            .collect()
    }
}

/// Parses a state document.
pub fn open(origin: &Path, bytes: &[u8]) -> Result<Value> {
    msgpack::decode(bytes).map_err(|e| Error::format(origin, e))
}

/// Checks a state's format, version and fingerprint; a difference is named, not shown
/// (a hidden scene's description stays out of messages).
pub fn check_header(f: &Fields, fingerprint: &[(String, String)]) -> Result<()> {
    if f.str("format")? != FORMAT {
        return Err(f.err("format", format!("not a training state ({FORMAT})")));
    }
    let v = f.u64("version")?;
    if v != VERSION {
        return Err(f.err(
            "version",
            format!("{v}: this program reads version {VERSION}"),
        ));
    }
    let saved = f.map("fingerprint")?;
    // A state holds what its own kind of trainer keeps between steps: the CPU's and the
    // GPU's are not interchangeable, and saying so beats naming the options that differ.
    let device_of = |d: Option<&str>| match d {
        None | Some("cpu") => "the CPU",
        Some("gpu") => "the GPU",
        Some(_) => "an unknown device",
    };
    let want = device_of(
        fingerprint
            .iter()
            .find(|(k, _)| k == DEVICE)
            .map(|(_, v)| v.as_str()),
    );
    let got = device_of(saved.str(DEVICE).ok());
    if got != want {
        return Err(f.err(
            "fingerprint",
            format!(
                "saved by training on {got}; this run trains on {want} (a state goes on only \
                 on the kind of device that saved it)"
            ),
        ));
    }
    let differ: Vec<&str> = fingerprint
        .iter()
        .filter(|(k, v)| saved.str(k).map_or(true, |s| s != v))
        .map(|(k, _)| k.as_str())
        .collect();
    if !differ.is_empty() {
        return Err(f.err(
            "fingerprint",
            format!(
                "saved by a different training: its {} differ from this run's (the same data, keys, model, options and thread count are needed to go on)",
                differ.join(", ")
            ),
        ));
    }
    Ok(())
}
