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
/// 2: a training policy's state, the mechanisms' (held-back gradients, table bounds) and
/// the gradients a step left waiting in the workers' buffers.
pub const VERSION: u64 = 2;
/// The fingerprint entry naming the kind of trainer that saved a state; a state without it
/// is the CPU trainer's.
pub const DEVICE: &str = "device";

pub fn f32s(v: &[f32]) -> Value {
    u32s(bytemuck::cast_slice(v))
}

pub fn u32s(v: &[u32]) -> Value {
    // Sized once and filled in place: a collected flat_map grows its buffer step by step.
    let mut out = vec![0u8; v.len() * 4];
    for (o, x) in out.chunks_exact_mut(4).zip(v) {
        o.copy_from_slice(&x.to_le_bytes());
    }
    Value::Binary(out)
}

/// Bit sets (64 members a word), little-endian.
pub fn u64s(v: &[u64]) -> Value {
    Value::Binary(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

/// Removes `key` from a map and returns its value (a document split to be nested
/// elsewhere: a checkpoint's optimizer, an experiment's run state).
pub fn take(doc: &mut Value, key: &str) -> Option<Value> {
    let Value::Map(m) = doc else {
        return None;
    };
    let i = m.iter().position(|(k, _)| k.as_str() == Some(key))?;
    Some(m.remove(i).1)
}

/// Sets `key` of a map (added at the end when absent).
pub fn put(doc: &mut Value, key: &str, value: Value) {
    if let Value::Map(m) = doc {
        match m.iter_mut().find(|(k, _)| k.as_str() == Some(key)) {
            Some((_, v)) => *v = value,
            None => m.push((Value::from(key), value)),
        }
    }
}

/// One scene's part of a trainer's state: its occupancy grid and the batch counters
/// (rays per batch, trained and marched samples of its last step).
pub fn scene_value(
    grid: &crate::occupancy::OccupancyGrid,
    counters: (u32, u32, u32),
    stride: u32,
) -> Value {
    map(vec![
        ("density", f32s(&grid.density)),
        ("bitfield", Value::Binary(grid.bitfield().to_vec())),
        ("mean", Value::F32(grid.mean)),
        ("grid_updates", Value::from(grid.ema_step)),
        ("rays_per_batch", Value::from(counters.0)),
        ("measured_samples", Value::from(counters.1)),
        ("measured_marched", Value::from(counters.2)),
        ("march_stride", Value::from(stride)),
    ])
}

/// Takes back a [`scene_value`] for a grid of `cells` cells.
pub fn scene_from(
    f: &Fields,
    cells: usize,
) -> Result<(crate::occupancy::OccupancyGrid, (u32, u32, u32), u32)> {
    let mut density = crate::pages::zeroed::<f32>(cells);
    f.f32s_into("density", &mut density)?;
    let mut bitfield = vec![0u8; cells / 8];
    f.bytes_into("bitfield", &mut bitfield)?;
    let grid = crate::occupancy::OccupancyGrid::from_parts(
        density,
        bitfield,
        f.f32("mean")?,
        f.u32("grid_updates")?,
    )
    .ok_or_else(|| f.err("density", "does not make an occupancy grid"))?;
    let counters = (
        f.u32("rays_per_batch")?,
        f.u32("measured_samples")?,
        f.u32("measured_marched")?,
    );
    // Absent from states saved before the coarse march: they marched the reference's step.
    let stride = if f.has("march_stride") {
        f.u32("march_stride")?
    } else {
        1
    };
    if !stride.is_power_of_two() || stride > 1 << crate::train::coarse::MAX_STRIDE_LOG2 {
        return Err(f.err(
            "march_stride",
            format!(
                "{stride}: not a power of two up to {}",
                1 << crate::train::coarse::MAX_STRIDE_LOG2
            ),
        ));
    }
    Ok((grid, counters, stride))
}

/// Held-back gradients ([`sparse`], one per parameter; field `key` of `f`) for `n`
/// parameters of which the first `n_matrix` are MLP weights, which are never held back.
pub fn held_from(f: &Fields, key: &str, n: usize, n_matrix: usize) -> Result<Option<Vec<f32>>> {
    if !f.has(key) {
        return Ok(None);
    }
    let mut pending = vec![0.0f32; n];
    f.sparse_into(key, &mut pending)?;
    if pending[..n_matrix].iter().any(|&g| g != 0.0) {
        return Err(f.err(key, "holds back an MLP gradient (never held)"));
    }
    Ok(Some(pending))
}

/// The values of `v` whose bits are not zero (−0.0 included), as `{index, value}`: what a
/// mostly-empty gradient or bound array costs.
pub fn sparse(v: &[f32]) -> Value {
    let (mut index, mut value) = (Vec::new(), Vec::new());
    for (i, x) in v.iter().enumerate() {
        if x.to_bits() != 0 {
            index.push(i as u32);
            value.push(*x);
        }
    }
    map(vec![("index", u32s(&index)), ("value", f32s(&value))])
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
    let mut out = Vec::with_capacity(msgpack::binary_bytes(v) + (1 << 16));
    msgpack::encode(v, &mut out);
    out
}

/// An optimizer's state laid out as tiny-cuda-nn serialises its NeRF optimizer into a
/// snapshot saved with optimizer state (`Ema::serialize` ∘ `ExponentialDecay::serialize` ∘
/// `Adam::serialize`, keys sorted as nlohmann writes them): instant-ngp loads a checkpoint
/// with it and trains on. `published` are the debiased EMA weights (written fp16, as the
/// reference keeps them); `ours` is what an exact resume needs besides (a backend's own EMA
/// accumulators), under `stegongp`, which tiny-cuda-nn ignores.
pub struct NgpOptimizer<'a> {
    pub config: &'a super::optimizer::OptimizerConfig,
    pub step: u32,
    pub m: &'a [f32],
    pub v: &'a [f32],
    pub param_steps: &'a [u32],
    pub published: &'a [f32],
    pub ours: Value,
}

impl NgpOptimizer<'_> {
    pub fn value(self) -> Value {
        let c = self.config;
        let lr = c.learning_rate(self.step);
        let ema16 = crate::snapshot::write::fp16_bytes(self.published);
        let adam = map(vec![
            ("base_learning_rate", Value::F32(lr)),
            ("current_step", Value::from(self.step)),
            ("first_moments_binary", f32s(self.m)),
            ("param_steps_binary", u32s(self.param_steps)),
            ("second_moments_binary", f32s(self.v)),
        ]);
        let decay = map(vec![
            ("learning_rate", Value::F32(c.lr)),
            ("learning_rate_factor", Value::F32(lr / c.lr)),
            ("nested", adam),
        ]);
        map(vec![
            ("nested", decay),
            ("stegongp", self.ours),
            ("weights_ema_binary", Value::Binary(ema16)),
        ])
    }

    /// Takes back Adam's part of a [`Self::value`] (`o`) into `m`, `v` and `param_steps`,
    /// checked: a step count bounded before any table is grown to it, no parameter counting
    /// more updates than the optimizer. Returns the step count and `stegongp`.
    pub fn read_into<'a>(
        o: &Fields<'a>,
        m: &mut [f32],
        v: &mut [f32],
        param_steps: &mut [u32],
    ) -> Result<(u32, Fields<'a>)> {
        let adam = o.map("nested")?.map("nested")?;
        adam.f32s_into("first_moments_binary", m)?;
        adam.f32s_into("second_moments_binary", v)?;
        adam.u32s_into("param_steps_binary", param_steps)?;
        let step = adam.u32("current_step")?;
        // The bias-correction tables hold a value a step: a forged count must not make
        // them gigabytes (the fuzzer's first run of training states found 2^30).
        if step > super::optimizer::MAX_STEPS {
            return Err(adam.err(
                "current_step",
                format!(
                    "{step}: more steps than a training runs (at most {})",
                    super::optimizer::MAX_STEPS
                ),
            ));
        }
        if let Some(bad) = param_steps.iter().find(|&&s| s > step) {
            return Err(adam.err(
                "param_steps_binary",
                format!("a step count {bad} beyond the optimizer's {step}"),
            ));
        }
        Ok((step, o.map("stegongp")?))
    }
}

