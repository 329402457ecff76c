//! Mutations that know the formats: a JSON or msgpack document is parsed and changed as a
//! tree (a number becomes an extreme, an array grows, a key goes), a PNG is changed chunk
//! by chunk with its CRC fixed so the decoder reads on, a text file line by line and token
//! by token; everything also gets byte-level mutations, which is how declared lengths come
//! to lie. Gzip-framed files are mutated inside the frame and framed again.

use ngp::rng::Pcg32;
use serde_json::Value as Json;
use std::io::{Read, Write};

/// The seeded source of every choice a mutation makes.
pub struct Rng(Pcg32);

impl Rng {
    pub fn new(seed: u64, stream: u64) -> Self {
        Rng(Pcg32::new(seed, stream))
    }

    pub fn below(&mut self, n: usize) -> usize {
        if n <= 1 {
            return 0;
        }
        (((self.0.next_u32() as u64) << 32 | self.0.next_u32() as u64) % n as u64) as usize
    }

    pub fn chance(&mut self, p: f32) -> bool {
        self.0.next_f32() < p
    }

    pub fn u64(&mut self) -> u64 {
        (self.0.next_u32() as u64) << 32 | self.0.next_u32() as u64
    }

    fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.below(xs.len())]
    }
}

/// Integers that break arithmetic: zero, one, signs, powers of two and their neighbours,
/// and the ends of every width.
const INTERESTING: &[u64] = &[
    0,
    1,
    2,
    3,
    7,
    8,
    16,
    255,
    256,
    1024,
    4096,
    65535,
    65536,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    0x1_0000_0000,
    1 << 40,
    1 << 62,
    0x7fff_ffff_ffff_ffff,
    0x8000_0000_0000_0000,
    u64::MAX,
    u64::MAX - 1,
];

const INTERESTING_F64: &[f64] = &[
    0.0,
    -0.0,
    -1.0,
    0.5,
    1e-310,
    1e-30,
    1e30,
    1e308,
    -1e308,
    3.4e38,
    4294967296.0,
    9.3e18,
    1.8e19,
];

/// The most one mutation adds to a document: growth by repetition, not by the mutator's
/// own runaway (a string repeated across generations reached 4.7 GB).
const GROWTH: usize = 1 << 20;

const TOKENS: &[&str] = &[
    "0",
    "-1",
    "1e40",
    "-1e40",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "99999999999999999999999",
    "4294967296",
    "18446744073709551615",
    "2147483648",
    "0x10",
    "",
    "1e-45",
    "../../../../etc/passwd",
    "/dev/zero",
];

/// Mutates the file `name` (its extension picks the mutator) in place.
pub fn mutate_file(name: &str, data: &mut Vec<u8>, pool: &[Vec<u8>], rng: &mut Rng) {
    if data.starts_with(&[0x1f, 0x8b])
        && rng.chance(0.85)
        && let Some(mut inner) = gunzip(data)
    {
        mutate_inner(name, &mut inner, pool, rng);
        *data = gzip(&inner);
        return;
    }
    mutate_inner(name, data, pool, rng);
}

fn mutate_inner(name: &str, data: &mut Vec<u8>, pool: &[Vec<u8>], rng: &mut Rng) {
    let ext = name.rsplit('.').next().unwrap_or("").to_ascii_lowercase();
    let structured = rng.chance(0.7);
    let done = structured
        && match ext.as_str() {
            "json" => mutate_json(data, rng),
            "msgpack" | "ingp" | "state" => mutate_msgpack(data, rng),
            "png" => mutate_png(data, rng),
            "txt" | "http" => mutate_text(data, rng),
            "npy" => mutate_text_prefix(data, 128, rng),
            _ => false,
        };
    if !done {
        for _ in 0..1 + rng.below(4) {
            mutate_bytes(data, pool, rng);
        }
    }
}

pub fn gunzip(data: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    flate2::read::GzDecoder::new(data)
        .take(64 << 20)
        .read_to_end(&mut out)
        .ok()?;
    Some(out)
}

pub fn gzip(data: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(data).expect("writing to memory");
    e.finish().expect("writing to memory")
}

