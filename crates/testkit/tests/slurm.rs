//! The one-node Slurm cluster the experiment tests submit to: it starts, runs an array and a
//! job that waits for it, cancels a running job, and leaves no process behind when dropped.
//! Without Slurm and munge (or as a user other than root) these skip; with `CI=true` they
//! fail. The two tests run at once, so two clusters share this machine meanwhile.

use std::fs;
use std::path::Path;
use std::time::{Duration, Instant};
use stegongp_testkit::slurm::SlurmCluster;

/// Whether a process is alive (a zombie, exited but not yet reaped, is not).
fn alive(pid: u32) -> bool {
    fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|stat| {
        let after = stat.rsplit_once(')').map_or("", |(_, rest)| rest);
        after.split_whitespace().next() != Some("Z")
    })
}

/// Polls `done` every 100 ms for up to `secs` seconds; whether it came true.
fn eventually(secs: u64, mut done: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while Instant::now() < deadline {
        if done() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    done()
}

fn path(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 temporary path")
}

#[test]
fn an_array_and_a_job_after_it_run() {
    let Some(cluster) = SlurmCluster::start_or_skip("an_array_and_a_job_after_it_run") else {
        return;
    };
    eprintln!(
        "Slurm started in {:.2} s: node {} with {} CPUs",
        cluster.startup_time().as_secs_f64(),
        cluster.node(),
        cluster.cpus()
    );
    let out = tempfile::tempdir().unwrap();
    let o = path(out.path());
    let t0 = Instant::now();
    let array = cluster
        .sbatch(&[
            "--array=0-3",
            &format!("--output={o}/%A_%a.log"),
            "--wrap",
            &format!("echo $SLURM_ARRAY_TASK_ID > {o}/$SLURM_ARRAY_TASK_ID"),
        ])
        .unwrap();
    // It lists what the array wrote, so it shows that it ran after all four.
    let after = cluster
        .sbatch(&[
            &format!("--dependency=afterany:{array}"),
            &format!("--output={o}/after.log"),
            "--wrap",
            &format!("ls {o} | grep -x '[0-9]' | tr '\\n' ' ' > {o}/after"),
        ])
        .unwrap();
    cluster.wait_idle(Duration::from_secs(45)).unwrap();
    let elapsed = t0.elapsed().as_secs_f64();
    for task in 0..4 {
        let written = fs::read_to_string(out.path().join(task.to_string()));
        assert_eq!(
            written.as_deref().ok().map(str::trim),
            Some(task.to_string().as_str()),
            "array {array} task {task}\n{}",
            cluster.logs()
        );
    }
    let listed = fs::read_to_string(out.path().join("after"));
    assert_eq!(
        listed.as_deref().ok().map(str::trim),
        Some("0 1 2 3"),
        "job {after}, after the array\n{}",
        cluster.logs()
    );
    eprintln!(
        "4 array tasks and 1 job after them: {elapsed:.2} s on {} CPUs",
        cluster.cpus()
    );

    // The scheduler's cost per job: a chain of trivial jobs, each waiting for the last.
    let t0 = Instant::now();
    let mut last = cluster
        .sbatch(&["--output=/dev/null", "--wrap", "true"])
        .unwrap();
    for _ in 1..4 {
        let dep = format!("--dependency=afterok:{last}");
        last = cluster
            .sbatch(&[&dep, "--output=/dev/null", "--wrap", "true"])
            .unwrap();
    }
    cluster.wait_idle(Duration::from_secs(30)).unwrap();
    eprintln!(
        "a chain of 4 empty jobs: {:.2} s per job",
        t0.elapsed().as_secs_f64() / 4.0
    );
}

/// A job that writes its shell's pid and then becomes `sleep 300`; the pid, once it runs.
fn start_sleeper(cluster: &SlurmCluster, dir: &Path, name: &str) -> (String, u32) {
    let pid_file = dir.join(name);
    let id = cluster
        .sbatch(&[
            "--output=/dev/null",
            "--wrap",
            &format!("echo $$ > {}; exec sleep 300", path(&pid_file)),
        ])
        .unwrap();
    let running = eventually(30, || {
        pid_file.exists() && cluster.job_state(&id).unwrap().as_deref() == Some("RUNNING")
    });
    assert!(running, "job {id} never ran\n{}", cluster.logs());
    let pid = fs::read_to_string(&pid_file)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(alive(pid), "job {id}'s sleep {pid} is not running");
    (id, pid)
}

#[test]
fn scancel_stops_a_running_job_and_drop_stops_everything() {
    let test = "scancel_stops_a_running_job_and_drop_stops_everything";
    let Some(cluster) = SlurmCluster::start_or_skip(test) else {
        return;
    };
    let out = tempfile::tempdir().unwrap();
    let (id, pid) = start_sleeper(&cluster, out.path(), "first");
    let t0 = Instant::now();
    let scancel = cluster.command("scancel").arg(&id).output().unwrap();
    assert!(scancel.status.success(), "scancel {id}: {scancel:?}");
    let gone = eventually(30, || {
        cluster.job_state(&id).unwrap().is_none() && !alive(pid)
    });
    assert!(
        gone,
        "job {id} (pid {pid}) still there after scancel\n{}",
        cluster.logs()
    );
    eprintln!(
        "scancel to the job gone: {:.2} s",
        t0.elapsed().as_secs_f64()
    );

    // Dropped with a job running: the job is cancelled and no daemon outlives the cluster.
    let (_, pid) = start_sleeper(&cluster, out.path(), "second");
    let daemons = cluster.pids();
    assert_eq!(daemons.len(), 3, "{daemons:?}");
    let dir = cluster.dir().to_path_buf();
    let t0 = Instant::now();
    drop(cluster);
    eprintln!("stopping the cluster: {:.2} s", t0.elapsed().as_secs_f64());
    for (name, daemon) in daemons {
        assert!(!alive(daemon), "{name} (pid {daemon}) outlived the cluster");
    }
    assert!(
        !alive(pid),
        "the running job's sleep (pid {pid}) outlived the cluster"
    );
    assert!(!dir.exists(), "{} left behind", dir.display());
}
