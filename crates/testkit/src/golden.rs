//! Golden files (`tests/golden/KIND/NAME.txt`): what a user and a script see, kept as it was
//! unless a change means to alter it. `STEGONGP_BLESS=1` rewrites them instead of comparing;
//! the diff is then reviewed as part of the change.

use serde_json::Value;
use std::path::PathBuf;

fn golden(kind: &str, name: &str) -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/golden"))
        .join(kind)
        .join(format!("{name}.txt"))
}

/// Compares `text` with its golden file, or rewrites the file under `STEGONGP_BLESS`.
/// Returns the mismatch, if any, so that one run can name them all.
pub fn check(kind: &str, name: &str, text: &str) -> Option<String> {
    let path = golden(kind, name);
    if std::env::var_os("STEGONGP_BLESS").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, text).unwrap();
        return None;
    }
    let want = std::fs::read_to_string(&path).unwrap_or_default();
    (want != text).then(|| {
        let line = want
            .lines()
            .zip(text.lines())
            .position(|(a, b)| a != b)
            .unwrap_or(want.lines().count().min(text.lines().count()));
        format!(
            "{}: differs from line {} (now: {:?})",
            path.display(),
            line + 1,
            text.lines().nth(line).unwrap_or("<end>")
        )
    })
}

/// A `--json` document's shape against `tests/golden/json/NAME.txt`: a failure names the
/// first line that differs.
pub fn assert_json_shape(name: &str, v: &Value) {
    if let Some(differ) = check("json", name, &json_shape(v)) {
        panic!("{differ}");
    }
}

/// A document's shape: its keys in order, each value's kind, an array's first element.
pub fn json_shape(v: &Value) -> String {
    let mut s = String::new();
    shape(v, 0, &mut s);
    s
}

fn shape(v: &Value, indent: usize, out: &mut String) {
    let pad = "  ".repeat(indent);
    match v {
        Value::Object(m) => {
            for (k, v) in m {
                match v {
                    Value::Object(_) => {
                        out.push_str(&format!("{pad}{k}: object\n"));
                        shape(v, indent + 1, out);
                    }
                    Value::Array(a) => {
                        out.push_str(&format!("{pad}{k}: array\n"));
                        if let Some(first) = a.first() {
                            shape(first, indent + 1, out);
                        }
                    }
                    _ => out.push_str(&format!("{pad}{k}: {}\n", kind(v))),
                }
            }
        }
        Value::Array(a) => {
            out.push_str(&format!("{pad}[array]\n"));
            if let Some(first) = a.first() {
                shape(first, indent + 1, out);
            }
        }
        _ => out.push_str(&format!("{pad}{}\n", kind(v))),
    }
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "bool",
        Value::Number(_) => "number",
        Value::String(_) => "string",
        Value::Array(_) => "array",
        Value::Object(_) => "object",
    }
}