/// One byte-level mutation; lengths and counts in headers lie after these.
pub fn mutate_bytes(data: &mut Vec<u8>, pool: &[Vec<u8>], rng: &mut Rng) {
    let n = data.len();
    match rng.below(9) {
        0 if n > 0 => {
            let i = rng.below(n);
            data[i] ^= 1 << rng.below(8);
        }
        1 if n > 0 => {
            let i = rng.below(n);
            data[i] = *rng.pick(&[0u8, 0xff, 0x7f, 0x80, 1, 0x20]);
        }
        // An integer field overwritten at a random spot, either endianness, 2 to 8 bytes.
        2 if n > 0 => {
            let w = *rng.pick(&[2usize, 4, 8]);
            let i = rng.below(n);
            let v = *rng.pick(INTERESTING);
            let bytes = if rng.chance(0.7) {
                v.to_le_bytes()
            } else {
                v.to_be_bytes()
            };
            let src = if rng.chance(0.7) { 0 } else { 8 - w };
            let k = w.min(n - i);
            data[i..i + k].copy_from_slice(&bytes[src..src + k]);
        }
        3 => {
            let i = rng.below(n + 1);
            let len = 1 + rng.below(16);
            let fill: Vec<u8> = (0..len).map(|_| rng.below(256) as u8).collect();
            data.splice(i..i, fill);
        }
        4 if n > 0 => {
            let i = rng.below(n);
            let len = 1 + rng.below((n - i).min(64));
            data.drain(i..i + len);
        }
        5 if n > 0 => {
            data.truncate(rng.below(n));
        }
        6 if n > 0 => {
            let i = rng.below(n);
            let len = 1 + rng.below((n - i).min(256));
            let chunk = data[i..i + len].to_vec();
            let at = rng.below(n + 1);
            let times = 1 + rng.below(4);
            for _ in 0..times {
                data.splice(at..at, chunk.iter().copied());
            }
        }
        // A piece of another seed of the same kind spliced in.
        7 if !pool.is_empty() => {
            let other = rng.pick(pool);
            if !other.is_empty() {
                let i = rng.below(other.len());
                let len = 1 + rng.below((other.len() - i).min(512));
                let at = rng.below(n + 1);
                let end = (at + len).min(n);
                data.splice(at..end, other[i..i + len].iter().copied());
            }
        }
        _ => {
            let i = rng.below(n + 1);
            let len = 1 + rng.below(8);
            data.splice(i..i, std::iter::repeat_n(0xffu8, len));
        }
    }
}

// ---- JSON ----

fn mutate_json(data: &mut Vec<u8>, rng: &mut Rng) -> bool {
    let Ok(mut v) = serde_json::from_slice::<Json>(data) else {
        return false;
    };
    for _ in 0..1 + rng.below(3) {
        let count = count_json(&v);
        let target = rng.below(count);
        let mut k = 0;
        mutate_json_node(&mut v, target, &mut k, rng);
    }
    *data = serde_json::to_vec(&v).expect("a JSON value serialises");
    true
}

fn count_json(v: &Json) -> usize {
    1 + match v {
        Json::Array(a) => a.iter().map(count_json).sum(),
        Json::Object(o) => o.values().map(count_json).sum(),
        _ => 0,
    }
}

/// Walks in pre-order to node number `target` and mutates it.
fn mutate_json_node(v: &mut Json, target: usize, k: &mut usize, rng: &mut Rng) -> bool {
    if *k == target {
        *v = mutated_json(v, rng);
        return true;
    }
    *k += 1;
    match v {
        Json::Array(a) => {
            for x in a.iter_mut() {
                if mutate_json_node(x, target, k, rng) {
                    return true;
                }
            }
        }
        Json::Object(o) => {
            for x in o.values_mut() {
                if mutate_json_node(x, target, k, rng) {
                    return true;
                }
            }
        }
        _ => {}
    }
    false
}

