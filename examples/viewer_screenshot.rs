//! Screenshots of `stegongp view` in headless Chromium: the cover, then the hidden scene
//! after the key file is picked in the page (README's pictures).
//!
//! cargo build --release && cargo run --release --example viewer_screenshot -- \
//!     MODEL KEY OUT_PREFIX [WIDTH HEIGHT]
//!
//! writes OUT_PREFIX-cover.png and OUT_PREFIX-key.png.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;
use testkit::browser::{Browser, find_chromium};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 4 && args.len() != 6 {
        eprintln!("usage: viewer_screenshot MODEL KEY OUT_PREFIX [WIDTH HEIGHT]");
        std::process::exit(2);
    }
    let (model, key, prefix) = (&args[1], Path::new(&args[2]), &args[3]);
    let size: Vec<&str> = args.get(4..6).map_or(vec!["320", "320"], |s| {
        s.iter().map(String::as_str).collect()
    });
    let chromium = find_chromium().expect("Chromium (Debian's chromium package)");
    // examples/ sits beside the program in target/release.
    let exe = std::env::current_exe().expect("own path");
    let bin: PathBuf = exe
        .parent()
        .and_then(Path::parent)
        .expect("target/release")
        .join("stegongp");
    let record =
        std::env::temp_dir().join(format!("viewer_screenshot_{}.json", std::process::id()));
    let mut child = Command::new(&bin)
        .args([
            "view", model, "--port", "0", "--width", size[0], "--height", size[1], "--record",
        ])
        .arg(&record)
        .stdout(Stdio::piped())
        .spawn()
        .expect("starting stegongp view");
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("the URL");
    let url = line
        .trim()
        .strip_prefix("open ")
        .expect("open URL")
        .to_string();
    let mut b = Browser::launch(&chromium, 960, 640);
    b.navigate(&url);
    b.wait_for(
        "window.viewer && viewer.fullFrames >= 1 && !viewer.inflight",
        Duration::from_secs(300),
    );
    b.screenshot(Path::new(&format!("{prefix}-cover.png")));
    let n = b.eval("viewer.fullFrames").as_u64().expect("a count");
    b.set_file(
        "#keyfile",
        &std::fs::canonicalize(key).expect("the key file"),
    );
    b.eval("document.getElementById('unlock').click()");
    b.wait_for(
        &format!("viewer.scene === 'key' && viewer.fullFrames > {n} && !viewer.inflight"),
        Duration::from_secs(300),
    );
    b.screenshot(Path::new(&format!("{prefix}-key.png")));
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_file(&record);
    eprintln!("wrote {prefix}-cover.png and {prefix}-key.png");
}