/// A policy's table bounds ([`super::hooks::TableBounds`]) as `{entries, bounds}`, the
/// bounded entries alone; nil before a policy set any.
pub fn bounds_value(b: Option<&super::hooks::TableBounds>) -> Value {
    let Some(b) = b else {
        return Value::Nil;
    };
    let bounded: Vec<u32> = (0..b.bounds().len() as u32)
        .filter(|&e| b.is_bounded(e as usize))
        .collect();
    let values: Vec<f32> = bounded.iter().map(|&e| b.bound(e as usize)).collect();
    map(vec![("entries", u32s(&bounded)), ("bounds", f32s(&values))])
}

/// Takes back a [`bounds_value`] (field `key` of `f`) for a table of `n_entries` entries of
/// `n_features`: entries in order and within the table, bounds finite and ≥ 0.
pub fn bounds_from(
    f: &Fields,
    key: &str,
    n_entries: usize,
    n_features: usize,
) -> Result<Option<super::hooks::TableBounds>> {
    if !f.has(key) {
        return Ok(None);
    }
    let bf = f.map(key)?;
    let entries = bf.u32s("entries", n_entries)?;
    let mut values = vec![0.0f32; entries.len()];
    bf.f32s_into("bounds", &mut values)?;
    let mut bound = vec![super::hooks::UNBOUNDED; n_entries];
    let mut next = 0;
    for (&e, &b) in entries.iter().zip(&values) {
        if (e as usize) < next || e as usize >= n_entries || !(b >= 0.0 && b.is_finite()) {
            return Err(bf.err(
                "entries",
                format!("entry {e} out of order, past {n_entries}, or with bound {b}"),
            ));
        }
        bound[e as usize] = b;
        next = e as usize + 1;
    }
    Ok(Some(super::hooks::TableBounds::from_bounds(
        bound, n_features,
    )))
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

    /// A nested document as it is.
    pub fn value(&self, key: &str) -> Result<&'a Value> {
        self.get(key)
    }

    /// Binary data of any length (a nested document).
    pub fn binary(&self, key: &str) -> Result<&'a [u8]> {
        match self.get(key)? {
            Value::Binary(b) => Ok(b),
            _ => Err(self.err(key, "expected binary data")),
        }
    }

    /// Binary data of any length, or `None` where the field is absent or nil.
    pub fn binary_opt(&self, key: &str) -> Result<Option<&'a [u8]>> {
        if self.has(key) {
            self.binary(key).map(Some)
        } else {
            Ok(None)
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

    /// A [`sparse`] array into `out` (zeroed first): indices strictly increasing and within
    /// `out`, one value each.
    pub fn sparse_into(&self, key: &str, out: &mut [f32]) -> Result<()> {
        let f = self.map(key)?;
        let (index, value) = (f.binary("index")?, f.binary("value")?);
        if index.len() % 4 != 0 || index.len() != value.len() || index.len() / 4 > out.len() {
            return Err(self.err(
                key,
                format!(
                    "{} index and {} value bytes for at most {} values",
                    index.len(),
                    value.len(),
                    out.len()
                ),
            ));
        }
        out.fill(0.0);
        let mut next = 0usize;
        for (i, v) in index.chunks_exact(4).zip(value.chunks_exact(4)) {
            let i = u32::from_le_bytes([i[0], i[1], i[2], i[3]]) as usize;
            if i < next || i >= out.len() {
                return Err(self.err(
                    key,
                    format!("index {i} out of order or past {} values", out.len()),
                ));
            }
            out[i] = f32::from_le_bytes([v[0], v[1], v[2], v[3]]);
            next = i + 1;
        }
        Ok(())
    }

    /// u32 values of any count up to `max`.
    pub fn u32s(&self, key: &str, max: usize) -> Result<Vec<u32>> {
        let b = self.binary(key)?;
        if b.len() % 4 != 0 || b.len() / 4 > max {
            return Err(self.err(
                key,
                format!(
                    "{} bytes where at most {max} values of 4 bytes fit",
                    b.len()
                ),
            ));
        }
        Ok(b.chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    /// `out.len()` words of a [`u64s`] into `out`.
    pub fn u64s_into(&self, key: &str, out: &mut [u64]) -> Result<()> {
        let b = self.bin(key, out.len(), 8)?;
        for (o, c) in out.iter_mut().zip(b.chunks_exact(8)) {
            *o = u64::from_le_bytes(c.try_into().expect("8 bytes"));
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

/// The parts of a training a saved state must share with the trainer it goes back into, by
/// name: the device kind (`None`: the CPU, whose states predate the entry), the layout and
/// options, whether a policy is installed, and each scene's image count, size and box.
/// Never the index functions: a state's errors may be printed, and a key must not be (the
/// program re-derives them from the same key files).
pub fn fingerprint<'a>(
    device: Option<&str>,
    layout: &crate::network::ModelConfig,
    options: &super::TrainConfig,
    policy: bool,
    scenes: impl ExactSizeIterator<Item = &'a crate::data::Dataset>,
) -> Vec<(String, String)> {
    let mut out: Vec<(String, String)> = device
        .map(|d| (DEVICE.to_string(), d.to_string()))
        .into_iter()
        .collect();
    out.extend([
        ("layout".to_string(), format!("{layout:?}")),
        ("options".to_string(), format!("{options:?}")),
        ("scenes".to_string(), scenes.len().to_string()),
        (
            "policy".to_string(),
            if policy { "installed" } else { "none" }.to_string(),
        ),
    ]);
    for (i, d) in scenes.enumerate() {
        let size = d
            .frames
            .first()
            .map_or((0, 0), |f| (f.camera.width, f.camera.height));
        out.push((
            format!("scene {i}"),
            format!(
                "{} images of {}x{}, aabb {}",
                d.frames.len(),
                size.0,
                size.1,
                d.aabb_scale
            ),
        ));
    }
    out
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
