//! Small helpers shared by every module that writes files.
//!
//! Every file the program writes goes through [`PendingFile`]: a temporary file in the same
//! folder, synced, renamed over the destination, then the folder synced. A process killed
//! at any moment leaves the old file or the complete new one under the name, never a torn
//! one; a handled error leaves the old file and no temporary file.

use crate::error::{Error, Result};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// An output file's folder must exist: a writer puts a temporary file beside it, then
/// renames. Checked before any work, so that a run does not end by failing to write.
pub fn check_parent_dir(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
        && !dir.is_dir()
    {
        return Err(Error::Other(format!(
            "{}: directory {} does not exist",
            path.display(),
            dir.display()
        )));
    }
    Ok(())
}

/// Writes `bytes` to `path` atomically (see [`PendingFile`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// Like [`write_atomic`], with the content produced by a writer callback.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut File) -> std::io::Result<()>,
) -> Result<()> {
    let (pending, mut file) = PendingFile::create(path)?;
    fill(&mut file).map_err(|e| Error::io(path, e))?;
    pending.commit(file)
}

/// The folder a file named `path` lives in (`.` for a bare name).
fn folder_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Makes a rename into the folder of `path` durable: without it a power cut after the
/// rename may bring back the old directory entry (or none, for a new file). File systems
/// that cannot sync a folder (some network and FUSE mounts answer EINVAL) are let be: the
/// rename itself is already atomic for every process that reads the folder.
pub fn sync_folder_of(path: &Path) -> Result<()> {
    #[cfg(unix)]
    {
        let dir = folder_of(path);
        let synced = File::open(&dir).and_then(|d| d.sync_all());
        if let Err(e) = synced
            && !matches!(
                e.kind(),
                std::io::ErrorKind::InvalidInput | std::io::ErrorKind::Unsupported
            )
        {
            return Err(Error::io(
                path,
                std::io::Error::new(
                    e.kind(),
                    format!(
                        "written, but syncing its folder {} failed: {e}",
                        dir.display()
                    ),
                ),
            ));
        }
    }
    #[cfg(not(unix))]
    let _ = path;
    Ok(())
}