fn mutated_json(v: &Json, rng: &mut Rng) -> Json {
    let other = || -> Json { Json::Null };
    match v {
        Json::Number(_) if rng.chance(0.75) => {
            if rng.chance(0.5) {
                let x = *rng.pick(INTERESTING);
                if rng.chance(0.3) {
                    serde_json::json!((x as i64).wrapping_neg())
                } else {
                    serde_json::json!(x)
                }
            } else {
                let x = *rng.pick(INTERESTING_F64);
                serde_json::Number::from_f64(x).map_or(Json::Null, Json::Number)
            }
        }
        Json::String(s) if rng.chance(0.75) => match rng.below(4) {
            0 => Json::String(rng.pick(TOKENS).to_string()),
            1 => Json::String(s.repeat((1 + rng.below(64)).min(GROWTH / s.len().max(1)).max(1))),
            2 => Json::String(s.chars().take(rng.below(s.len() + 1)).collect()),
            _ => Json::String(format!("{s}\u{0}\u{ffff}")),
        },
        Json::Array(a) if rng.chance(0.8) => {
            let mut a = a.clone();
            match rng.below(4) {
                0 if !a.is_empty() => {
                    let i = rng.below(a.len());
                    a.remove(i);
                }
                1 if !a.is_empty() => {
                    let i = rng.below(a.len());
                    let x = a[i].clone();
                    let size = serde_json::to_vec(&x).map_or(GROWTH, |v| v.len().max(1));
                    for _ in 0..(1 + rng.below(200)).min(GROWTH / size) {
                        a.push(x.clone());
                    }
                }
                2 => a.clear(),
                _ => a.push(Json::Null),
            }
            Json::Array(a)
        }
        Json::Object(o) if rng.chance(0.8) => {
            let mut o = o.clone();
            let keys: Vec<String> = o.keys().cloned().collect();
            match rng.below(3) {
                0 if !keys.is_empty() => {
                    o.remove(rng.pick(&keys));
                }
                1 if !keys.is_empty() => {
                    let key = rng.pick(&keys).clone();
                    let x = o.remove(&key).expect("a key just listed");
                    o.insert(format!("{key}_"), x);
                }
                _ => {
                    let key = keys.get(rng.below(keys.len().max(1))).cloned();
                    if let Some(key) = key {
                        let x = o[&key].clone();
                        o.insert(key, Json::Array(vec![x]));
                    }
                }
            }
            Json::Object(o)
        }
        _ => match rng.below(6) {
            0 => other(),
            1 => Json::Bool(rng.chance(0.5)),
            2 => serde_json::json!(*rng.pick(INTERESTING)),
            3 => Json::String(rng.pick(TOKENS).to_string()),
            4 => Json::Array(vec![v.clone(); 1 + rng.below(3)]),
            _ => serde_json::json!({ "x": v.clone() }),
        },
    }
}

// ---- msgpack ----

fn mutate_msgpack(data: &mut Vec<u8>, rng: &mut Rng) -> bool {
    let Ok(mut v) = rmpv::decode::read_value(&mut data.as_slice()) else {
        return false;
    };
    for _ in 0..1 + rng.below(3) {
        let count = count_mp(&v);
        let target = rng.below(count);
        let mut k = 0;
        mutate_mp_node(&mut v, target, &mut k, rng);
    }
    let mut out = Vec::new();
    rmpv::encode::write_value(&mut out, &v).expect("writing to memory");
    *data = out;
    true
}

fn count_mp(v: &rmpv::Value) -> usize {
    use rmpv::Value as V;
    1 + match v {
        V::Array(a) => a.iter().map(count_mp).sum(),
        V::Map(m) => m.iter().map(|(_, x)| count_mp(x)).sum(),
        _ => 0,
    }
}

fn mutate_mp_node(v: &mut rmpv::Value, target: usize, k: &mut usize, rng: &mut Rng) -> bool {
    use rmpv::Value as V;
    if *k == target {
        *v = mutated_mp(v, rng);
        return true;
    }
    *k += 1;
    match v {
        V::Array(a) => {
            for x in a.iter_mut() {
                if mutate_mp_node(x, target, k, rng) {
                    return true;
                }
            }
        }
        V::Map(m) => {
            for (_, x) in m.iter_mut() {
                if mutate_mp_node(x, target, k, rng) {
                    return true;
                }
            }
        }
        _ => {}
    }
    false
}

