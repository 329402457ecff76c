//! A real one-node Slurm cluster on this machine: munged, slurmctld and slurmd started from a
//! configuration written into a temporary folder, for the tests that submit work to Slurm as
//! a user's cluster runs it (Debian's `slurm-wlm` 22.05 and `munge`, as root, as CI runs).
//!
//! Nothing outside the folder is read or written: munged gets its key, socket, pid and seed
//! files by option, Slurm gets the socket through `AuthInfo`, its ports are free ones, and
//! every command finds the configuration through `SLURM_CONF` ([`SlurmCluster::env`],
//! [`SlurmCluster::command`]). So a system Slurm, or a second cluster started by another
//! test at the same time, is not disturbed. The daemons run in the foreground as children of
//! the test; dropping the cluster cancels its jobs and stops them all (never hold one in a
//! `static`: statics are not dropped, and the daemons would outlive the tests).

use std::fmt::Write as _;
use std::fs;
use std::io::Read;
use std::net::TcpListener;
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};
use tempfile::TempDir;

/// How long the daemons may take to bring the node to idle (about 1.2 s on this 2-core
/// machine; the issue expected about 20 s).
const START_TIMEOUT: Duration = Duration::from_secs(60);
/// How long a stopped daemon may take to exit on SIGTERM before it gets SIGKILL.
const STOP_TIMEOUT: Duration = Duration::from_secs(10);
/// How long dropping the cluster waits for its cancelled jobs to leave the queue.
const CANCEL_TIMEOUT: Duration = Duration::from_secs(15);
/// The cluster's one partition, the default one.
pub const PARTITION: &str = "main";

/// The daemons, in the order they start (and the reverse of the order they stop).
const DAEMONS: [&str; 3] = ["munged", "slurmctld", "slurmd"];
/// The client commands the cluster itself and the tests use.
const CLIENTS: [&str; 5] = ["sbatch", "squeue", "sinfo", "scancel", "scontrol"];
/// What installs them on Debian (and in `.ci/run`).
const INSTALL: &str = "apt-get install slurm-wlm munge";

/// A running one-node cluster; see the module's documentation.
pub struct SlurmCluster {
    dir: TempDir,
    node: String,
    cpus: usize,
    /// In start order; stopped in reverse.
    daemons: Vec<(&'static str, Child)>,
    startup: Duration,
}

impl SlurmCluster {
    /// Starts a cluster and waits until its node is idle. `Ok(None)`, with a message on
    /// standard error, when this machine cannot run one (the packages are missing, or the
    /// test is not root); an error, with the end of the daemons' logs, when it can and the
    /// cluster did not come up.
    pub fn start() -> Result<Option<SlurmCluster>, String> {
        if let Some(why) = unavailable() {
            eprintln!("no Slurm cluster: {why}");
            return Ok(None);
        }
        let t0 = Instant::now();
        let dir = tempfile::Builder::new()
            .prefix("slurm-")
            .tempdir()
            .map_err(|e| format!("a temporary folder for the Slurm cluster: {e}"))?;
        let (node, cpus) = (node_name()?, available_cpus());
        write_config(dir.path(), &node, cpus)?;
        let mut cluster = SlurmCluster {
            dir,
            node,
            cpus,
            daemons: Vec::new(),
            startup: Duration::ZERO,
        };
        // On an error the cluster is dropped here, which stops what did start.
        cluster.launch()?;
        cluster.startup = t0.elapsed();
        Ok(Some(cluster))
    }

    /// [`start`](Self::start) for a test named `test`: `None` (the test returns) with
    /// "skipping TEST: ..." when this machine cannot run a cluster, except with `CI=true`,
    /// where `.ci/run` installs the packages and runs as root, so that is a failure (a
    /// panic), as is a cluster that did not come up.
    pub fn start_or_skip(test: &str) -> Option<SlurmCluster> {
        if let Some(why) = unavailable() {
            let ci = std::env::var("CI").is_ok_and(|v| v == "true");
            assert!(!ci, "CI=true and {test} cannot start Slurm: {why}");
            eprintln!("skipping {test}: {why}");
            return None;
        }
        match Self::start() {
            Ok(cluster) => cluster,
            Err(e) => panic!("{test}: the Slurm cluster did not start: {e}"),
        }
    }

