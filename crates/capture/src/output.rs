//! The output folder appears whole or not at all: everything is built in a hidden folder
//! beside it (`.NAME.process.PID.tmp`), synced, and renamed to NAME at the end. A handled
//! error removes the hidden folder; only a killed run can leave one behind.

use anyhow::{Context, Result, bail};
use std::path::{Path, PathBuf};

/// What is refused before any work: an output that exists (without `--force`), a file in
/// its place, a missing parent folder, or an output that holds or lies inside the input.
pub fn check(out: &Path, input: &Path, force: bool) -> Result<()> {
    let name = out.file_name().filter(|n| *n != "." && *n != "..");
    if name.is_none() {
        bail!("{}: give the output folder a name", out.display());
    }
    check_parent_dir(out)?;
    if out.exists() || out.is_symlink() {
        if !out.is_dir() || out.is_symlink() {
            bail!(
                "{}: exists and is not a folder; give another --out",
                out.display()
            );
        }
        if !force {
            bail!(
                "{}: exists; give --force to replace it, or another --out",
                out.display()
            );
        }
    }
    let abs_out = absolute(out)?;
    let abs_in = std::fs::canonicalize(input)
        .with_context(|| format!("{}: cannot read", input.display()))?;
    if abs_in.starts_with(&abs_out) {
        bail!(
            "{}: the output would hold the input {}; give another --out",
            out.display(),
            input.display()
        );
    }
    if input.is_dir() && abs_out.starts_with(&abs_in) {
        bail!(
            "{}: the output would lie inside the input folder {}; give another --out",
            out.display(),
            input.display()
        );
    }
    Ok(())
}

/// The output's parent folder must exist.
fn check_parent_dir(path: &Path) -> Result<()> {
    Ok(ngp::util::check_parent_dir(path)?)
}

/// `p` with its parent resolved (the path itself need not exist).
fn absolute(p: &Path) -> Result<PathBuf> {
    let parent = match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let parent = std::fs::canonicalize(parent)
        .with_context(|| format!("{}: cannot resolve its folder", p.display()))?;
    Ok(parent.join(p.file_name().unwrap_or_default()))
}

/// The hidden folder being built, removed unless committed.
pub struct Staging {
    pub dir: PathBuf,
    dest: PathBuf,
    committed: bool,
}

fn hidden_beside(dest: &Path, what: &str) -> PathBuf {
    let name = dest.file_name().unwrap_or_default().to_string_lossy();
    let hidden = format!(".{name}.process.{}.{what}", std::process::id());
    match dest.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.join(hidden),
        _ => PathBuf::from(hidden),
    }
}

