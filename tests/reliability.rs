//! Faults around the files the program writes: a full disk, a missing folder and a kill -9
//! at any moment leave the old file or the complete new one; two runs into one output
//! folder do not interleave.

use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use stegongp::ngp::model::Model;
use testkit::cli::{bin, fails_naming, run_ok, stegongp};

/// The names in `dir`, sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// A scene small enough that a few training steps take a fraction of a second.
fn tiny_scene(dir: &Path) {
    testkit::cli::synth(dir, "object", 24, 8);
}

/// `stegongp train` of [`tiny_scene`] into `out`: a 2^`log2_t`-entry, 8-level grid, a few
/// steps.
fn train_cmd(scene: &Path, out: &Path, log2_t: u32, seed: u32) -> Command {
    let mut c = Command::new(bin());
    c.arg("train")
        .arg(scene)
        .arg("--out")
        .arg(out)
        .args(["--steps", "3", "--batch", "1024", "--levels", "8"])
        .args(["--log2-t", &log2_t.to_string(), "--seed", &seed.to_string()])
        .args(["--occupancy-fraction", "0.01"]);
    c
}

/// `cmd` with its output thrown away: the runs whose message nobody reads.
fn quiet(mut cmd: Command) -> Command {
    cmd.stdout(Stdio::null()).stderr(Stdio::null());
    cmd
}

/// A full disk, as a file-size limit makes one: `train` writing a model over an existing one
/// under RLIMIT_FSIZE (SIGXFSZ ignored, so the write fails with EFBIG instead of killing the
/// program) fails with a message naming the model, the old model byte-identical and no
/// temporary file beside it.
#[test]
fn a_full_disk_leaves_the_old_model() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    tiny_scene(&scene);
    let out_dir = d.path().join("models");
    std::fs::create_dir(&out_dir).unwrap();
    let model = out_dir.join("m.ingp");
    let status = quiet(train_cmd(&scene, &model, 10, 1)).status().unwrap();
    assert!(status.success());
    let old = std::fs::read(&model).unwrap();
    assert!(old.len() > 32 * 1024, "the limit must cut the model");
    let mut cmd = train_cmd(&scene, &model, 10, 2);
    // SAFETY: between fork and exec only async-signal-safe calls (setrlimit, signal).
    unsafe {
        cmd.pre_exec(|| {
            let lim = libc::rlimit {
                rlim_cur: 16 * 1024,
                rlim_max: 16 * 1024,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            Ok(())
        });
    }
    let out = cmd.output().unwrap();
    fails_naming(&out, &[model.to_str().unwrap(), "too large"]);
    assert_eq!(std::fs::read(&model).unwrap(), old, "the old model changed");
    assert_eq!(names(&out_dir), ["m.ingp"]);
}

/// A missing folder: refused with its name, nothing created.
#[test]
fn a_missing_folder_is_refused_by_name() {
    let d = tempfile::tempdir().unwrap();
    let key = d.path().join("no_such_dir").join("k.json");
    fails_naming(
        &stegongp(&["keygen", "--out", key.to_str().unwrap()]),
        &["no_such_dir"],
    );
    let model = d.path().join("nowhere").join("m.ingp");
    fails_naming(
        &stegongp(&["train", "scene", "--out", model.to_str().unwrap()]),
        &["nowhere"],
    );
    assert!(names(d.path()).is_empty());
}

