//! MessagePack encoding exactly as nlohmann/json 3.10.4 `to_msgpack` writes it (the library
//! instant-ngp saves snapshots with): object keys in byte order (its objects are `std::map`),
//! integers in their smallest form with non-negative signed values written as unsigned,
//! floats as float32 when the double round-trips through float32, else float64, binary as
//! `bin` without subtype. Decoding uses rmpv, which never preallocates from length fields.

use rmpv::Value;

/// The bytes of the binaries in `v`, however deep: what an output buffer is sized by, so
/// that one holding hundreds of megabytes is not copied as it grows.
pub fn binary_bytes(v: &Value) -> usize {
    match v {
        Value::Binary(b) => b.len(),
        Value::Array(a) => a.iter().map(binary_bytes).sum(),
        Value::Map(m) => m.iter().map(|(_, v)| binary_bytes(v)).sum(),
        _ => 0,
    }
}

/// Appends `v` to `out` with nlohmann's choices of widths. Map keys that are not strings
/// cannot come from nlohmann; they sort after the string keys, in their original order.
pub fn encode(v: &Value, out: &mut Vec<u8>) {
    match v {
        Value::Nil => out.push(0xc0),
        Value::Boolean(b) => out.push(if *b { 0xc3 } else { 0xc2 }),
        Value::Integer(i) => {
            if let Some(u) = i.as_u64() {
                encode_unsigned(u, out)
            } else if let Some(s) = i.as_i64() {
                encode_negative(s, out)
            }
        }
        Value::F32(f) => encode_float(*f as f64, out),
        Value::F64(f) => encode_float(*f, out),
        Value::String(s) => {
            let b = s.as_bytes();
            let n = b.len();
            if n <= 31 {
                out.push(0xa0 | n as u8);
            } else if n <= u8::MAX as usize {
                out.push(0xd9);
                out.push(n as u8);
            } else if n <= u16::MAX as usize {
                out.push(0xda);
                out.extend_from_slice(&(n as u16).to_be_bytes());
            } else {
                out.push(0xdb);
                out.extend_from_slice(&(n as u32).to_be_bytes());
            }
            out.extend_from_slice(b);
        }
        Value::Binary(b) => {
            encode_bin_header(b.len(), out);
            out.extend_from_slice(b);
        }
        Value::Array(a) => {
            let n = a.len();
            if n <= 15 {
                out.push(0x90 | n as u8);
            } else if n <= u16::MAX as usize {
                out.push(0xdc);
                out.extend_from_slice(&(n as u16).to_be_bytes());
            } else {
                out.push(0xdd);
                out.extend_from_slice(&(n as u32).to_be_bytes());
            }
            for e in a {
                encode(e, out);
            }
        }
        Value::Map(m) => {
            let n = m.len();
            if n <= 15 {
                out.push(0x80 | n as u8);
            } else if n <= u16::MAX as usize {
                out.push(0xde);
                out.extend_from_slice(&(n as u16).to_be_bytes());
            } else {
                out.push(0xdf);
                out.extend_from_slice(&(n as u32).to_be_bytes());
            }
            let mut entries: Vec<&(Value, Value)> = m.iter().collect();
            // Stable sort: equal keys keep their order, non-string keys go last.
            entries.sort_by(|a, b| key_bytes(&a.0).cmp(&key_bytes(&b.0)));
            for (k, val) in entries {
                encode(k, out);
                encode(val, out);
            }
        }
        Value::Ext(ty, data) => {
            // nlohmann writes binary values that carry a subtype as ext.
            let n = data.len();
            match n {
                1 => out.push(0xd4),
                2 => out.push(0xd5),
                4 => out.push(0xd6),
                8 => out.push(0xd7),
                16 => out.push(0xd8),
                _ if n <= u8::MAX as usize => {
                    out.push(0xc7);
                    out.push(n as u8);
                }
                _ if n <= u16::MAX as usize => {
                    out.push(0xc8);
                    out.extend_from_slice(&(n as u16).to_be_bytes());
                }
                _ => {
                    out.push(0xc9);
                    out.extend_from_slice(&(n as u32).to_be_bytes());
                }
            }
            out.push(*ty as u8);
            out.extend_from_slice(data);
        }
    }
}

/// Header of a `bin` value of `n` bytes; the caller appends the payload.
pub fn encode_bin_header(n: usize, out: &mut Vec<u8>) {
    if n <= u8::MAX as usize {
        out.push(0xc4);
        out.push(n as u8);
    } else if n <= u16::MAX as usize {
        out.push(0xc5);
        out.extend_from_slice(&(n as u16).to_be_bytes());
    } else {
        out.push(0xc6);
        out.extend_from_slice(&(n as u32).to_be_bytes());
    }
}

fn key_bytes(k: &Value) -> (u8, &[u8]) {
    match k {
        Value::String(s) => (0, s.as_bytes()),
        _ => (1, &[]),
    }
}

fn encode_unsigned(u: u64, out: &mut Vec<u8>) {
    if u < 128 {
        out.push(u as u8);
    } else if u <= u8::MAX as u64 {
        out.push(0xcc);
        out.push(u as u8);
    } else if u <= u16::MAX as u64 {
        out.push(0xcd);
        out.extend_from_slice(&(u as u16).to_be_bytes());
    } else if u <= u32::MAX as u64 {
        out.push(0xce);
        out.extend_from_slice(&(u as u32).to_be_bytes());
    } else {
        out.push(0xcf);
        out.extend_from_slice(&u.to_be_bytes());
    }
}

