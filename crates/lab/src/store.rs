//! Resumable model files for experiments that train many models: each `.ingp` has a
//! sidecar `.json` holding `{"config": …}` (everything the file depends on) and what
//! training recorded. A rerun reuses a model whose sidecar holds the same config.

use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::util::write_atomic;
use serde_json::{Map, Value};
use std::path::Path;

/// The sidecar of `path` if it holds `config` and the model file is there, else trains with
/// `train` (the model and the fields to record beside the config), saves the model and then
/// the sidecar: a model without its sidecar is trained again. Returns the sidecar and
/// whether it was reused.
pub(super) fn reuse_or_train(
    path: &Path,
    config: &Value,
    verbose: bool,
    train: impl FnOnce() -> Result<(Model, Map<String, Value>)>,
) -> Result<(Value, bool)> {
    let side = path.with_extension("json");
    let reused = std::fs::read(&side)
        .ok()
        .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
        .filter(|v| v["config"] == *config && path.exists());
    if let Some(v) = reused {
        if verbose {
            eprintln!("  reusing {}", path.display());
        }
        return Ok((v, true));
    }
    let (model, fields) = train()?;
    model.save(path)?;
    let mut v = Map::new();
    v.insert("config".into(), config.clone());
    v.extend(fields);
    let v = Value::Object(v);
    let text = serde_json::to_string_pretty(&v).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&side, text.as_bytes())?;
    Ok((v, false))
}
