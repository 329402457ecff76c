//! What StegoNGP's tests share, so that each test file holds its own assertions only:
//! generated scenes loaded as datasets ([`scenes`]), keys drawn from a seed ([`keys`]), the
//! `stegongp` program run as a user runs it ([`cli`]), small models trained through the
//! recipe ([`models`]), comparisons of two backends' weights ([`compare`]), and the geometry
//! that writing a COLMAP capture and comparing poses need ([`geometry`]), cameras made wrong on
//! purpose for camera refinement ([`cameras`]), a capture
//! photographed from known cameras for `process` ([`capture`]), a headless Chromium driven over
//! the DevTools protocol ([`browser`]), a real one-node Slurm cluster ([`slurm`]), and the golden files of what a user sees
//! ([`golden`]).
//!
//! A dev-dependency of the workspace's root package (its integration tests); it sits above
//! every library crate, so their own unit tests cannot use it.

pub mod browser;
pub mod cameras;
pub mod capture;
pub mod cli;
pub mod compare;
pub mod geometry;
pub mod golden;
pub mod keys;
pub mod models;
pub mod scenes;
pub mod slurm;

/// A test's outside requirement is missing (a package, a program): with `CI=true` that is a
/// failure, since `.ci/run` installs it; elsewhere the test says what it skips and why.
/// The caller returns after it.
pub fn missing(what: &str, install: &str) {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    assert!(!ci, "CI=true and no {what}: {install}");
    eprintln!("skipping: no {what} ({install})");
}