fn encode_negative(s: i64, out: &mut Vec<u8>) {
    if s >= -32 {
        out.push(s as i8 as u8);
    } else if s >= i8::MIN as i64 {
        out.push(0xd0);
        out.push(s as i8 as u8);
    } else if s >= i16::MIN as i64 {
        out.push(0xd1);
        out.extend_from_slice(&(s as i16).to_be_bytes());
    } else if s >= i32::MIN as i64 {
        out.push(0xd2);
        out.extend_from_slice(&(s as i32).to_be_bytes());
    } else {
        out.push(0xd3);
        out.extend_from_slice(&s.to_be_bytes());
    }
}

/// nlohmann's `write_compact_float`: float32 iff within float range and exact (so NaN and
/// infinities go out as float64).
fn encode_float(f: f64, out: &mut Vec<u8>) {
    if f >= f32::MIN as f64 && f <= f32::MAX as f64 && (f as f32) as f64 == f {
        out.push(0xca);
        out.extend_from_slice(&(f as f32).to_be_bytes());
    } else {
        out.push(0xcb);
        out.extend_from_slice(&f.to_be_bytes());
    }
}

/// Decodes one complete document; trailing bytes are an error (nlohmann's strict mode).
pub fn decode(bytes: &[u8]) -> Result<Value, String> {
    let mut rd = bytes;
    let v = rmpv::decode::read_value(&mut rd).map_err(|e| match e {
        rmpv::decode::Error::DepthLimitExceeded => "msgpack nesting too deep".to_string(),
        e => format!("invalid msgpack: {e}"),
    })?;
    if !rd.is_empty() {
        return Err(format!(
            "invalid msgpack: {} trailing bytes after the document",
            rd.len()
        ));
    }
    Ok(v)
}

// Small builders that keep the document code readable.

pub fn s(v: &str) -> Value {
    Value::String(v.into())
}

/// A float the reference holds as C++ `float` (stored by nlohmann as the widened double).
pub fn f(v: f32) -> Value {
    Value::F64(v as f64)
}

/// A number the reference parsed from JSON text (a double).
pub fn d(v: f64) -> Value {
    Value::F64(v)
}

pub fn u(v: u64) -> Value {
    Value::from(v)
}

pub fn i(v: i64) -> Value {
    Value::from(v)
}

pub fn fv(v: &[f32]) -> Value {
    Value::Array(v.iter().map(|x| f(*x)).collect())
}

pub fn map(entries: Vec<(&str, Value)>) -> Value {
    Value::Map(entries.into_iter().map(|(k, v)| (s(k), v)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn enc(v: Value) -> Vec<u8> {
        let mut o = Vec::new();
        encode(&v, &mut o);
        o
    }

    #[test]
    fn widths_follow_nlohmann() {
        assert_eq!(enc(u(127)), [0x7f]);
        assert_eq!(enc(u(128)), [0xcc, 0x80]);
        assert_eq!(enc(u(20000)), [0xcd, 0x4e, 0x20]);
        assert_eq!(enc(u(12_206_480)), [0xce, 0x00, 0xba, 0x41, 0x90]);
        // A non-negative signed value is written like an unsigned one.
        assert_eq!(enc(Value::from(200i64)), [0xcc, 200]);
        assert_eq!(enc(i(-1)), [0xff]);
        assert_eq!(enc(i(-33)), [0xd0, 0xdf]);
        assert_eq!(enc(i(-200)), [0xd1, 0xff, 0x38]);
        assert_eq!(enc(d(0.5)), [0xca, 0x3f, 0x00, 0x00, 0x00]);
        assert_eq!(enc(d(0.0)), [0xca, 0, 0, 0, 0]);
        // 0.95 parsed from JSON text has no exact float32: float64.
        let e = enc(d(0.95));
        assert_eq!(e[0], 0xcb);
        assert_eq!(&e[1..], &0.95f64.to_be_bytes());
        // A C++ float widened to double is always exact: float32.
        assert_eq!(enc(f(0.95))[0], 0xca);
        assert_eq!(enc(f(f32::INFINITY))[0], 0xcb);
        assert_eq!(enc(f(f32::NAN))[0], 0xcb);
        assert_eq!(enc(Value::Binary(vec![1, 2])), [0xc4, 2, 1, 2]);
        assert_eq!(enc(Value::Binary(vec![0; 300]))[..3], [0xc5, 0x01, 0x2c]);
        assert_eq!(
            enc(Value::Binary(vec![0; 70000]))[..5],
            [0xc6, 0, 1, 0x11, 0x70]
        );
        assert_eq!(enc(s("nerf")), [0xa4, b'n', b'e', b'r', b'f']);
        assert_eq!(enc(Value::Boolean(true)), [0xc3]);
    }

    #[test]
    fn maps_are_sorted_by_key_bytes() {
        let m = map(vec![("b", u(1)), ("a", u(2)), ("B", u(3))]);
        assert_eq!(enc(m), [0x83, 0xa1, b'B', 3, 0xa1, b'a', 2, 0xa1, b'b', 1]);
        let big = Value::Map((0..16).map(|k| (u(k), Value::Nil)).collect());
        assert_eq!(enc(big)[..3], [0xde, 0, 16]);
    }

    #[test]
    fn decode_round_trip_and_trailing_bytes() {
        let v = map(vec![
            ("x", fv(&[1.0, -2.5])),
            ("y", Value::Binary(vec![9; 3])),
        ]);
        let b = enc(v.clone());
        let back = decode(&b).unwrap();
        let mut again = Vec::new();
        encode(&back, &mut again);
        assert_eq!(again, b);
        let mut t = b.clone();
        t.push(0);
        assert!(decode(&t).unwrap_err().contains("trailing"));
        assert!(decode(&b[..b.len() - 1]).is_err());
        assert!(decode(&[]).is_err());
    }
}