/// Every temporary file this process makes gets its own number, so two threads writing the
/// same destination never share one (the process id alone would collide).
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A file being written beside its destination: hidden, in the same folder (a rename does
/// not cross file systems), named for this process and a per-process counter, ending in
/// `.tmp` so that one left by a killed process is recognisable. [`PendingFile::commit`] puts
/// it under its name; dropping it uncommitted (an error, a panic, an interrupted render)
/// removes it.
#[derive(Debug)]
pub struct PendingFile {
    dest: PathBuf,
    tmp: PathBuf,
    committed: bool,
}

impl PendingFile {
    /// Creates the temporary file for `dest` and returns it open for writing. Errors name
    /// `dest`.
    pub fn create(dest: &Path) -> Result<(Self, File)> {
        let name = dest
            .file_name()
            .ok_or_else(|| Error::format(dest, "not a file path"))?
            .to_string_lossy()
            .into_owned();
        let dir = folder_of(dest);
        let pid = std::process::id();
        // Exclusive creation: a leftover of a killed process whose id this one reuses, or a
        // link planted under the name, is stepped over rather than written through.
        let mut last = None;
        for _ in 0..16 {
            let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
            let tmp = dir.join(format!(".{name}.{pid}.{n}.tmp"));
            match File::options().write(true).create_new(true).open(&tmp) {
                Ok(file) => {
                    let pending = PendingFile {
                        dest: dest.to_path_buf(),
                        tmp,
                        committed: false,
                    };
                    return Ok((pending, file));
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
                Err(e) => return Err(Error::io(dest, e)),
            }
        }
        Err(Error::io(
            dest,
            last.unwrap_or_else(|| std::io::Error::other("no free temporary name")),
        ))
    }

    /// The temporary file's path.
    pub fn temp_path(&self) -> &Path {
        &self.tmp
    }

    /// The destination's path.
    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// Syncs `file` (the one [`PendingFile::create`] returned, fully written), renames it
    /// over the destination and syncs the folder. On an error before the rename the
    /// destination is as it was and the temporary file is gone.
    pub fn commit(mut self, file: File) -> Result<()> {
        file.sync_all().map_err(|e| Error::io(&self.dest, e))?;
        drop(file);
        std::fs::rename(&self.tmp, &self.dest).map_err(|e| Error::io(&self.dest, e))?;
        self.committed = true;
        sync_folder_of(&self.dest)
    }
}

impl Drop for PendingFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// An exclusive advisory lock on a folder that a long run writes many files into, held for
/// the run's lifetime: a second run into the same folder is refused instead of interleaving
/// its files with the first's. The lock is the kernel's `flock` on `DIR/.lock`, so it ends
/// with the process however that ends, and the file itself is left in place (removing it
/// would let a third run lock a fresh file while the second still holds the old one).
#[derive(Debug)]
pub struct FolderLock {
    _file: File,
}

impl FolderLock {
    /// The name of the lock file inside a locked folder.
    pub const FILE: &str = ".lock";

    /// Locks `dir` (which must exist) without waiting. Errors name the folder and, when
    /// another process holds it, say so.
    pub fn acquire(dir: &Path) -> Result<FolderLock> {
        let path = dir.join(Self::FILE);
        let file = File::options()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        match file.try_lock() {
            Ok(()) => Ok(FolderLock { _file: file }),
            Err(std::fs::TryLockError::WouldBlock) => Err(Error::Other(format!(
                "{}: another stegongp run is writing into this folder (it holds {}); \
                 wait for it to end or choose another output folder",
                dir.display(),
                path.display()
            ))),
            Err(std::fs::TryLockError::Error(e)) => Err(Error::io(&path, e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn atomic_write_replaces_and_leaves_no_temp() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(names(dir.path()), ["a.bin"]);
    }

    /// A missing folder: an error naming the file, nothing created.
    #[test]
    fn a_missing_parent_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("missing_dir").join("x.bin");
        let e = write_atomic(&bad, b"x").unwrap_err().to_string();
        assert!(e.contains("missing_dir/x.bin"), "{e}");
        assert!(names(dir.path()).is_empty());
    }

    /// A failing writer callback: the old file as it was, no temporary file.
    #[test]
    fn a_failed_fill_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        write_atomic(&p, b"old").unwrap();
        let e = write_atomic_with(&p, |f| {
            f.write_all(b"half")?;
            Err(std::io::Error::other("disk on fire"))
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("a.bin") && e.contains("disk on fire"), "{e}");
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(names(dir.path()), ["a.bin"]);
    }

    /// A pending file dropped uncommitted (an error mid-way, a panic) removes its temporary.
    #[test]
    fn an_uncommitted_pending_file_is_removed() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v.mp4");
        let (pending, mut f) = PendingFile::create(&p).unwrap();
        f.write_all(b"partial").unwrap();
        assert!(pending.temp_path().exists());
        assert!(pending.temp_path().to_string_lossy().ends_with(".tmp"));
        drop(pending);
        drop(f);
        assert!(names(dir.path()).is_empty());
    }

    /// Threads of one process writing the same file each get their own temporary file: the
    /// result is one writer's complete content, never a mix, and nothing is left over.
    #[test]
    fn threads_writing_one_path_do_not_share_a_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("same.bin");
        let contents: Vec<Vec<u8>> = (0..8u8).map(|i| vec![i; 64 * 1024]).collect();
        std::thread::scope(|s| {
            for c in &contents {
                let p = &p;
                s.spawn(move || {
                    for _ in 0..4 {
                        write_atomic(p, c).unwrap();
                    }
                });
            }
        });
        let got = std::fs::read(&p).unwrap();
        assert!(contents.contains(&got), "a mixed file");
        assert_eq!(names(dir.path()), ["same.bin"]);
    }

    /// A read-only folder: an error naming the file, the old file as it was, no temporary
    /// file. Root ignores permissions, so there it says so and checks nothing.
    #[cfg(unix)]
    #[test]
    fn a_read_only_folder_is_an_error_naming_the_file() {
        use std::os::unix::fs::PermissionsExt;
        // SAFETY: geteuid has no preconditions.
        if unsafe { libc::geteuid() } == 0 {
            eprintln!("skipped: root writes into read-only folders");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ingp");
        write_atomic(&p, b"old").unwrap();
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o555)).unwrap();
        let r = write_atomic(&p, b"new");
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
        let e = r.unwrap_err().to_string();
        assert!(e.contains("m.ingp"), "{e}");
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(names(dir.path()), ["m.ingp"]);
    }

    /// The environment variable that turns [`a_full_disk_keeps_the_old_file`] into its own
    /// child: the write under a file-size limit.
    const FULL_DISK_CHILD: &str = "STEGONGP_UTIL_FULL_DISK_CHILD";

    /// A full disk, as a file-size limit makes one: the test runs itself again as a child
    /// with RLIMIT_FSIZE at 64 KiB (SIGXFSZ ignored, so the write fails with EFBIG instead of
    /// killing it), which writes 1 MiB over an existing file. The child reports an error
    /// naming the file; the old file is byte-identical and no temporary file is left.
    #[cfg(unix)]
    #[test]
    fn a_full_disk_keeps_the_old_file() {
        if let Some(target) = std::env::var_os(FULL_DISK_CHILD) {
            match write_atomic(Path::new(&target), &vec![7u8; 1 << 20]) {
                Ok(()) => std::process::exit(0),
                Err(e) => {
                    eprintln!("child error: {e}");
                    std::process::exit(3);
                }
            }
        }
        use std::os::unix::process::CommandExt;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model.ingp");
        let old: Vec<u8> = (0..5000u32).map(|i| (i * 31 % 251) as u8).collect();
        std::fs::write(&p, &old).unwrap();
        let mut cmd = std::process::Command::new(std::env::current_exe().unwrap());
        cmd.args([
            "--exact",
            "util::tests::a_full_disk_keeps_the_old_file",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(FULL_DISK_CHILD, &p);
        // SAFETY: between fork and exec only async-signal-safe calls (setrlimit, signal).
        unsafe {
            cmd.pre_exec(|| {
                let lim = libc::rlimit {
                    rlim_cur: 64 * 1024,
                    rlim_max: 64 * 1024,
                };
                if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
                Ok(())
            });
        }
        let out = cmd.output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned()
            + &String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success(),
            "the child wrote past the limit: {text}"
        );
        assert!(
            text.contains("child error:") && text.contains("too large"),
            "{text}"
        );
        assert!(text.contains(&p.display().to_string()), "{text}");
        assert_eq!(std::fs::read(&p).unwrap(), old);
        assert_eq!(names(dir.path()), ["model.ingp"]);
    }

    #[test]
    fn a_held_folder_lock_refuses_a_second_and_frees_on_drop() {
        let dir = tempfile::tempdir().unwrap();
        let first = FolderLock::acquire(dir.path()).unwrap();
        let e = FolderLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains(&dir.path().display().to_string()) && e.contains("another stegongp run"),
            "{e}"
        );
        drop(first);
        FolderLock::acquire(dir.path()).unwrap();
    }
}
