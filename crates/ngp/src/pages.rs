//! Large tables read and written at random (the hash grid and its fp16 copy, its gradients
//! and Adam moments, the occupancy grid's densities) allocated so that Linux backs them with
//! 2 MiB pages where it can.
//!
//! A sample reads its corners from lines scattered over tens of MiB of table: with 4 KiB
//! pages nearly every one of those reads also misses the TLB, and in a virtual machine a
//! page walk is itself several memory reads. Most kernels give huge pages only to memory a
//! process asks for (`transparent_hugepage` = `madvise`), so these allocations ask before
//! their pages are first touched. Where the kernel refuses or the platform has no such
//! thing, nothing changes but the speed: the values and their order are the same.
//! (benchmarks/engine.md, "Huge pages for the tables")

/// Allocations smaller than this stay as they are: they hold at most a page or two.
const MIN_BYTES: usize = 4 << 20;

#[cfg(target_os = "linux")]
const HUGE_PAGE: usize = 2 << 20;

/// `Vec::with_capacity(n)` whose storage, when it is large, is advised to use huge pages
/// before anything is written to it (fill it with `extend` or `push`).
pub fn with_capacity<T>(n: usize) -> Vec<T> {
    advised(Vec::with_capacity(n))
}

/// `vec![T::default(); n]` on huge pages where the kernel allows. For the numbers the
/// tables hold, whose default is all zero bits, the allocator maps a large block without
/// writing it, so the advice comes before any page is touched and nothing is written now
/// that training would not write anyway.
pub fn zeroed<T: Clone + Default>(n: usize) -> Vec<T> {
    advised(vec![T::default(); n])
}

/// `v`, its whole allocation advised.
fn advised<T>(v: Vec<T>) -> Vec<T> {
    advise(
        v.as_ptr() as usize,
        v.capacity().saturating_mul(std::mem::size_of::<T>()),
    );
    v
}

#[cfg(target_os = "linux")]
fn advise(start: usize, bytes: usize) {
    if bytes < MIN_BYTES {
        return;
    }
    // Only whole 2 MiB pages inside the allocation can be huge.
    let first = start.next_multiple_of(HUGE_PAGE);
    let end = (start + bytes) / HUGE_PAGE * HUGE_PAGE;
    if end <= first {
        return;
    }
    // SAFETY: MADV_HUGEPAGE only changes how the kernel backs this range of our own live
    // allocation, never its contents or its mapping. A refusal (no THP in this kernel, THP
    // off) leaves ordinary pages, which is what there was.
    unsafe {
        libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
    }
}

#[cfg(not(target_os = "linux"))]
fn advise(_start: usize, _bytes: usize) {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_is_the_vec_macro() {
        for n in [0, 1, 1000, (MIN_BYTES / 4) + 12_345] {
            assert_eq!(zeroed::<f32>(n), vec![0.0f32; n]);
            assert_eq!(zeroed::<u32>(n), vec![0u32; n]);
        }
        let v: Vec<u16> = with_capacity(MIN_BYTES);
        assert!(v.is_empty() && v.capacity() >= MIN_BYTES);
    }

    /// The AnonHugePages of the mapping holding `addr`, from /proc/self/smaps.
    #[cfg(target_os = "linux")]
    fn huge_kb_at(addr: usize) -> usize {
        let smaps = std::fs::read_to_string("/proc/self/smaps").expect("/proc/self/smaps");
        let mut inside = false;
        for line in smaps.lines() {
            let head = line.split_whitespace().next().unwrap_or("");
            if let Some((a, b)) = head.split_once('-')
                && let (Ok(a), Ok(b)) = (usize::from_str_radix(a, 16), usize::from_str_radix(b, 16))
            {
                inside = a <= addr && addr < b;
                continue;
            }
            if inside && let Some(rest) = line.strip_prefix("AnonHugePages:") {
                return rest
                    .trim()
                    .trim_end_matches("kB")
                    .trim()
                    .parse()
                    .expect("a size in kB");
            }
        }
        panic!("no mapping holds {addr:#x}");
    }

    /// On Linux with THP in `always` or `madvise` mode, a large table filled after the
    /// advice is on huge pages: what the module is for. Skips where the kernel gives none
    /// to anyone.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_large_table_lands_on_huge_pages() {
        let mode = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled")
            .unwrap_or_default();
        if !(mode.contains("[always]") || mode.contains("[madvise]")) {
            eprintln!(
                "skipping: transparent huge pages are off here ({})",
                mode.trim()
            );
            return;
        }
        // A process the kernel was told to give none (prctl PR_SET_THP_DISABLE) says so.
        let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
        if status
            .lines()
            .any(|l| l.replace(char::is_whitespace, "") == "THP_enabled:0")
        {
            eprintln!("skipping: transparent huge pages are disabled for this process");
            return;
        }
        let mut v = zeroed::<f32>(16 << 20); // 64 MiB
        v.fill(1.0);
        // With `defrag` at its default the kernel compacts memory for advised ranges at
        // fault time, so a 64 MiB table gets huge pages unless the advice was not given.
        let kb = huge_kb_at(v.as_ptr() as usize + (32 << 20));
        assert!(
            kb >= 2048,
            "a 64 MiB table advised before it was filled got no huge page ({kb} kB)"
        );
    }
}
