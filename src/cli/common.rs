//! Pieces shared by the subcommands.

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::Path;
use stegongp::ngp::data::Split;

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SplitArg {
    Train,
    Val,
    Test,
}

impl From<SplitArg> for Split {
    fn from(s: SplitArg) -> Split {
        match s {
            SplitArg::Train => Split::Train,
            SplitArg::Val => Split::Val,
            SplitArg::Test => Split::Test,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Background {
    White,
    Black,
}

impl Background {
    pub fn rgb(self) -> [f32; 3] {
        match self {
            Background::White => [1.0; 3],
            Background::Black => [0.0; 3],
        }
    }
}

/// Fails before any work when a model can't be written to `path`.
pub fn check_model_path(path: &Path) -> Result<()> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("ingp") | Some("msgpack") => {}
        _ => bail!(
            "{}: a model file must end in .ingp (gzip-compressed snapshot) or .msgpack",
            path.display()
        ),
    }
    check_parent_dir(path)?;
    Ok(())
}

pub fn ensure_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("{}: cannot create directory", dir.display()))
}

pub fn progress(len: u64, template: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template(template)
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb
}

/// An output file's folder must exist: we write a temporary file beside it, then rename.
pub fn check_parent_dir(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
        && !dir.is_dir()
    {
        bail!(
            "{}: directory {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(())
}