fn mutated_mp(v: &rmpv::Value, rng: &mut Rng) -> rmpv::Value {
    use rmpv::Value as V;
    match v {
        V::Integer(_) if rng.chance(0.8) => {
            let x = *rng.pick(INTERESTING);
            if rng.chance(0.3) {
                V::from(-((x >> 1) as i64))
            } else {
                V::from(x)
            }
        }
        V::F32(_) | V::F64(_) if rng.chance(0.8) => {
            let x = *rng.pick(INTERESTING_F64);
            if rng.chance(0.3) {
                V::F64(f64::NAN)
            } else if rng.chance(0.5) {
                V::F32(x as f32)
            } else {
                V::F64(x)
            }
        }
        V::Binary(b) if rng.chance(0.8) => {
            let mut b = b.clone();
            match rng.below(4) {
                0 => b.truncate(rng.below(b.len() + 1)),
                1 => {
                    let extra = 1 + rng.below(64);
                    b.extend(std::iter::repeat_n(0u8, extra));
                }
                2 if !b.is_empty() => {
                    for _ in 0..1 + rng.below(8) {
                        let i = rng.below(b.len());
                        b[i] = 0xff; // f16 NaN/inf bytes and huge floats
                    }
                }
                _ => b.clear(),
            }
            V::Binary(b)
        }
        V::String(s) if rng.chance(0.7) => {
            let s = s.as_str().unwrap_or("");
            V::from(if rng.chance(0.5) || s.len() > GROWTH {
                rng.pick(TOKENS).to_string()
            } else {
                format!("{s}{s}")
            })
        }
        V::Array(a) if rng.chance(0.8) => {
            let mut a = a.clone();
            match rng.below(3) {
                0 if !a.is_empty() => {
                    let i = rng.below(a.len());
                    a.remove(i);
                }
                1 if !a.is_empty() && a.len() < 100_000 => {
                    let x = a[rng.below(a.len())].clone();
                    let mut size = Vec::new();
                    let _ = rmpv::encode::write_value(&mut size, &x);
                    for _ in 0..(1 + rng.below(100)).min(GROWTH / size.len().max(1)) {
                        a.push(x.clone());
                    }
                }
                _ => a.clear(),
            }
            V::Array(a)
        }
        V::Map(m) if rng.chance(0.8) => {
            let mut m = m.clone();
            if !m.is_empty() {
                let i = rng.below(m.len());
                if rng.chance(0.5) {
                    m.remove(i);
                } else {
                    m[i].1 = V::Nil;
                }
            }
            V::Map(m)
        }
        _ => match rng.below(5) {
            0 => V::Nil,
            1 => V::from(*rng.pick(INTERESTING)),
            2 => V::from("x"),
            3 => V::Array(vec![v.clone()]),
            _ => V::Binary(vec![0; rng.below(32)]),
        },
    }
}

// ---- PNG ----

/// Changes one chunk's content (IHDR's sizes and formats above all) and fixes its CRC,
/// or drops, duplicates or reorders a chunk.
fn mutate_png(data: &mut Vec<u8>, rng: &mut Rng) -> bool {
    const SIG: usize = 8;
    if data.len() < SIG || &data[1..4] != b"PNG" {
        return false;
    }
    let mut chunks: Vec<(Vec<u8>, Vec<u8>)> = Vec::new(); // (type, data)
    let mut i = SIG;
    while i + 12 <= data.len() {
        let len = u32::from_be_bytes(data[i..i + 4].try_into().expect("4 bytes")) as usize;
        if i + 12 + len > data.len() {
            return false;
        }
        chunks.push((
            data[i + 4..i + 8].to_vec(),
            data[i + 8..i + 8 + len].to_vec(),
        ));
        i += 12 + len;
    }
    if chunks.is_empty() {
        return false;
    }
    let c = if rng.chance(0.5) {
        0
    } else {
        rng.below(chunks.len())
    };
    match rng.below(5) {
        0 | 1 => {
            let is_ihdr = chunks[c].0 == b"IHDR";
            let body = &mut chunks[c].1;
            if is_ihdr && body.len() >= 13 && rng.chance(0.7) {
                let field = rng.below(4);
                match field {
                    0 | 1 => {
                        let v = *rng.pick(&[0u32, 1, 65535, 0x7fff_ffff, 0xffff_ffff, 100_000]);
                        body[field * 4..field * 4 + 4].copy_from_slice(&v.to_be_bytes());
                    }
                    2 => body[8] = *rng.pick(&[1u8, 2, 4, 8, 16, 3, 0]),
                    _ => body[9] = *rng.pick(&[0u8, 2, 3, 4, 6, 7]),
                }
            } else {
                mutate_bytes(body, &[], rng);
            }
        }
        2 => {
            chunks.remove(c);
        }
        3 => {
            let x = chunks[c].clone();
            chunks.insert(c, x);
        }
        _ => {
            let j = rng.below(chunks.len());
            chunks.swap(c, j);
        }
    }
    let mut out = data[..SIG].to_vec();
    for (ty, body) in &chunks {
        png_chunk(ty, body, &mut out);
    }
    *data = out;
    true
}

