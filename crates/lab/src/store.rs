//! Resumable model files for experiments that train many models: each `.ingp` has a
//! sidecar `.json` holding `{"config": …}` (everything the file depends on) and what
//! training recorded. A rerun reuses a model whose sidecar holds the same config, and goes
//! on inside a model that was training when the run stopped ([`ModelState`]).

use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::util::write_atomic;
use serde_json::{Map, Value};
use std::path::{Path, PathBuf};
use stego::recipe::{SaveEvery, Training};

/// The sidecar of `path` if it holds `config` and the model file is there, else trains with
/// `train` (the model and the fields to record beside the config), saves the model and then
/// the sidecar: a model without its sidecar is trained again. Returns the sidecar and
/// whether it was reused.
/// `train` gets the model's [`ModelState`] when `save_every` is given; the state is removed
/// once the sidecar is written (or when the model is reused).
pub(super) fn reuse_or_train(
    path: &Path,
    config: &Value,
    verbose: bool,
    save_every: Option<SaveEvery>,
    train: impl FnOnce(Option<&mut ModelState>) -> Result<(Model, Map<String, Value>)>,
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
    train: impl FnOnce(Option<&mut ModelState>) -> Result<(Model, Map<String, Value>)>,
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
    train: impl FnOnce(Option<&mut ModelState>) -> Result<(Model, Map<String, Value>)>,
) -> Result<(Value, bool)> {
    let side = path.with_extension("json");
    if let Some(v) = read_stored(path, config) {
        if verbose {
            eprintln!("  reusing {}", path.display());
        }
        remove(&state_path(path))?;
        return Ok((v, true));
    }
    let mut state = save_every.map(|every| ModelState::new(path, config, every, verbose));
    let (model, fields) = train(state.as_mut())?;
    save(&model, path)?;
    let mut v = Map::new();
    v.insert("config".into(), config.clone());
    v.extend(fields);
    let v = Value::Object(v);
    let text = serde_json::to_string_pretty(&v).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&side, text.as_bytes())?;
    remove(&state_path(path))?;
    Ok((v, false))
}

/// A model's training state while it trains (`MODEL.ingp.state`), saved every so often so
/// that a rerun goes on inside the model rather than from its first step. Owner-only and
/// written atomically like a key ([`stego::keyfile::write_secret`]): a stego model's state
/// describes its hidden scene. It holds the model's config, so that a state left by another
/// configuration is never taken for this one, and it is removed once the model and its
/// sidecar are written.
pub(crate) struct ModelState<'a> {
    path: PathBuf,
    config: &'a Value,
    every: SaveEvery,
    saved_at: f64,
    /// Set when the device cannot save a state (said once, then training goes on without).
    off: bool,
    verbose: bool,
}

/// The document around a model's run state.
const STATE_FORMAT: &str = "stegongp-experiment-model-state";

impl<'a> ModelState<'a> {
    /// The state of the model at `model` (its path with `.state` added).
    pub(crate) fn new(model: &Path, config: &'a Value, every: SaveEvery, verbose: bool) -> Self {
        ModelState {
            path: state_path(model),
            config,
            every,
            saved_at: 0.0,
            off: false,
            verbose,
        }
    }

    /// Goes on from the saved state, if there is one of this model's config ([`Self::read`]).
    pub(crate) fn resume(&mut self, training: &mut Training) -> Result<()> {
        let Some(run) = self.read()? else {
            return Ok(());
        };
        training
            .restore_state_doc(&run, &self.path)
            .map_err(damaged)?;
        self.saved_at = training.totals().seconds;
        if self.verbose {
            eprintln!(
                "  resumed {} at step {} ({:.1} s trained)",
                self.path.display(),
                training.totals().steps,
                self.saved_at
            );
        }
        Ok(())
    }

