//! COLMAP driven as a user would drive it, headless: its version and option names read from
//! its own help (3.8's `SiftExtraction.use_gpu` became `FeatureExtraction.use_gpu` in later
//! releases), each stage's output kept in `colmap.log` and read for progress, the largest
//! model kept, and `model_analyzer`'s figures read back.

use crate::Progress;
use crate::tools::{Tool, cpu_seconds, first_line, version_after};
use anyhow::{Context, Result, anyhow, bail};
use std::collections::{HashMap, HashSet, VecDeque};
use std::ffi::OsString;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::mpsc;
use std::time::Instant;

/// Lines of COLMAP's log kept for an error message.
const TAIL_LINES: usize = 15;

/// What COLMAP's mapper says when it ends without a model because no pair of images starts
/// one (an exit status of 1, not a crash).
const NO_MODEL: [&str; 3] = [
    "failed to create sparse model",
    "No good initial image pair",
    "No images with matches",
];

/// The log of every COLMAP stage, and its last lines.
pub struct Log {
    /// Written a line at a time, so that the log of a run killed mid-stage is whole.
    file: std::io::LineWriter<std::fs::File>,
    pub path: PathBuf,
    tail: VecDeque<String>,
    /// The current stage said one of [`NO_MODEL`].
    pub no_model: bool,
}

impl Log {
    pub fn create(path: &Path) -> Result<Log> {
        let f = std::fs::File::create(path)
            .with_context(|| format!("{}: cannot create", path.display()))?;
        Ok(Log {
            file: std::io::LineWriter::new(f),
            path: path.to_path_buf(),
            tail: VecDeque::new(),
            no_model: false,
        })
    }

    fn line(&mut self, s: &str) -> Result<()> {
        self.no_model |= NO_MODEL.iter().any(|m| s.contains(m));
        writeln!(self.file, "{s}").with_context(|| format!("{}: writing", self.path.display()))?;
        if self.tail.len() == TAIL_LINES {
            self.tail.pop_front();
        }
        self.tail.push_back(s.to_string());
        Ok(())
    }

    /// A line of ours among COLMAP's.
    pub fn note(&mut self, s: &str) -> Result<()> {
        self.line(&format!("== note: {s}"))
    }

    /// The last lines written, indented for an error message.
    pub fn tail(&self) -> String {
        let v: Vec<&str> = self.tail.iter().map(String::as_str).collect();
        format!("  {}", v.join("\n  "))
    }

    /// Flushes and syncs the log (it is renamed into place with the output).
    pub fn finish(self) -> Result<()> {
        let f = self
            .file
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("{}: writing", self.path.display()))?;
        f.sync_all()
            .with_context(|| format!("{}: syncing", self.path.display()))
    }
}

/// One COLMAP installation.
pub struct Colmap {
    tool: Tool,
    pub version: String,
    /// Option names each command takes, from its `-h`.
    options: HashMap<String, HashSet<String>>,
}

/// The environment every COLMAP command runs in: Qt without a display.
fn headless(c: &mut std::process::Command) {
    c.env("QT_QPA_PLATFORM", "offscreen");
}

impl Colmap {
    /// Runs `colmap -h`: the program must be there and say it is COLMAP.
    pub fn open(tool: Tool) -> Result<Colmap> {
        let mut c = tool.command();
        headless(&mut c);
        let out = c.arg("-h").output().map_err(|e| tool.spawn_error(e))?;
        let text = String::from_utf8_lossy(&out.stdout).into_owned()
            + &String::from_utf8_lossy(&out.stderr);
        let version = version_after(&text, "COLMAP").ok_or_else(|| {
            anyhow!(
                "{} does not look like COLMAP (`-h` said: {:?}); install it (Debian/Ubuntu: \
                 apt-get install colmap) or give its path with --colmap",
                tool.path.display(),
                first_line(text.as_bytes())
            )
        })?;
        Ok(Colmap {
            tool,
            version,
            options: HashMap::new(),
        })
    }

