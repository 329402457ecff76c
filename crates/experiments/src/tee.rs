//! A job's log: everything the process writes to stderr (progress, errors) also appended to
//! a file in the plan's folder, whichever scheduler ran it and wherever that one sends its
//! own output, so that `collect` can show why a job did not finish.

use crate::plan::{bare, context};
use ngp::error::Result;
use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::{FromRawFd, OwnedFd};
use std::path::Path;

/// Stderr copied into a file until [`Tee::stop`].
pub(crate) struct Tee {
    /// The process's stderr as it was, restored by `stop`.
    saved: OwnedFd,
    copier: std::thread::JoinHandle<()>,
}

impl Tee {
    /// From now on, stderr also goes to `log` (appended).
    pub fn start(log: &Path) -> Result<Tee> {
        let mut file = File::options()
            .create(true)
            .append(true)
            .open(log)
            .map_err(context(format!(
                "{}: cannot open the job's log",
                log.display()
            )))?;
        let mut fds = [0i32; 2];
        // SAFETY: plain POSIX calls on descriptors this function owns; every result is
        // checked, and each descriptor is owned by exactly one OwnedFd/File afterwards.
        let (read_end, saved) = unsafe {
            if libc::pipe(fds.as_mut_ptr()) != 0 {
                return Err(context("pipe for the job's log")(
                    std::io::Error::last_os_error(),
                ));
            }
            let saved = libc::dup(2);
            if saved < 0 || libc::dup2(fds[1], 2) < 0 {
                let e = std::io::Error::last_os_error();
                libc::close(fds[0]);
                libc::close(fds[1]);
                if saved >= 0 {
                    libc::close(saved);
                }
                return Err(context("redirecting stderr into the job's log")(e));
            }
            libc::close(fds[1]);
            (File::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(saved))
        };
        let mut terminal = File::from(saved.try_clone().map_err(bare)?);
        let copier = std::thread::spawn(move || {
            let mut read_end = read_end;
            let mut buf = [0u8; 8192];
            // Ends when the last writer (fd 2) is closed by `stop`.
            while let Ok(n) = read_end.read(&mut buf) {
                if n == 0 {
                    break;
                }
                let _ = terminal.write_all(&buf[..n]);
                let _ = file.write_all(&buf[..n]);
            }
        });
        Ok(Tee { saved, copier })
    }

    /// Stderr back to where it was; everything written so far is in the log.
    pub fn stop(self) {
        use std::os::fd::AsRawFd;
        // SAFETY: `saved` is a valid descriptor owned by self; dup2 replaces fd 2, which
        // closes the pipe's last writer, so the copier sees the end of its input.
        unsafe {
            libc::dup2(self.saved.as_raw_fd(), 2);
        }
        let _ = self.copier.join();
    }
}