    /// The saved run state, if there is one of this model's config. One of another config is
    /// removed (the model it belonged to is not this run's); a damaged one is an error naming
    /// it.
    fn read(&self) -> Result<Option<rmpv::Value>> {
        use ngp::train::state::{Fields, open};
        let bytes = match std::fs::read(&self.path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(&self.path, e)),
        };
        let mut doc = open(&self.path, &bytes).map_err(damaged)?;
        drop(bytes);
        let f = Fields::top(&self.path, &doc).map_err(damaged)?;
        if f.str("format").map_err(damaged)? != STATE_FORMAT {
            return Err(damaged(f.err("format", "not a model's training state")));
        }
        let config: Option<Value> = serde_json::from_str(f.str("config").map_err(damaged)?).ok();
        if config.as_ref() != Some(self.config) {
            if self.verbose {
                eprintln!(
                    "  {}: left by another configuration, removed",
                    self.path.display()
                );
            }
            remove(&self.path)?;
            return Ok(None);
        }
        f.value("run").map_err(damaged)?;
        // Taken out of the document, not copied: a model's state is hundreds of megabytes.
        Ok(ngp::train::state::take(&mut doc, "run"))
    }

    /// Saves the state if one is due after this step. A device that cannot save one says so
    /// once, and the model trains on without (its model is still written).
    pub(crate) fn after_step(&mut self, training: &Training) -> Result<()> {
        if self.off || !self.every.due(training.totals(), self.saved_at) {
            return Ok(());
        }
        let run = match training.save_state_doc() {
            Ok(run) => run,
            Err(Error::Config(why)) => {
                eprintln!("  no training state for this model: {why}");
                self.off = true;
                return Ok(());
            }
            Err(e) => return Err(e),
        };
        use ngp::train::state::{encode, map};
        let config = serde_json::to_string(self.config).map_err(|e| Error::Other(e.to_string()))?;
        let doc = map(vec![
            ("format", rmpv::Value::from(STATE_FORMAT)),
            ("config", rmpv::Value::from(config)),
            ("run", run),
        ]);
        stego::keyfile::write_secret(&self.path, &encode(&doc))?;
        self.saved_at = training.totals().seconds;
        Ok(())
    }
}

/// An error about a model's state, with what to do about it.
fn damaged(e: Error) -> Error {
    Error::Other(format!(
        "{e} (a model's training state left by an interrupted experiment: delete it to train \
         that model from its first step)"
    ))
}

fn state_path(model: &Path) -> PathBuf {
    let mut p = model.as_os_str().to_owned();
    p.push(".state");
    PathBuf::from(p)
}

fn remove(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(path, e)),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// A state is taken back only by the config that saved it: another config's is removed,
    /// a damaged one is an error naming it and saying what to do, none is nothing.
    #[test]
    fn a_model_state_belongs_to_its_config() {
        use ngp::train::state::{encode, map};
        let d = tempfile::tempdir().unwrap();
        let model = d.path().join("m.ingp");
        let config = json!({"steps": 30, "seed": 1});
        let every = SaveEvery::Steps(5);
        let st = ModelState::new(&model, &config, every, false);
        assert!(st.read().unwrap().is_none(), "no state, nothing to resume");
        let doc = |config: &Value| {
            encode(&map(vec![
                ("format", rmpv::Value::from(STATE_FORMAT)),
                ("config", rmpv::Value::from(config.to_string())),
                ("run", rmpv::Value::Binary(vec![1, 2, 3])),
            ]))
        };
        let path = d.path().join("m.ingp.state");
        std::fs::write(&path, doc(&config)).unwrap();
        assert_eq!(st.read().unwrap(), Some(rmpv::Value::Binary(vec![1, 2, 3])));
        // Another config's (the budget changed): removed, nothing resumed.
        std::fs::write(&path, doc(&json!({"steps": 31, "seed": 1}))).unwrap();
        assert!(st.read().unwrap().is_none());
        assert!(!path.exists(), "a stale state stays behind");
        // Damaged: an error naming the file.
        let mut bytes = doc(&config);
        bytes.truncate(bytes.len() / 2);
        std::fs::write(&path, bytes).unwrap();
        let e = st.read().unwrap_err().to_string();
        assert!(e.contains("m.ingp.state") && e.contains("delete it"), "{e}");
        assert!(path.exists(), "a damaged state is the user's to delete");
    }
}