    /// The first of `names` that `cmd` takes, from its help (asked once a command).
    pub fn pick(&mut self, cmd: &str, names: &[&str]) -> Result<Option<String>> {
        if !self.options.contains_key(cmd) {
            let mut c = self.tool.command();
            headless(&mut c);
            let out = c
                .args([cmd, "-h"])
                .output()
                .map_err(|e| self.tool.spawn_error(e))?;
            let text = String::from_utf8_lossy(&out.stdout).into_owned()
                + &String::from_utf8_lossy(&out.stderr);
            let set: HashSet<String> = text
                .split_whitespace()
                .filter_map(|w| w.strip_prefix("--"))
                .map(str::to_string)
                .collect();
            if set.is_empty() {
                bail!(
                    "COLMAP {} has no command {cmd} (its help listed no options)",
                    self.version
                );
            }
            self.options.insert(cmd.to_string(), set);
        }
        let set = &self.options[cmd];
        Ok(names
            .iter()
            .find(|n| set.contains(**n))
            .map(|n| n.to_string()))
    }

    /// Runs `colmap cmd args`, its output into `log`; `progress` reads a line into a
    /// (done, of) pair for `pb`. A failure carries the log's last lines. Returns the wall
    /// and processor seconds it took.
    pub fn run(
        &self,
        cmd: &str,
        args: &[OsString],
        log: &mut Log,
        pb: &dyn Progress,
        progress: fn(&str) -> Option<(u64, u64)>,
    ) -> Result<(f64, f64)> {
        let (t0, cpu0) = (Instant::now(), cpu_seconds());
        let shown: Vec<String> = args
            .iter()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        log.line(&format!("== colmap {cmd} {}", shown.join(" ")))?;
        log.no_model = false;
        let mut c = self.tool.command();
        headless(&mut c);
        let mut child = c
            .arg(cmd)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| self.tool.spawn_error(e))?;
        let (tx, rx) = mpsc::channel::<String>();
        let readers: Vec<_> = [
            Box::new(child.stdout.take().expect("piped")) as Box<dyn std::io::Read + Send>,
            Box::new(child.stderr.take().expect("piped")),
        ]
        .into_iter()
        .map(|r| {
            let tx = tx.clone();
            std::thread::spawn(move || {
                let mut r = BufReader::new(r);
                let mut buf = Vec::new();
                while r.read_until(b'\n', &mut buf).is_ok_and(|n| n > 0) {
                    let s = String::from_utf8_lossy(&buf);
                    for part in s.split('\r') {
                        let part = part.trim_end();
                        if !part.is_empty() && tx.send(part.to_string()).is_err() {
                            return;
                        }
                    }
                    buf.clear();
                }
            })
        })
        .collect();
        drop(tx);
        let mut logged = Ok(());
        for line in rx {
            if let Some((done, of)) = progress(&line) {
                pb.set_length(of.max(done));
                pb.set_position(done);
            }
            if logged.is_ok() {
                logged = log.line(&line);
            }
        }
        for r in readers {
            let _ = r.join();
        }
        let status = child.wait().context("waiting for colmap")?;
        let (secs, cpu) = (t0.elapsed().as_secs_f64(), cpu_seconds() - cpu0);
        logged?;
        log.line(&format!("== {status} after {secs:.1} s"))?;
        if !status.success() {
            bail!(
                "colmap {cmd} failed ({status}); the last lines of its log:\n{}",
                log.tail()
            );
        }
        Ok((secs, cpu))
    }
}

/// Reads "a/b" at the start of `s` (spaces first allowed).
fn ratio(s: &str) -> Option<(u64, u64)> {
    let (a, rest) = s.trim_start().split_once('/')?;
    let b: String = rest.chars().take_while(char::is_ascii_digit).collect();
    Some((a.trim().parse().ok()?, b.parse().ok()?))
}

/// Reads "[done/of" after `needle` in `line`.
fn bracket(line: &str, needle: &str) -> Option<(u64, u64)> {
    let rest = &line[line.find(needle)? + needle.len()..];
    ratio(rest.trim_start().strip_prefix('[')?)
}

/// feature_extractor: "Processed file [i/n]".
pub fn extraction_progress(line: &str) -> Option<(u64, u64)> {
    bracket(line, "Processed file")
}

/// exhaustive_matcher: "Matching block [a/A, b/B]"; sequential_matcher: "Matching image
/// [i/n]".
pub fn matching_progress(line: &str) -> Option<(u64, u64)> {
    if let Some((i, n)) = bracket(line, "Matching image") {
        return Some((i, n));
    }
    let (a, na) = bracket(line, "Matching block")?;
    let (b, nb) = ratio(line.split_once(',')?.1)?;
    Some((a.saturating_sub(1) * nb + b, na * nb))
}

