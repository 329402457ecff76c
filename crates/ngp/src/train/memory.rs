//! What a CPU trainer holds in memory, checked before it is allocated: a worker count or a
//! table size the machine cannot back must be refused with its reason, not end in the
//! kernel's out-of-memory kill part-way through allocating.

use crate::error::{Error, Result};

/// Most gradient partitions a CPU trainer keeps, each a whole gradient buffer. More
/// partitions than threads buy nothing; 256 covers the largest CPUs.
pub const MAX_WORKERS: usize = 256;

/// Bytes a CPU trainer holds for `n_params` parameters: the weights, Adam's two moments,
/// the per-parameter update counts and the EMA, and one gradient buffer a worker.
pub fn training_bytes(n_params: usize, workers: usize) -> u64 {
    n_params as u64 * 4 * (5 + workers as u64)
}

/// `MemAvailable` of a `/proc/meminfo` text, in bytes.
fn parse_available(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let mut words = line.split_whitespace().skip(1);
    let kib: u64 = words.next()?.parse().ok()?;
    (words.next() == Some("kB")).then_some(kib * 1024)
}

/// The memory the kernel says it can give without swapping; `None` where it does not say
/// (not Linux), and then nothing is checked.
pub fn available_bytes() -> Option<u64> {
    parse_available(&std::fs::read_to_string("/proc/meminfo").ok()?)
}

/// Refuses a CPU training of `n_params` parameters and `workers` gradient buffers that
/// exceeds [`MAX_WORKERS`] or the memory `available` (bytes; `None`: unknown).
pub fn check(n_params: usize, workers: usize, available: Option<u64>) -> Result<()> {
    if workers > MAX_WORKERS {
        return Err(Error::Config(format!(
            "{workers} workers: at most {MAX_WORKERS} (the default is one per core)"
        )));
    }
    let need = training_bytes(n_params, workers);
    match available {
        Some(avail) if need > avail => Err(Error::Config(format!(
            "training {n_params} parameters with {workers} workers needs about {:.1} GB \
             ({} copies of the parameters: weights, two Adam moments, update counts, EMA \
             and a gradient a worker), and {:.1} GB is available: use fewer --workers or a \
             smaller --log2-t",
            need as f64 / 1e9,
            5 + workers,
            avail as f64 / 1e9
        ))),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn meminfo_is_read_in_kib() {
        let text = "MemTotal:       24583164 kB\nMemFree:        23000000 kB\nMemAvailable:   23800000 kB\n";
        assert_eq!(parse_available(text), Some(23_800_000 * 1024));
        assert_eq!(parse_available("MemTotal: 1 kB\n"), None);
        assert_eq!(parse_available("MemAvailable: lots\n"), None);
        assert_eq!(parse_available("MemAvailable: 12 MB\n"), None);
    }

    #[test]
    fn workers_and_memory_are_bounded_before_allocation() {
        // lego's default model: 12.2 M parameters.
        let n = 12_206_480;
        assert_eq!(training_bytes(n, 2), n as u64 * 28);
        assert!(check(n, 2, Some(1 << 30)).is_ok());
        assert!(check(n, 2, None).is_ok());
        let e = check(n, MAX_WORKERS + 1, None).unwrap_err().to_string();
        assert!(e.contains("at most 256"), "{e}");
        let e = check(n, 16, Some(512 << 20)).unwrap_err().to_string();
        assert!(e.contains("GB") && e.contains("--workers"), "{e}");
        // Exactly what is available is allowed.
        assert!(check(n, 3, Some(training_bytes(n, 3))).is_ok());
    }
}
