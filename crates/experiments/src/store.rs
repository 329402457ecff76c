//! Resumable model files for experiments that train many models: each `.ingp` has a
//! sidecar `.json` holding `{"config": …}` (everything the file depends on) and what
//! training recorded. A rerun reuses a model whose sidecar holds the same config, and goes
//! on inside a model that was training when the run stopped ([`model_state`]).

use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::util::write_atomic;
use serde_json::{Map, Value};
use std::path::Path;
use training::state::{SaveEvery, StateFile, StateSaver};

/// The sidecar of `path` if it holds `config` and the model file is there, else trains with
/// `train` (the model and the fields to record beside the config), saves the model and then
/// the sidecar: a model without its sidecar is trained again. Returns the sidecar and
/// whether it was reused.
/// `train` gets the model's state saver ([`model_state`]) when `save_every` is given; the state is removed
/// once the sidecar is written (or when the model is reused).
pub(super) fn reuse_or_train(
    path: &Path,
    config: &Value,
    verbose: bool,
    save_every: Option<SaveEvery>,
    train: impl FnOnce(Option<StateSaver>) -> Result<(Model, Map<String, Value>)>,
) -> Result<(Value, bool)> {
    reuse_or_train_with(path, config, verbose, save_every, Model::save, train)
}

/// [`reuse_or_train`], the model stored at full precision ([`Model::save_exact`]): for a
/// model that another process scores as if it had trained it.
pub(super) fn reuse_or_train_exact(
    path: &Path,
    config: &Value,
    verbose: bool,
    save_every: Option<SaveEvery>,
    train: impl FnOnce(Option<StateSaver>) -> Result<(Model, Map<String, Value>)>,
) -> Result<(Value, bool)> {
    reuse_or_train_with(path, config, verbose, save_every, Model::save_exact, train)
}

/// The sidecar of the model at `path` if it holds `config` and the model file is there.
pub(super) fn read_stored(path: &Path, config: &Value) -> Option<Value> {
    let side = path.with_extension("json");
    std::fs::read(&side)
        .ok()
        .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
        .filter(|v| v["config"] == *config && path.exists())
}

fn reuse_or_train_with(
    path: &Path,
    config: &Value,
    verbose: bool,
    save_every: Option<SaveEvery>,
    save: fn(&Model, &Path) -> Result<()>,
    train: impl FnOnce(Option<StateSaver>) -> Result<(Model, Map<String, Value>)>,
) -> Result<(Value, bool)> {
    let side = path.with_extension("json");
    if let Some(v) = read_stored(path, config) {
        if verbose {
            eprintln!("  reusing {}", path.display());
        }
        StateFile::beside_model(path, config.to_string()).remove()?;
        return Ok((v, true));
    }
    let state = save_every.map(|every| model_state(path, config, every));
    let (model, fields) = train(state)?;
    save(&model, path)?;
    let mut v = Map::new();
    v.insert("config".into(), config.clone());
    v.extend(fields);
    let v = Value::Object(v);
    let text = serde_json::to_string_pretty(&v).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&side, text.as_bytes())?;
    StateFile::beside_model(path, config.to_string()).remove()?;
    Ok((v, false))
}

/// A model's training state while it trains (`MODEL.ingp.state`), saved every so often so
/// that a rerun goes on inside the model rather than from its first step: an experiment's
/// [`StateSaver`] (owner-only, written atomically, holding the model's config so that a
/// state left by another configuration is never taken for this one). It is removed once
/// the model and its sidecar are written.
fn model_state(model: &Path, config: &Value, every: SaveEvery) -> StateSaver {
    StateSaver::for_experiment(every, StateFile::beside_model(model, config.to_string()))
}