    /// The environment every Slurm command needs to reach this cluster: `SLURM_CONF`.
    pub fn env(&self) -> Vec<(String, String)> {
        vec![(
            "SLURM_CONF".to_string(),
            self.conf().to_string_lossy().into_owned(),
        )]
    }

    /// `prog` (found on `PATH` or in the sbin folders) set up to reach this cluster: the
    /// [`env`](Self::env), and without the `SLURM_*` variables this process inherited (a
    /// test run inside a job of another cluster would otherwise aim at that job). Any
    /// program: `command("bash").arg("submit.sh")` submits through a script.
    pub fn command(&self, prog: &str) -> Command {
        let mut cmd = Command::new(find_program(prog).unwrap_or_else(|| PathBuf::from(prog)));
        for (key, _) in std::env::vars_os() {
            if key.to_string_lossy().starts_with("SLURM_") {
                cmd.env_remove(key);
            }
        }
        cmd.envs(self.env());
        cmd
    }

    /// Submits `sbatch --parsable ARGS`; the job's id (an array's id for `--array`).
    pub fn sbatch(&self, args: &[&str]) -> Result<String, String> {
        let out = self.run("sbatch", &[&["--parsable"], args].concat())?;
        // --parsable prints "ID" or, on a federation, "ID;CLUSTER".
        let id = out.trim().split(';').next().unwrap_or_default();
        if id.is_empty() {
            return Err(format!("sbatch {args:?} printed no job id"));
        }
        Ok(id.to_string())
    }

    /// The jobs in the queue (pending, running or completing), as squeue names them
    /// (`12`, `10_3`, `10_[4-7]`).
    pub fn jobs(&self) -> Result<Vec<String>, String> {
        let out = self.run("squeue", &["--noheader", "--format=%i"])?;
        Ok(out.split_whitespace().map(str::to_string).collect())
    }

    /// A job's state as squeue prints it (`PENDING`, `RUNNING`, `SUSPENDED`, `COMPLETING`),
    /// or `None` once it has left the queue (finished, failed or cancelled). An array's id
    /// gives a line per task (or per range of pending tasks).
    pub fn job_state(&self, id: &str) -> Result<Option<String>, String> {
        let mut cmd = self.command("squeue");
        cmd.args(["--noheader", "--format=%T", "--jobs", id]);
        let out = output(&mut cmd, "squeue")?;
        let err = String::from_utf8_lossy(&out.stderr);
        // A job that has left slurmctld's records (MinJobAge after it ended) is an error
        // to squeue --jobs; one that ended more recently prints nothing.
        if !out.status.success() {
            if err.contains("Invalid job id") {
                return Ok(None);
            }
            return Err(format!(
                "squeue --jobs {id} failed ({}): {}",
                out.status,
                err.trim()
            ));
        }
        let text = String::from_utf8_lossy(&out.stdout).trim().to_string();
        Ok((!text.is_empty()).then_some(text))
    }