/// A read-only folder: refused naming the file, the old file kept, nothing left beside it.
/// Root writes into read-only folders, so as root (CI) the program runs as `nobody`, for
/// whom the folder is read-only too.
#[test]
fn a_read_only_folder_is_refused_by_name() {
    use std::os::unix::fs::PermissionsExt;
    let d = tempfile::tempdir().unwrap();
    // Traversable by `nobody` (a temporary folder is its owner's alone).
    std::fs::set_permissions(d.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let key = d.path().join("k.json");
    run_ok(&["keygen", "--out", key.to_str().unwrap()]);
    let old = std::fs::read(&key).unwrap();
    std::fs::set_permissions(d.path(), std::fs::Permissions::from_mode(0o555)).unwrap();
    let mut cmd = Command::new(bin());
    cmd.args(["keygen", "--force", "--out", key.to_str().unwrap()]);
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    if root {
        const NOBODY: libc::uid_t = 65534;
        // SAFETY: between fork and exec only async-signal-safe calls (setgroups, setgid,
        // setuid).
        unsafe {
            cmd.pre_exec(|| {
                if libc::setgroups(0, std::ptr::null()) != 0
                    || libc::setgid(NOBODY) != 0
                    || libc::setuid(NOBODY) != 0
                {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    }
    let out = cmd.output();
    std::fs::set_permissions(d.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let out = match out {
        Ok(o) => o,
        // No privilege to drop to, or the program out of `nobody`'s reach.
        Err(e) if root => {
            eprintln!("skipped: cannot run the program as nobody ({e})");
            return;
        }
        Err(e) => panic!("{e}"),
    };
    fails_naming(&out, &["k.json", "Permission denied"]);
    assert_eq!(std::fs::read(&key).unwrap(), old);
    assert_eq!(names(d.path()), ["k.json"]);
}

/// When a trial kills its run.
#[derive(Clone, Copy, Debug)]
enum Moment {
    /// This long after the start.
    After(Duration),
    /// This long after the temporary file beside the output appears: while the new file is
    /// written, synced and renamed, a window of a millisecond or two that delays from the
    /// start seldom hit.
    AfterTemp(Duration),
}

/// How killed runs left their output.
#[derive(Default, Debug)]
struct Outcomes {
    /// The old file, byte for byte.
    old: u32,
    /// A complete new file that loads.
    new: u32,
    /// Of those, runs that had ended before the kill.
    ended_first: u32,
    /// Runs killed while their temporary file was there (mid-write).
    killed_mid_write: u32,
    /// Temporary files killed runs left beside the output (never under its name).
    temp_left: u32,
}

/// Uniform numbers in [0, 1) from a fixed seed (splitmix64): reproducible kill moments
/// without a random-number crate.
struct Uniform(u64);

impl Uniform {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        (z ^ (z >> 31)) as f64 / (u64::MAX as f64 + 1.0)
    }
}

/// Runs `cmd` once for each of `moments` over `out` restored to `old`, killing it with
/// SIGKILL at that moment; each time the output must be `old` byte for byte or a new file
/// that `loads` accepts.
fn kill_trials(
    moments: &[Moment],
    out: &Path,
    old: &[u8],
    mut cmd: impl FnMut() -> Command,
    loads: impl Fn(&Path) -> bool,
) -> Outcomes {
    let dir = out.parent().unwrap();
    let name = out.file_name().unwrap().to_string_lossy().into_owned();
    let is_temp = |n: &str| n.starts_with(&format!(".{name}.")) && n.ends_with(".tmp");
    let mut o = Outcomes::default();
    for (t, &moment) in moments.iter().enumerate() {
        std::fs::write(out, old).unwrap();
        let mut child = cmd().spawn().unwrap();
        match moment {
            Moment::After(d) => std::thread::sleep(d),
            Moment::AfterTemp(d) => {
                while child.try_wait().unwrap().is_none() && !names(dir).iter().any(|n| is_temp(n))
                {
                    std::hint::spin_loop();
                }
                std::thread::sleep(d);
            }
        }
        if child.try_wait().unwrap().is_some() {
            o.ended_first += 1;
        } else if names(dir).iter().any(|n| is_temp(n)) {
            o.killed_mid_write += 1;
        }
        // SIGKILL: the program gets no chance to clean up.
        let _ = child.kill();
        child.wait().unwrap();
        if std::fs::read(out).unwrap() == old {
            o.old += 1;
        } else {
            assert!(
                loads(out),
                "trial {t} ({moment:?}): {} is neither the old file nor a loadable new one",
                out.display()
            );
            o.new += 1;
        }
        for n in names(dir) {
            if is_temp(&n) {
                o.temp_left += 1;
                std::fs::remove_file(dir.join(n)).unwrap();
            }
        }
    }
    o
}

/// 20 kill moments spread over [0.2, 1.1] × `span` from the start, and 20 within `window`
/// of the temporary file's appearance.
fn moments(span: Duration, window: Duration, seed: u64) -> Vec<Moment> {
    let mut u = Uniform(seed);
    let mut m: Vec<Moment> = (0..20)
        .map(|_| Moment::After(span.mul_f64(0.2 + 0.9 * u.next())))
        .collect();
    m.extend((0..20).map(|_| Moment::AfterTemp(window.mul_f64(u.next()))));
    m
}

/// kill -9 of `train` and `keygen` at 40 moments each over an existing output, half of them
/// while the new file is being written: every time the old file or a complete new one (which
/// loads), never a torn one. `cargo test --release --test reliability kill -- --nocapture`
/// prints the counts.
#[test]
fn a_kill_at_any_moment_leaves_the_old_file_or_the_new_one() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    tiny_scene(&scene);
    let out_dir = d.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();

    let model = out_dir.join("m.ingp");
    // A 2^16 table: a 1.5 MB model, whose write takes long enough to be killed in.
    let run_train = |seed: u32| quiet(train_cmd(&scene, &model, 16, seed));
    assert!(run_train(1).status().unwrap().success());
    let old = std::fs::read(&model).unwrap();
    // One whole run sets the span the kills are spread over.
    let t0 = Instant::now();
    assert!(run_train(2).status().unwrap().success());
    let span = t0.elapsed();
    assert_ne!(std::fs::read(&model).unwrap(), old);
    let mut seed = 2;
    let train = kill_trials(
        &moments(span, Duration::from_millis(3), 1),
        &model,
        &old,
        || {
            seed += 1;
            run_train(seed)
        },
        |p| Model::load(p).is_ok(),
    );
    println!("train ({span:?} a run): {train:?}");

    let key = out_dir.join("k.json");
    run_ok(&["keygen", "--out", key.to_str().unwrap()]);
    let old_key = std::fs::read(&key).unwrap();
    let keygen = || {
        let mut c = Command::new(bin());
        c.args(["keygen", "--force", "--out"]).arg(&key);
        quiet(c)
    };
    let t0 = Instant::now();
    assert!(keygen().status().unwrap().success());
    let span = t0.elapsed();
    let keys = kill_trials(
        &moments(span, Duration::from_micros(300), 2),
        &key,
        &old_key,
        keygen,
        |p| stegongp::stego::load_key(p).is_ok(),
    );
    println!("keygen ({span:?} a run): {keys:?}");
    assert_eq!(train.old + train.new, 40);
    assert_eq!(keys.old + keys.new, 40);
}

/// A second `experiment` (or `demo`) into a folder another run holds is refused at once,
/// naming the folder, and writes nothing there; once the lock is let go it runs.
#[test]
fn a_second_run_into_a_held_folder_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("exp");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "untouched").unwrap();
    // The lock a first run takes: flock on OUT/.lock.
    let lock = std::fs::File::create(out.join(".lock")).unwrap();
    lock.try_lock().unwrap();
    let o = out.to_str().unwrap();
    for args in [
        vec!["experiment", "key-strength", "--out", o],
        vec!["demo", "--out", o],
    ] {
        let t0 = Instant::now();
        let r = stegongp(&args);
        fails_naming(&r, &[o, "another stegongp run"]);
        assert!(t0.elapsed() < Duration::from_secs(10), "{args:?} waited");
        assert_eq!(names(&out), [".lock", "keep.txt"], "{args:?} wrote");
        assert_eq!(std::fs::read(out.join("keep.txt")).unwrap(), b"untouched");
    }
    drop(lock);
    // A small grid: key-strength of the default one takes seconds.
    run_ok(&[
        "experiment",
        "key-strength",
        "--out",
        o,
        "--levels",
        "4",
        "--log2-t",
        "10",
    ]);
    assert!(out.join("key-strength/report.json").exists());
}