/// Removes the working folders that killed runs into `dest` left beside it (their process
/// is gone): a run stopped with Ctrl-C leaves its half-built folder, database included.
fn remove_left_behind(dest: &Path) {
    let name = dest.file_name().unwrap_or_default().to_string_lossy();
    let prefix = format!(".{name}.process.");
    let parent = match dest.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let Ok(rd) = std::fs::read_dir(parent) else {
        return;
    };
    for e in rd.flatten() {
        let file = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = file.strip_prefix(&prefix) else {
            continue;
        };
        let Some((pid, kind)) = rest.split_once('.') else {
            continue;
        };
        let Ok(pid) = pid.parse::<i32>() else {
            continue;
        };
        // SAFETY: signal 0 only asks whether the process exists.
        let gone = unsafe { libc::kill(pid, 0) } != 0
            && std::io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH);
        if gone && (kind == "tmp" || kind == "old") {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

impl Staging {
    pub fn create(dest: &Path) -> Result<Staging> {
        remove_left_behind(dest);
        let dir = hidden_beside(dest, "tmp");
        std::fs::create_dir(&dir)
            .with_context(|| format!("{}: cannot create the working folder", dir.display()))?;
        Ok(Staging {
            dir,
            dest: dest.to_path_buf(),
            committed: false,
        })
    }

    /// Syncs what was built, then puts it under the output's name: an old output (with
    /// `--force`) is moved aside first and removed once the new one is in place.
    pub fn commit(mut self, force: bool) -> Result<()> {
        sync_tree(&self.dir)?;
        let old = (force && self.dest.is_dir()).then(|| hidden_beside(&self.dest, "old"));
        if let Some(old) = &old {
            std::fs::rename(&self.dest, old).with_context(|| {
                format!("{}: cannot move the old output aside", self.dest.display())
            })?;
        }
        if let Err(e) = std::fs::rename(&self.dir, &self.dest) {
            if let Some(old) = &old {
                let _ = std::fs::rename(old, &self.dest);
            }
            return Err(e).with_context(|| {
                format!(
                    "{}: cannot rename the finished output {} to it",
                    self.dest.display(),
                    self.dir.display()
                )
            });
        }
        self.committed = true;
        ngp::util::sync_folder_of(&self.dest)?;
        if let Some(old) = old {
            std::fs::remove_dir_all(&old).with_context(|| {
                format!(
                    "{}: the replaced output could not be removed",
                    old.display()
                )
            })?;
        }
        Ok(())
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// Syncs every file and folder under `dir` (COLMAP writes without syncing).
fn sync_tree(dir: &Path) -> Result<()> {
    for e in std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))? {
        let p = e
            .with_context(|| format!("{}: cannot list", dir.display()))?
            .path();
        if p.is_dir() {
            sync_tree(&p)?;
        } else {
            std::fs::File::open(&p)
                .and_then(|f| f.sync_all())
                .with_context(|| format!("{}: syncing", p.display()))?;
        }
    }
    std::fs::File::open(dir)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("{}: syncing", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_committed_output_replaces_the_old_one_and_a_dropped_one_leaves_nothing() {
        let t = tempfile::tempdir().unwrap();
        let dest = t.path().join("cap");
        let s = Staging::create(&dest).unwrap();
        std::fs::write(s.dir.join("a"), b"1").unwrap();
        drop(s);
        assert_eq!(std::fs::read_dir(t.path()).unwrap().count(), 0);
        let s = Staging::create(&dest).unwrap();
        std::fs::create_dir(s.dir.join("sub")).unwrap();
        std::fs::write(s.dir.join("sub/a"), b"1").unwrap();
        s.commit(false).unwrap();
        assert_eq!(std::fs::read(dest.join("sub/a")).unwrap(), b"1");
        let s = Staging::create(&dest).unwrap();
        std::fs::write(s.dir.join("b"), b"2").unwrap();
        s.commit(true).unwrap();
        assert!(!dest.join("sub").exists());
        assert_eq!(std::fs::read(dest.join("b")).unwrap(), b"2");
        let names: Vec<_> = std::fs::read_dir(t.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("cap")]);
        // What a killed run left (its process gone) goes at the next run; a live one's stays.
        let dead = t.path().join(".cap.process.2147483646.tmp");
        let live = t
            .path()
            .join(format!(".cap.process.{}.old", std::process::id()));
        std::fs::create_dir(&dead).unwrap();
        std::fs::create_dir(&live).unwrap();
        drop(Staging::create(&dest).unwrap());
        assert!(!dead.exists() && live.exists());
    }

    #[test]
    fn outputs_that_exist_or_hold_the_input_are_refused() {
        let t = tempfile::tempdir().unwrap();
        let input = t.path().join("photos");
        std::fs::create_dir(&input).unwrap();
        let e = |out: &Path, force| check(out, &input, force).unwrap_err().to_string();
        assert!(e(&input, true).contains("hold the input"));
        assert!(e(t.path(), true).contains("hold the input"));
        assert!(e(&input.join("out"), false).contains("inside the input"));
        let out = t.path().join("out");
        check(&out, &input, false).unwrap();
        std::fs::create_dir(&out).unwrap();
        assert!(e(&out, false).contains("--force"));
        check(&out, &input, true).unwrap();
        let file = t.path().join("file");
        std::fs::write(&file, b"").unwrap();
        assert!(e(&file, true).contains("not a folder"));
        assert!(e(&t.path().join("no/such/out"), false).contains("does not exist"));
    }
}