/// Appends a PNG chunk: length, type, data and the CRC of type and data.
pub fn png_chunk(ty: &[u8], body: &[u8], out: &mut Vec<u8>) {
    out.extend((body.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend(ty);
    out.extend(body);
    let crc = crc32(&out[start..]);
    out.extend(crc.to_be_bytes());
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

// ---- text ----

/// Line and token mutations (COLMAP's text model, HTTP requests).
fn mutate_text(data: &mut Vec<u8>, rng: &mut Rng) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    let sep = if text.contains("\r\n") { "\r\n" } else { "\n" };
    let mut lines: Vec<String> = text.split(sep).map(str::to_string).collect();
    let i = rng.below(lines.len());
    match rng.below(5) {
        0 => {
            lines.remove(i);
        }
        1 => {
            let x = lines[i].clone();
            for _ in 0..1 + rng.below(50) {
                lines.insert(i, x.clone());
            }
        }
        _ => {
            let mut toks: Vec<String> = lines[i].split(' ').map(str::to_string).collect();
            let t = rng.below(toks.len());
            match rng.below(3) {
                0 => toks[t] = rng.pick(TOKENS).to_string(),
                1 => {
                    toks.remove(t);
                }
                _ => toks.insert(t, rng.pick(TOKENS).to_string()),
            }
            lines[i] = toks.join(" ");
        }
    }
    *data = lines.join(sep).into_bytes();
    true
}

/// Token mutations confined to a text header (npy's dictionary), the binary rest kept.
fn mutate_text_prefix(data: &mut Vec<u8>, header: usize, rng: &mut Rng) -> bool {
    let end = data.len().min(header);
    let Some(open) = data[..end].iter().position(|&b| b == b'{') else {
        return false;
    };
    let Some(close) = data[..end].iter().rposition(|&b| b == b'}') else {
        return false;
    };
    if close <= open {
        return false;
    }
    let Ok(dict) = std::str::from_utf8(&data[open..=close]) else {
        return false;
    };
    let mut dict = dict.to_string();
    let digits: Vec<(usize, usize)> = {
        let b = dict.as_bytes();
        let mut v = Vec::new();
        let mut s = None;
        for (k, &c) in b.iter().enumerate() {
            match (c.is_ascii_digit(), s) {
                (true, None) => s = Some(k),
                (false, Some(a)) => {
                    v.push((a, k));
                    s = None;
                }
                _ => {}
            }
        }
        v
    };
    if digits.is_empty() || rng.chance(0.3) {
        let swaps = [
            ("<f8", "<f4"),
            ("<f8", ">f8"),
            ("False", "True"),
            ("<f8", "|O"),
        ];
        let (a, b) = *rng.pick(&swaps);
        dict = dict.replacen(a, b, 1);
    } else {
        let (a, b) = *rng.pick(&digits);
        let v = rng.pick(&[
            "0",
            "1",
            "4294967296",
            "99999999999",
            "18446744073709551615",
        ]);
        dict.replace_range(a..b, v);
    }
    let mut out = data[..open].to_vec();
    out.extend(dict.as_bytes());
    out.extend(&data[close + 1..]);
    *data = out;
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_matches_the_png_standard() {
        // The CRC of an IEND chunk (type only) is fixed by the standard.
        assert_eq!(crc32(b"IEND"), 0xae42_6082);
    }

    #[test]
    fn json_mutation_keeps_json_and_changes_it() {
        let mut rng = Rng::new(1, 2);
        let seed = br#"{"a": [1, 2, {"b": "x"}], "c": 0.5}"#.to_vec();
        let mut changed = 0;
        for _ in 0..50 {
            let mut d = seed.clone();
            assert!(mutate_json(&mut d, &mut rng));
            serde_json::from_slice::<Json>(&d).expect("still JSON");
            changed += (d != seed) as usize;
        }
        assert!(changed > 40, "{changed} of 50 changed");
    }

    #[test]
    fn gzip_frames_are_mutated_inside() {
        let mut rng = Rng::new(3, 4);
        let inner = br#"{"k": 1}"#;
        let mut d = gzip(inner);
        let mut inside = 0;
        for _ in 0..20 {
            let mut x = d.clone();
            mutate_file("a.json", &mut x, &[], &mut rng);
            if let Some(u) = gunzip(&x) {
                inside += (u != inner) as usize;
            }
        }
        assert!(inside > 10, "{inside}");
        d.clear();
    }
}