/// mapper: "Registering image #ID (k)" — k images registered so far (its length is set by
/// the caller).
pub fn mapping_progress(line: &str) -> Option<(u64, u64)> {
    let rest = &line[line.find("Registering image #")? + "Registering image #".len()..];
    let inner = rest.split_once('(')?.1.split_once(')')?.0;
    let k: u64 = inner.trim().parse().ok()?;
    Some((k, 0))
}

/// What `model_analyzer` says of a model.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Analysis {
    pub registered: Option<u64>,
    pub points: Option<u64>,
    pub observations: Option<u64>,
    pub mean_track_length: Option<f64>,
    pub mean_reprojection_error_px: Option<f64>,
}

/// Reads `model_analyzer`'s "Key: value" lines (3.8 prints them bare; later releases
/// through glog, behind a prefix).
pub fn parse_analysis(text: &str) -> Analysis {
    let value = |key: &str| -> Option<f64> {
        text.lines().find_map(|l| {
            let rest = &l[l.find(key)? + key.len()..];
            let v: String = rest
                .trim_start()
                .chars()
                .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == 'e' || *c == '-')
                .collect();
            v.parse().ok()
        })
    };
    Analysis {
        registered: value("Registered images:").map(|v| v as u64),
        points: value("Points:").map(|v| v as u64),
        observations: value("Observations:").map(|v| v as u64),
        mean_track_length: value("Mean track length:"),
        mean_reprojection_error_px: value("Mean reprojection error:"),
    }
}

impl Colmap {
    /// `model_analyzer` of `model`, its output logged.
    pub fn analyze(&self, model: &Path, log: &mut Log) -> Result<Analysis> {
        let mut c = self.tool.command();
        headless(&mut c);
        let out = c
            .arg("model_analyzer")
            .arg("--path")
            .arg(model)
            .output()
            .map_err(|e| self.tool.spawn_error(e))?;
        let text = String::from_utf8_lossy(&out.stdout).into_owned()
            + &String::from_utf8_lossy(&out.stderr);
        log.line(&format!(
            "== colmap model_analyzer --path {}",
            model.display()
        ))?;
        for l in text.lines() {
            log.line(l)?;
        }
        // Figures are a report's, not the output's: a failure here costs them only.
        Ok(parse_analysis(&text))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn progress_lines_of_each_stage() {
        assert_eq!(
            extraction_progress("Processed file [12/64]"),
            Some((12, 64))
        );
        assert_eq!(
            extraction_progress("I0101 00:00:00.0 1 feature_extraction.cc:1] Processed file [3/9]"),
            Some((3, 9))
        );
        assert_eq!(
            matching_progress("Matching image [5/40] in 0.1s"),
            Some((5, 40))
        );
        // Block 2 of 3 rows, column 1 of 3: 4 of 9 done.
        assert_eq!(
            matching_progress("Matching block [2/3, 1/3] in 1.2s"),
            Some((4, 9))
        );
        assert_eq!(
            mapping_progress("Registering image #17 (23)"),
            Some((23, 0))
        );
        assert_eq!(extraction_progress("  Name: frame_000001.png"), None);
        assert_eq!(matching_progress("Elapsed time: 0.1 [minutes]"), None);
    }

    #[test]
    fn analyzer_figures_are_read_with_or_without_a_log_prefix() {
        let t38 = "Cameras: 1\nImages: 64\nRegistered images: 64\nPoints: 12345\n\
                   Observations: 60000\nMean track length: 4.86\n\
                   Mean observations per image: 937.5\nMean reprojection error: 0.524px\n";
        let a = parse_analysis(t38);
        assert_eq!(a.registered, Some(64));
        assert_eq!(a.points, Some(12345));
        assert_eq!(a.observations, Some(60000));
        assert_eq!(a.mean_track_length, Some(4.86));
        assert_eq!(a.mean_reprojection_error_px, Some(0.524));
        let glog = "I20250101 12:00:00.1 123 model.cc:1] Registered images: 7\n\
                    I20250101 12:00:00.1 123 model.cc:1] Mean reprojection error: 1.5px";
        let a = parse_analysis(glog);
        assert_eq!(
            (a.registered, a.mean_reprojection_error_px),
            (Some(7), Some(1.5))
        );
        assert_eq!(parse_analysis("nothing"), Analysis::default());
    }
}
