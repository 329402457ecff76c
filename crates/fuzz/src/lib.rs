//! Fuzzing of every file StegoNGP reads, on stable Rust: structure-aware mutation from
//! seeds the project's own writers make ([`seeds`], [`mutate`]), run in process under an
//! allocator that remembers the largest request ([`alloc`]), with every input that ever
//! failed kept as a regression case (`crates/fuzz/regressions/<target>/<case>/`).
//!
//! `cargo test -p stegongp-fuzz` replays the regressions and runs a bounded, seeded number
//! of cases per target; `cargo run --release -p stegongp-fuzz -- --help` runs longer.

pub mod alloc;
pub mod mutate;
pub mod real;
pub mod runner;
pub mod seeds;
pub mod state;
pub mod targets;
pub mod viewer;

/// `../shared/data` beside the repository, when it is there.
pub fn shared_data() -> Option<std::path::PathBuf> {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    p.canonicalize().ok().filter(|p| p.is_dir())
}

/// The regression corpus in the repository.
pub fn regressions_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("regressions")
}