    /// Waits until the queue is empty (every job finished, failed or cancelled).
    pub fn wait_idle(&self, timeout: Duration) -> Result<(), String> {
        let deadline = Instant::now() + timeout;
        loop {
            let jobs = self.jobs()?;
            if jobs.is_empty() {
                return Ok(());
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "jobs still queued after {:.0} s: {}\n{}",
                    timeout.as_secs_f64(),
                    jobs.join(" "),
                    self.logs()
                ));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// The end of each daemon's log, for a failure's message.
    pub fn logs(&self) -> String {
        let mut text = String::new();
        for name in [
            "slurmctld.log",
            "slurmd.log",
            "munged.out",
            "slurmctld.out",
            "slurmd.out",
        ] {
            let Ok(log) = fs::read_to_string(self.dir.path().join("log").join(name)) else {
                continue;
            };
            let lines: Vec<&str> = log.lines().collect();
            let tail = &lines[lines.len().saturating_sub(20)..];
            if !tail.is_empty() {
                let _ = writeln!(text, "--- {name} (last {} lines)", tail.len());
                text.extend(tail.iter().map(|l| format!("{l}\n")));
            }
        }
        text
    }

    /// The cluster's folder (configuration, state, logs); it is deleted with the cluster.
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// The node's name (this host's short name).
    pub fn node(&self) -> &str {
        &self.node
    }

    /// The CPUs the node offers (this process's available parallelism): as many 1-CPU jobs
    /// run at once.
    pub fn cpus(&self) -> usize {
        self.cpus
    }

    /// How long [`start`](Self::start) took, from writing the configuration to an idle node.
    pub fn startup_time(&self) -> Duration {
        self.startup
    }

    /// The daemons (`munged`, `slurmctld`, `slurmd`) and their process ids, so that a test
    /// can check that none outlives the cluster.
    pub fn pids(&self) -> Vec<(&'static str, u32)> {
        self.daemons.iter().map(|(n, c)| (*n, c.id())).collect()
    }

    fn conf(&self) -> PathBuf {
        self.dir.path().join("slurm.conf")
    }

    /// Runs a Slurm command that must succeed; its standard output.
    fn run(&self, prog: &str, args: &[&str]) -> Result<String, String> {
        let mut cmd = self.command(prog);
        cmd.args(args);
        let out = output(&mut cmd, prog)?;
        if !out.status.success() {
            return Err(format!(
                "{prog} {args:?} failed ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    }

    /// Starts the daemons one after the other, each once the one it needs answers.
    fn launch(&mut self) -> Result<(), String> {
        let deadline = Instant::now() + START_TIMEOUT;
        let d = self.dir.path().to_path_buf();
        let arg = |opt: &str, rel: &str| format!("{opt}={}", d.join(rel).display());
        let munged = [
            "--foreground".to_string(),
            arg("--key-file", "munge/munge.key"),
            arg("--seed-file", "munge/munged.seed"),
            arg("--socket", "run/munge.sock"),
            arg("--pid-file", "run/munged.pid"),
            // In the foreground munged logs to standard error (log/munged.out); named all
            // the same, so that no path of its points outside the folder.
            arg("--log-file", "log/munged.log"),
        ];
        self.spawn("munged", &munged)?;
        let socket = d.join("run/munge.sock");
        self.wait_for(deadline, "munged's socket", |_| socket.exists())?;
        self.spawn("slurmctld", &["-D".to_string()])?;
        self.wait_for(deadline, "slurmctld to answer", |c| {
            c.node_state().is_some()
        })?;
        let node = self.node.clone();
        self.spawn("slurmd", &["-D".to_string(), "-N".to_string(), node])?;
        self.wait_for(deadline, "the node to be idle", |c| {
            c.node_state().as_deref() == Some("idle")
        })
    }

    /// The node's state as sinfo prints it (`idle`, `unk*`, ...), `None` while slurmctld
    /// does not answer.
    fn node_state(&self) -> Option<String> {
        let out = self
            .run("sinfo", &["--noheader", "--Node", "--format=%t"])
            .ok()?;
        let state = out.trim();
        (!state.is_empty()).then(|| state.to_string())
    }

    /// Starts `name` in the foreground, its standard output and error in `log/NAME.out`.
    fn spawn(&mut self, name: &'static str, args: &[String]) -> Result<(), String> {
        let prog = find_program(name).ok_or_else(|| format!("no {name} ({INSTALL})"))?;
        let out_path = self.dir.path().join("log").join(format!("{name}.out"));
        let out = fs::File::create(&out_path)
            .map_err(|e| format!("creating {}: {e}", out_path.display()))?;
        let err = out
            .try_clone()
            .map_err(|e| format!("{}: {e}", out_path.display()))?;
        let mut cmd = self.command(&prog.to_string_lossy());
        cmd.args(args)
            .current_dir(self.dir.path())
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err);
        let child = cmd
            .spawn()
            .map_err(|e| format!("starting {}: {e}", prog.display()))?;
        self.daemons.push((name, child));
        Ok(())
    }

    /// Polls `ready` until it holds; an error naming `what` when a daemon exits first or
    /// the deadline passes.
    fn wait_for(
        &mut self,
        deadline: Instant,
        what: &str,
        ready: impl Fn(&SlurmCluster) -> bool,
    ) -> Result<(), String> {
        loop {
            if ready(self) {
                return Ok(());
            }
            let exited = self.daemons.iter_mut().find_map(|(name, child)| {
                child
                    .try_wait()
                    .ok()
                    .flatten()
                    .map(|status| (*name, status))
            });
            if let Some((name, status)) = exited {
                return Err(format!(
                    "{name} exited ({status}) while waiting for {what}\n{}",
                    self.logs()
                ));
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "still waiting for {what} after {} s\n{}",
                    START_TIMEOUT.as_secs(),
                    self.logs()
                ));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Cancels every job, stops the daemons (SIGTERM, then SIGKILL), and kills whatever is
    /// left that belongs to the cluster (a job step slurmd no longer watches).
    fn stop(&mut self) {
        let ctld_up = self
            .daemons
            .iter_mut()
            .any(|(name, child)| *name == "slurmctld" && matches!(child.try_wait(), Ok(None)));
        if ctld_up {
            let _ = self.run("scancel", &["--partition", PARTITION]);
            if let Err(e) = self.wait_idle(CANCEL_TIMEOUT) {
                eprintln!("stopping the Slurm cluster: {e}");
            }
        }
        for (name, child) in self.daemons.iter_mut().rev() {
            terminate(name, child);
        }
        for pid in leftovers(self.dir.path()) {
            eprintln!("stopping the Slurm cluster: killing leftover process {pid}");
            // SAFETY: kill(2) with a pid read from /proc and a valid signal.
            unsafe { libc::kill(pid, libc::SIGKILL) };
        }
    }
}

impl Drop for SlurmCluster {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Why this machine cannot run a cluster, if it cannot.
fn unavailable() -> Option<String> {
    let missing: Vec<&str> = DAEMONS
        .iter()
        .chain(&CLIENTS)
        .filter(|p| find_program(p).is_none())
        .copied()
        .collect();
    if !missing.is_empty() {
        return Some(format!("no {} ({INSTALL})", missing.join(", ")));
    }
    // SAFETY: geteuid(2) cannot fail.
    if unsafe { libc::geteuid() } != 0 {
        return Some("not root (the cluster's daemons and jobs run as root, as in CI)".into());
    }
    None
}

/// `name` on `PATH` or in the sbin folders, which a user's `PATH` often lacks.
fn find_program(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/local/sbin", "/usr/sbin", "/sbin"].map(PathBuf::from))
        .map(|dir| dir.join(name))
        .find(|p| {
            p.metadata()
                .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        })
}

fn output(cmd: &mut Command, prog: &str) -> Result<Output, String> {
    cmd.stdin(Stdio::null())
        .output()
        .map_err(|e| format!("running {prog}: {e}"))
}

/// This host's short name: slurmctld starts only on the host `SlurmctldHost` names.
fn node_name() -> Result<String, String> {
    let mut buf = [0u8; 256];
    // SAFETY: the buffer is valid for its length, which is passed with it.
    let rc = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) };
    if rc != 0 {
        return Err(format!("gethostname: {}", std::io::Error::last_os_error()));
    }
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    let host = String::from_utf8_lossy(&buf[..end]);
    let short = host.split('.').next().unwrap_or_default();
    let valid = |c: char| c.is_ascii_alphanumeric() || c == '-' || c == '_';
    if short.is_empty() || !short.chars().all(valid) {
        return Err(format!(
            "this host's name {host:?} cannot name a Slurm node"
        ));
    }
    Ok(short.to_string())
}

fn available_cpus() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The node's `RealMemory` in MiB: 90 % of MemTotal, since slurmd marks a node that has
/// less than its configured memory invalid, and the kernel's count varies a little.
fn real_memory_mib() -> u64 {
    let total_kib = fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|m| {
            m.lines()
                .find_map(|l| l.strip_prefix("MemTotal:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .unwrap_or(1 << 20);
    (total_kib / 1024 * 9 / 10).max(1)
}

/// Two TCP ports free at the moment (held together, so they differ), for slurmctld and
/// slurmd: a system Slurm's 6817/6818 or another test's cluster keeps its own.
fn free_ports() -> Result<(u16, u16), String> {
    let bind = || -> Result<(u16, TcpListener), String> {
        let listener = TcpListener::bind(("0.0.0.0", 0))
            .map_err(|e| format!("finding a free TCP port: {e}"))?;
        let port = listener
            .local_addr()
            .map_err(|e| format!("finding a free TCP port: {e}"))?
            .port();
        Ok((port, listener))
    };
    let (a, _la) = bind()?;
    let (b, _lb) = bind()?;
    Ok((a, b))
}

/// Writes the folders, the munge key, `slurm.conf` and `cgroup.conf` under `dir`.
fn write_config(dir: &Path, node: &str, cpus: usize) -> Result<(), String> {
    let shown = dir.display().to_string();
    // slurm.conf has no quoting: a blank or '#' would cut its paths.
    if shown.contains(|c: char| c.is_whitespace() || c == '#') {
        return Err(format!(
            "the temporary folder {shown} has a blank or '#', which slurm.conf cannot hold (set TMPDIR)"
        ));
    }
    let io = |what: &Path, e: std::io::Error| format!("{}: {e}", what.display());
    let set_mode = |p: &Path, mode: u32| {
        fs::set_permissions(p, fs::Permissions::from_mode(mode)).map_err(|e| io(p, e))
    };
    // munged refuses a socket whose folders are not searchable by everyone (the cluster's
    // folder is 0700 as created) and a key readable by anyone but its owner.
    set_mode(dir, 0o755)?;
    for (sub, mode) in [
        ("munge", 0o700),
        ("run", 0o755),
        ("state", 0o755),
        ("spool", 0o755),
        ("log", 0o755),
    ] {
        let p = dir.join(sub);
        fs::create_dir(&p).map_err(|e| io(&p, e))?;
        set_mode(&p, mode)?;
    }
    let key_path = dir.join("munge/munge.key");
    let mut key = [0u8; 1024];
    fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut key))
        .map_err(|e| format!("/dev/urandom: {e}"))?;
    fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o400)
        .open(&key_path)
        .and_then(|mut f| std::io::Write::write_all(&mut f, &key))
        .map_err(|e| io(&key_path, e))?;
    let (ctld_port, slurmd_port) = free_ports()?;
    let conf = slurm_conf(dir, node, cpus, real_memory_mib(), ctld_port, slurmd_port);
    let conf_path = dir.join("slurm.conf");
    fs::write(&conf_path, conf).map_err(|e| io(&conf_path, e))?;
    let cgroup_path = dir.join("cgroup.conf");
    fs::write(&cgroup_path, CGROUP_CONF).map_err(|e| io(&cgroup_path, e))
}

/// `cgroup.conf`, which Slurm reads beside `slurm.conf`.
///
/// slurmd 22.05 loads a cgroup plugin at start-up whatever the other plugins are
/// (`cgroup_g_init()` in `_slurmd_init`, fatal on failure), and `CgroupPlugin=disabled`
/// only came in 23.02. Its default, `autodetect`, picks `cgroup/v2` where /sys/fs/cgroup
/// is cgroup2 (a container on a current host), and that plugin's init has systemd create
/// a scope over D-Bus, or with `IgnoreSystemd` writes the hierarchy itself, and fails
/// without systemd or on a read-only /sys/fs/cgroup (and, on a hybrid host such as this
/// one, stops at "Hybrid mode is not supported"); autodetect fails outright where nothing
/// is mounted there. `cgroup/v1`'s init only sets up empty lists and touches no file, and
/// nothing here calls it after that: proctrack/linuxproc, task/none and jobacct_gather/none
/// use no cgroup, and without CoreSpec/MemSpec slurmd makes no system cgroup. So naming
/// `cgroup/v1` is 22.05's way of loading a cgroup plugin that does nothing. (Checked here by
/// starting slurmd in a mount namespace with a read-only cgroup2 over /sys/fs/cgroup: it
/// fails under autodetect and starts and runs jobs with this file.)
const CGROUP_CONF: &str = "\
# Written by StegoNGP's tests: see crates/testkit/src/slurm.rs for why.
CgroupPlugin=cgroup/v1
";

/// `slurm.conf` for one node, `node`, serving `cpus` 1-CPU jobs at once; every path under
/// `dir`.
fn slurm_conf(
    dir: &Path,
    node: &str,
    cpus: usize,
    memory_mib: u64,
    ctld_port: u16,
    slurmd_port: u16,
) -> String {
    let d = dir.display();
    format!(
        "\
# Written by StegoNGP's tests (crates/testkit/src/slurm.rs): a one-node cluster in {d}.
ClusterName=stegotest
SlurmctldHost={node}(127.0.0.1)
SlurmctldPort={ctld_port}
SlurmdPort={slurmd_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
# This cluster's munged, not /run/munge's.
AuthInfo=socket={d}/run/munge.sock
StateSaveLocation={d}/state
SlurmdSpoolDir={d}/spool
SlurmctldPidFile={d}/run/slurmctld.pid
SlurmdPidFile={d}/run/slurmd.pid
SlurmctldLogFile={d}/log/slurmctld.log
SlurmdLogFile={d}/log/slurmd.log
# No systemd and no cgroups: processes are tracked through their parents, tasks are not
# bound, nothing is accounted (see cgroup.conf).
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
MailProg=/bin/true
# Cores are the consumable resource, so several 1-CPU jobs share the node.
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
# The defaults (batch_sched_delay=3, sched_interval=60, bf_interval=30) leave a finished
# job's CPU idle for about 3 s; these start the next job within about a second.
SchedulerParameters=batch_sched_delay=0,sched_interval=1,bf_interval=1
# A finished job leaves slurmctld's records after 30 s (scontrol show job works till then).
MinJobAge=30
# scancel: SIGTERM, then SIGKILL 2 s later (default 30 s).
KillWait=2
ReturnToService=2
NodeName={node} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={memory_mib} State=UNKNOWN
PartitionName={PARTITION} Nodes={node} Default=YES MaxTime=INFINITE State=UP
"
    )
}

/// SIGTERM to a daemon, SIGKILL if it has not exited within [`STOP_TIMEOUT`]; reaped.
fn terminate(name: &str, child: &mut Child) {
    if matches!(child.try_wait(), Ok(Some(_))) {
        return;
    }
    let Ok(pid) = libc::pid_t::try_from(child.id()) else {
        return;
    };
    // SAFETY: kill(2) on our own, not yet reaped, child.
    unsafe { libc::kill(pid, libc::SIGTERM) };
    let deadline = Instant::now() + STOP_TIMEOUT;
    while Instant::now() < deadline {
        if matches!(child.try_wait(), Ok(Some(_))) {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!(
        "stopping the Slurm cluster: {name} ignored SIGTERM for {} s, killing it",
        STOP_TIMEOUT.as_secs()
    );
    let _ = child.kill();
    let _ = child.wait();
}

/// Processes that still belong to the cluster once its daemons are gone: those whose
/// command line, working folder or open files lie in `dir` (a slurmstepd holds slurmd's
/// log, a batch script runs from the spool folder), and their descendants. Not this one.
fn leftovers(dir: &Path) -> Vec<libc::pid_t> {
    let me = std::process::id() as libc::pid_t;
    let mut parent = Vec::new();
    let mut marked = Vec::new();
    let Ok(entries) = fs::read_dir("/proc") else {
        return Vec::new();
    };
    for entry in entries.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<libc::pid_t>().ok())
        else {
            continue;
        };
        let proc_dir = entry.path();
        let Ok(stat) = fs::read_to_string(proc_dir.join("stat")) else {
            continue;
        };
        // "PID (COMM) STATE PPID ...": COMM may hold blanks, so read after its ')'.
        let after = stat.rsplit_once(')').map_or("", |(_, rest)| rest);
        let mut fields = after.split_whitespace();
        let state = fields.next().unwrap_or("");
        let ppid = fields.next().and_then(|p| p.parse().ok()).unwrap_or(0);
        if pid == me || state == "Z" {
            continue;
        }
        parent.push((pid, ppid));
        if refers_to(&proc_dir, dir) {
            marked.push(pid);
        }
    }
    // Add descendants until nothing changes (the job's own children, e.g. a `sleep`).
    let mut grown = true;
    while grown {
        grown = false;
        for &(pid, ppid) in &parent {
            if marked.contains(&ppid) && !marked.contains(&pid) && pid != me {
                marked.push(pid);
                grown = true;
            }
        }
    }
    marked
}

/// Whether the process at `/proc/PID` names `dir` in its command line, works in it or
/// holds a file in it.
fn refers_to(proc_dir: &Path, dir: &Path) -> bool {
    let needle = dir.as_os_str().as_encoded_bytes();
    let cmdline = fs::read(proc_dir.join("cmdline")).unwrap_or_default();
    if cmdline.windows(needle.len()).any(|w| w == needle) {
        return true;
    }
    if fs::read_link(proc_dir.join("cwd")).is_ok_and(|p| p.starts_with(dir)) {
        return true;
    }
    fs::read_dir(proc_dir.join("fd")).is_ok_and(|fds| {
        fds.flatten()
            .any(|fd| fs::read_link(fd.path()).is_ok_and(|p| p.starts_with(dir)))
    })
}
