//! The outside programs `process` drives (ffmpeg, ffprobe, colmap): found by running them,
//! so that a missing one is reported before any work, with the package that brings it.

use anyhow::{Result, anyhow};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

/// One outside program and how a user gets it.
#[derive(Clone, Debug)]
pub struct Tool {
    /// What the user knows it as (`colmap`, `ffmpeg`, `ffprobe`).
    pub name: &'static str,
    /// The program run: a bare name looked up on PATH, or a path.
    pub path: PathBuf,
    /// The Debian / Ubuntu package (and Homebrew formula) that installs it.
    pub package: &'static str,
    /// The option that names another copy.
    pub flag: &'static str,
}

impl Tool {
    pub fn command(&self) -> Command {
        let mut c = Command::new(&self.path);
        c.stdin(Stdio::null());
        c
    }

    /// What a failure to start it means for the user: not installed, or not runnable.
    pub fn spawn_error(&self, e: std::io::Error) -> anyhow::Error {
        if e.kind() == std::io::ErrorKind::NotFound {
            anyhow!(
                "{} not found ({}): install it (Debian/Ubuntu: apt-get install {}; macOS: brew \
                 install {}), or give its path with {}",
                self.name,
                self.path.display(),
                self.package,
                self.package,
                self.flag
            )
        } else {
            anyhow!(
                "{} ({}) could not be started: {e}",
                self.name,
                self.path.display()
            )
        }
    }

    /// Runs it to completion with `args`, its output captured.
    pub fn output<I, S>(&self, args: I) -> Result<Output>
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        self.command()
            .args(args)
            .output()
            .map_err(|e| self.spawn_error(e))
    }
}

pub fn colmap(path: Option<&Path>) -> Tool {
    Tool {
        name: "colmap",
        path: path.map_or_else(|| "colmap".into(), Path::to_path_buf),
        package: "colmap",
        flag: "--colmap",
    }
}

pub fn ffmpeg(path: Option<&Path>) -> Tool {
    Tool {
        name: "ffmpeg",
        path: path.map_or_else(|| "ffmpeg".into(), Path::to_path_buf),
        package: "ffmpeg",
        flag: "--ffmpeg",
    }
}

/// ffprobe ships with ffmpeg: beside a given ffmpeg when it is there, else on PATH.
pub fn ffprobe(ffmpeg: Option<&Path>) -> Tool {
    let beside = ffmpeg
        .and_then(Path::parent)
        .filter(|d| !d.as_os_str().is_empty())
        .map(|d| d.join(format!("ffprobe{}", std::env::consts::EXE_SUFFIX)))
        .filter(|p| p.is_file());
    Tool {
        name: "ffprobe",
        path: beside.unwrap_or_else(|| "ffprobe".into()),
        package: "ffmpeg",
        flag: "--ffmpeg (ffprobe is looked for beside it)",
    }
}

/// Processor seconds spent so far by this process and the children it has waited for: a
/// stage's cost that does not depend on what else the machine runs.
pub fn cpu_seconds() -> f64 {
    let used = |who| {
        // SAFETY: rusage is plain integers, for which all zeros is a valid value.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: getrusage fills the struct it is given and reads nothing else.
        if unsafe { libc::getrusage(who, &mut u) } != 0 {
            return 0.0;
        }
        let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
        t(u.ru_utime) + t(u.ru_stime)
    };
    used(libc::RUSAGE_SELF) + used(libc::RUSAGE_CHILDREN)
}

/// The first line of a program's output that says something, for messages.
pub fn first_line(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes)
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .unwrap_or("")
        .to_string()
}

/// The version word after `name` in a banner such as "ffmpeg version 5.1.9-0+deb12u1 …"
/// or "COLMAP 3.8 -- Structure-from-Motion …".
pub fn version_after(text: &str, name: &str) -> Option<String> {
    text.lines().find_map(|l| {
        let rest = l.trim().strip_prefix(name)?.trim_start();
        let rest = rest.strip_prefix("version").unwrap_or(rest).trim_start();
        let v = rest.split_whitespace().next()?;
        v.starts_with(|c: char| c.is_ascii_digit() || c == 'n')
            .then(|| v.to_string())
    })
}

/// The leading major and minor numbers of a version ("5.1.9-0+deb12u1" → (5, 1); "n7.0"
/// → (7, 0); "3.8" → (3, 8)); a missing minor is 0.
pub fn major_minor(version: &str) -> Option<(u32, u32)> {
    let mut parts = version
        .trim_start_matches('n')
        .split(|c: char| !c.is_ascii_digit());
    let major = parts.next()?.parse().ok()?;
    let minor = parts.next().and_then(|m| m.parse().ok()).unwrap_or(0);
    Some((major, minor))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_from_banners() {
        let c = "COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo\n  (Commit Unknown)";
        assert_eq!(version_after(c, "COLMAP").as_deref(), Some("3.8"));
        let c = "COLMAP 3.13.0.dev0 (Commit 1234 on 2025-01-01 without CUDA)";
        assert_eq!(version_after(c, "COLMAP").as_deref(), Some("3.13.0.dev0"));
        let f = "ffmpeg version 5.1.9-0+deb12u1 Copyright (c) 2000-2026 the FFmpeg developers";
        let v = version_after(f, "ffmpeg").unwrap();
        assert_eq!(v, "5.1.9-0+deb12u1");
        assert_eq!(major_minor(&v), Some((5, 1)));
        assert_eq!(major_minor("n7.0.2"), Some((7, 0)));
        assert_eq!(major_minor("3.13.0.dev0"), Some((3, 13)));
        assert_eq!(major_minor("4"), Some((4, 0)));
        assert_eq!(major_minor("git"), None);
        assert_eq!(version_after("Usage: colmap", "COLMAP"), None);
    }

    #[test]
    fn a_missing_program_names_its_package() {
        let t = colmap(Some(Path::new("/nonexistent/colmap")));
        let e = t.output(["-h"]).unwrap_err().to_string();
        assert!(e.contains("apt-get install colmap"), "{e}");
        assert!(e.contains("--colmap"), "{e}");
    }
}
