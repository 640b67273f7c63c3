//! The kernel test rig: real kernel buses for tests on machines whose own kernel has none.
//!
//! The rig boots a Debian 6.12 kernel under qemu (TCG, one vCPU; KVM is not usable on
//! these machines) whose root is the host's `/`, shared read-only over virtio-9p with a tmpfs
//! overlay on top. A test binary therefore runs in the guest exactly as built, with the
//! host's tools (can-utils, iproute2, …) but the guest's kernel: vcan, real CAN controller
//! emulation (kvaser_pci), i2c-stub, comedi_test. Output and the exit code come back through
//! a read-write 9p share of a per-run directory; every boot is bounded by a timeout, and
//! qemu dies with the process that started it.
//!
//! A test binary opts in by replacing libtest's `main` (`harness = false` in Cargo.toml)
//! with [`harness`]: on the host it boots the guest and runs itself there with the same
//! arguments; in the guest it runs the trials. So plain `cargo test` runs kernel tests, one
//! boot per test binary.
//!
//! ```no_run
//! use kernel_rig::{Rig, Trial};
//!
//! fn main() -> std::process::ExitCode {
//!     let rig = Rig::new().module("vcan").tool("candump", "can-utils");
//!     kernel_rig::harness(&rig, vec![Trial::test("vcan_exists", || {
//!         kernel_rig::sh("ip link add vcan9 type vcan && ip link set vcan9 up")?;
//!         Ok(())
//!     })])
//! }
//! ```
//!
//! When the rig cannot start (no root to install qemu, no apt archive), the trials are
//! reported as ignored under a loud banner, unless `CI` is set: then that is a failure.

pub mod cpio;
pub mod prepare;

pub use libtest_mimic::{Failed, Measurement, Trial};

use std::ffi::OsString;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

/// qemu arguments for two kvaser_pci (SJA1000) CAN controllers on one emulated bus; in
/// the guest they are `can0` and `can1` (load `kvaser_pci`).
pub const KVASER_PAIR: [&str; 6] = [
    "-object",
    "can-bus,id=canbus0",
    "-device",
    "kvaser_pci,canbus=canbus0",
    "-device",
    "kvaser_pci,canbus=canbus0",
];

/// Set (to `1`) in the guest's environment.
pub const GUEST_ENV: &str = "HWGW_RIG_GUEST";

/// Set in the guest's environment to the run directory: shared with the host read-write
/// at the same path, where qemu's own records of a run are (see [`Rig::parallel_port`]).
pub const RUN_ENV: &str = "HWGW_RIG_RUN";

/// The file in the run directory where [`Rig::parallel_port`] has qemu record the
/// port's register writes.
pub const PARPORT_TRACE: &str = "parport.trace";

/// Why the rig could not run something.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RigError {
    /// A tool or package is missing and cannot be installed here.
    #[error("{0}")]
    Missing(String),
    /// A host command failed.
    #[error("{command}: {problem}")]
    Command {
        /// The command.
        command: String,
        /// How it failed.
        problem: String,
    },
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The guest ran past its time limit and was killed.
    #[error(
        "the guest did not finish within {limit:?} and was killed; its console ended with:\n{console}"
    )]
    Timeout {
        /// The limit.
        limit: Duration,
        /// The last lines of the guest console.
        console: String,
    },
    /// The guest stopped without reporting an exit code.
    #[error("the guest stopped without a result ({status}); its console ended with:\n{console}")]
    NoResult {
        /// qemu's exit status.
        status: String,
        /// The last lines of the guest console.
        console: String,
    },
}

impl RigError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> RigError {
        RigError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// True inside the rig's guest.
pub fn in_guest() -> bool {
    std::env::var_os(GUEST_ENV).is_some()
}

/// The run directory, in the guest (see [`RUN_ENV`]).
pub fn run_dir() -> Option<PathBuf> {
    std::env::var_os(RUN_ENV).map(PathBuf::from)
}

/// True when running under CI (`CI` set and not `false`/`0`), where an unusable rig fails.
pub fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "false" && v != "0")
}

/// Where the rig keeps its kernel, initramfs and run directories:
/// `$CARGO_TARGET_DIR/kernel-rig`, or `target/kernel-rig` of this workspace.
pub fn rig_dir() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            let ws = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
            ws.canonicalize().unwrap_or(ws).join("target")
        });
    target.join("kernel-rig")
}

/// A guest to boot: its modules, host tools, setup and qemu devices.
#[derive(Debug, Clone)]
pub struct Rig {
    modules: Vec<String>,
    tools: Vec<(String, String)>,
    setup: Vec<String>,
    qemu: Vec<String>,
    memory_mb: u32,
    cpus: u32,
    timeout: Duration,
    systemd: bool,
    gpio_sim: bool,
    parallel: bool,
}

impl Default for Rig {
    fn default() -> Self {
        Rig::new()
    }
}

/// Quotes `s` for a POSIX shell.
fn quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

impl Rig {
    /// A guest with no extra modules, one CPU, 1 GiB and a 10-minute limit
    /// (`HWGW_RIG_TIMEOUT` in seconds overrides the limit).
    pub fn new() -> Rig {
        let timeout = std::env::var("HWGW_RIG_TIMEOUT")
            .ok()
            .and_then(|s| s.parse().ok())
            .map_or(Duration::from_secs(600), Duration::from_secs);
        Rig {
            modules: Vec::new(),
            tools: Vec::new(),
            setup: Vec::new(),
            qemu: Vec::new(),
            memory_mb: 1024,
            // qemu 7.2's multi-threaded TCG breaks the kernel's int3 text patching now
            // and then (an oops in early boot, seen in about one boot in twenty with 2
            // vCPUs); one vCPU never showed it.
            cpus: 1,
            timeout,
            systemd: false,
            gpio_sim: false,
            parallel: false,
        }
    }

    /// Boots the guest with the host's systemd as PID 1 (journald, udevd, the basic
    /// system), the command running as a oneshot service: for tests of units as an
    /// operator would run them. Installs the host's `systemd` and `udev` if missing.
    pub fn systemd(mut self) -> Rig {
        self.systemd = true;
        self.tool("/lib/systemd/systemd", "systemd")
            .tool("udevadm", "udev")
    }

    /// Gives the guest the kernel's GPIO simulator: the gpio-sim module (built once for
    /// the rig's kernel, see [`prepare::gpio_sim`]) loaded, configfs mounted at
    /// `/sys/kernel/config`, and libgpiod's tools (Debian `gpiod`) on the host.
    pub fn gpio_sim(mut self) -> Rig {
        self.gpio_sim = true;
        self.module("gpio-sim")
            .setup("mountpoint -q /sys/kernel/config || mount -t configfs none /sys/kernel/config")
            .tool("gpioinfo", "gpiod")
    }

    /// Gives the guest comedi: the core with four legacy device files (`/dev/comedi0`…`3`,
    /// no board attached), the comedi_test and comedi_parport drivers loaded, a
    /// [`parallel_port`](Self::parallel_port) for comedi_parport, and comedilib's
    /// `comedi_config` (Debian `libcomedi0`) on the host to attach boards with.
    pub fn comedi(self) -> Rig {
        self.parallel_port()
            .setup("modprobe comedi comedi_num_legacy_minors=4")
            .setup("modprobe comedi_test noauto=1")
            .setup("modprobe comedi_parport")
            .tool("comedi_config", "libcomedi0")
    }

    /// Gives the guest a PC parallel port at I/O 0x378 (IRQ 7), and records every write
    /// the guest makes to its registers as qemu sees it (qemu's `parallel_ioport_write`
    /// trace event, with host timestamps) in [`PARPORT_TRACE`] in the run directory: the
    /// port's outputs read from outside the guest's kernel (see [`run_dir`]).
    ///
    /// qemu's parallel port hands its data register to its character device only on a
    /// strobe (and only with INIT and SELECT high), so a chardev (`-parallel file:`) sees
    /// none of the writes a driver of the data lines makes; the trace sees each one.
    pub fn parallel_port(mut self) -> Rig {
        self.parallel = true;
        self
    }

    /// Loads `module` (with its dependencies) in the guest before the command runs.
    pub fn module(mut self, module: &str) -> Rig {
        self.modules.push(module.to_string());
        self
    }

    /// Makes sure the host has `command`, installing Debian `package` if not.
    pub fn tool(mut self, command: &str, package: &str) -> Rig {
        self.tools.push((command.to_string(), package.to_string()));
        self
    }

    /// A shell line run in the guest (as root) before the command, after the modules.
    pub fn setup(mut self, line: &str) -> Rig {
        self.setup.push(line.to_string());
        self
    }

    /// Extra qemu arguments (devices, buses).
    pub fn qemu_args(mut self, args: &[&str]) -> Rig {
        self.qemu.extend(args.iter().map(|s| s.to_string()));
        self
    }

    /// Boots with `n` vCPUs (default 1; more runs into qemu 7.2's TCG text-patching
    /// race now and then).
    pub fn cpus(mut self, n: u32) -> Rig {
        self.cpus = n.max(1);
        self
    }

    /// The time limit of one boot, from power-on to power-off.
    pub fn timeout(mut self, limit: Duration) -> Rig {
        self.timeout = limit;
        self
    }

    fn prepare(&self) -> Result<prepare::Kernel, RigError> {
        let tools: Vec<(&str, &str)> = self
            .tools
            .iter()
            .map(|(c, p)| (c.as_str(), p.as_str()))
            .collect();
        let kernel = prepare::kernel(&rig_dir(), &tools)?;
        if self.gpio_sim {
            prepare::gpio_sim(&rig_dir(), &kernel)?;
        }
        Ok(kernel)
    }

    /// Boots the guest, runs `program` with `args` in the current directory with this
    /// process's environment, streams its output here and returns its exit code.
    ///
    /// A guest that fails before the command started (an emulator fault in early boot)
    /// is booted once more, saying so; a command that started is never run twice.
    pub fn run(&self, program: &Path, args: &[OsString]) -> Result<i32, RigError> {
        let kernel = self.prepare()?;
        match self.run_once(&kernel, program, args) {
            Err((e @ RigError::NoResult { .. }, false)) => {
                eprintln!(
                    "kernel-rig: the guest failed before the command started; booting again. It said:\n{e}"
                );
                self.run_once(&kernel, program, args).map_err(|(e, _)| e)
            }
            other => other.map_err(|(e, _)| e),
        }
    }

    /// One boot; an error says whether the command had started.
    fn run_once(
        &self,
        kernel: &prepare::Kernel,
        program: &Path,
        args: &[OsString],
    ) -> Result<i32, (RigError, bool)> {
        let run = RunDir::new().map_err(|e| (e, false))?;
        let started = || run.path.join("started").exists();
        self.run_in(kernel, &run, program, args)
            .map_err(|e| (e, started()))
    }

    fn run_in(
        &self,
        kernel: &prepare::Kernel,
        run: &RunDir,
        program: &Path,
        args: &[OsString],
    ) -> Result<i32, RigError> {
        let mut cmd = String::from("run_command() {\n  env -i");
        for (k, v) in std::env::vars_os() {
            let (k, v) = (k.to_string_lossy(), v.to_string_lossy());
            // Host session plumbing that means nothing in the guest.
            if matches!(
                k.as_ref(),
                "XDG_RUNTIME_DIR" | "JOURNAL_STREAM" | "NOTIFY_SOCKET" | "DBUS_SESSION_BUS_ADDRESS"
            ) || k.starts_with("LISTEN_")
            {
                continue;
            }
            cmd.push_str(&format!(" {}", quote(&format!("{k}={v}"))));
        }
        cmd.push_str(&format!(
            " {GUEST_ENV}=1 {RUN_ENV}={} {}",
            quote(&run.path.to_string_lossy()),
            quote(&program.to_string_lossy())
        ));
        for a in args {
            cmd.push_str(&format!(" {}", quote(&a.to_string_lossy())));
        }
        cmd.push_str("\n}\n");
        self.write_script(run, "run", &cmd)?;
        let mut qemu = self.qemu_command(kernel, run, false);
        qemu.stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(file(&run.path.join("qemu.log"), true)?);
        let mut child = Guard::spawn(&mut qemu)?;
        let deadline = Instant::now() + self.timeout;
        let mut out = Tail::new(run.path.join("stdout"));
        let mut err = Tail::new(run.path.join("stderr"));
        let status = loop {
            out.pump(&mut std::io::stdout());
            err.pump(&mut std::io::stderr());
            match child.0.try_wait() {
                Ok(Some(status)) => break status,
                Ok(None) => {}
                Err(e) => return Err(RigError::io(Path::new("qemu"), e)),
            }
            if Instant::now() >= deadline {
                drop(child);
                return Err(RigError::Timeout {
                    limit: self.timeout,
                    console: run.console_tail(),
                });
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        out.pump(&mut std::io::stdout());
        err.pump(&mut std::io::stderr());
        let rc = std::fs::read_to_string(run.path.join("rc"))
            .ok()
            .and_then(|s| s.trim().parse::<i32>().ok());
        match rc {
            Some(rc) => Ok(rc),
            None => Err(RigError::NoResult {
                status: status.to_string(),
                console: run.console_tail(),
            }),
        }
    }

    /// Boots the guest with a root shell on this terminal (leave with `exit`).
    pub fn shell(&self) -> Result<(), RigError> {
        let kernel = self.prepare()?;
        let run = RunDir::new()?;
        self.write_script(&run, "shell", "")?;
        let mut qemu = self.qemu_command(&kernel, &run, true);
        let mut child = Guard::spawn(qemu.stdin(Stdio::inherit()))?;
        child
            .0
            .wait()
            .map_err(|e| RigError::io(Path::new("qemu"), e))?;
        Ok(())
    }

    fn write_script(&self, run: &RunDir, mode: &str, command: &str) -> Result<(), RigError> {
        let cwd = std::env::current_dir().map_err(|e| RigError::io(Path::new("."), e))?;
        let vars = format!(
            "RUN={}\nMODULES={}\nSETUP={}\nMODE={mode}\nCWD={}\nSYSTEMD={}\n{command}",
            quote(&run.path.to_string_lossy()),
            quote(&self.modules.join(" ")),
            quote(&self.setup.join("\n")),
            quote(&cwd.to_string_lossy()),
            u8::from(self.systemd),
        );
        let script = include_str!("../guest/guest.sh.in").replace("@VARS@", &vars);
        let path = run.path.join("guest.sh");
        std::fs::write(&path, script).map_err(|e| RigError::io(&path, e))
    }

    fn qemu_command(&self, kernel: &prepare::Kernel, run: &RunDir, interactive: bool) -> Command {
        let mut c = Command::new("qemu-system-x86_64");
        let modules = kernel.root.join("lib/modules");
        c.args(["-machine", "pc", "-accel", "tcg"])
            .args([
                "-smp",
                &self.cpus.to_string(),
                "-m",
                &self.memory_mb.to_string(),
            ])
            .args([
                "-nodefaults",
                "-no-user-config",
                "-display",
                "none",
                "-no-reboot",
            ])
            .arg("-kernel")
            .arg(&kernel.vmlinuz)
            .arg("-initrd")
            .arg(&kernel.initramfs)
            .arg("-append")
            .arg(format!(
                "console=ttyS0 quiet loglevel=3 panic=-1 RIG_RUN={} RIG_MODULES={}{}",
                run.path.display(),
                modules.display(),
                if self.systemd {
                    " RIG_SYSTEMD=1 systemd.unit=rig.target systemd.show_status=false"
                } else {
                    ""
                }
            ))
            .args([
                "-fsdev",
                "local,id=host,path=/,security_model=none,readonly=on,multidevs=remap",
                "-device",
                "virtio-9p-pci,fsdev=host,mount_tag=host",
                "-fsdev",
            ])
            .arg(format!(
                "local,id=rig,path={},security_model=none,multidevs=remap",
                run.path.display()
            ))
            .args(["-device", "virtio-9p-pci,fsdev=rig,mount_tag=rig"])
            .args(&self.qemu);
        if self.parallel {
            c.args(["-chardev", "null,id=lpt0"])
                .args(["-device", "isa-parallel,chardev=lpt0,iobase=0x378,irq=7"])
                .args(["-trace", "enable=parallel_ioport_write"])
                .args(["-msg", "timestamp=on"])
                .arg("-D")
                .arg(run.path.join(PARPORT_TRACE));
        }
        if interactive {
            c.args(["-serial", "mon:stdio"]);
        } else {
            c.arg("-serial")
                .arg(format!("file:{}", run.path.join("console.log").display()));
        }
        c
    }
}

/// A run's directory under the rig directory; removed when the run is done.
struct RunDir {
    path: PathBuf,
}

impl RunDir {
    fn new() -> Result<RunDir, RigError> {
        use std::sync::atomic::{AtomicU32, Ordering};
        static N: AtomicU32 = AtomicU32::new(0);
        let base = rig_dir().join("runs");
        let path = base.join(format!(
            "{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).map_err(|e| RigError::io(&path, e))?;
        // The path travels on the kernel command line, which splits at spaces.
        let path = path.canonicalize().map_err(|e| RigError::io(&path, e))?;
        if path.to_string_lossy().contains(char::is_whitespace) {
            return Err(RigError::Missing(format!(
                "the rig directory {} has a space in it; set CARGO_TARGET_DIR elsewhere",
                path.display()
            )));
        }
        Ok(RunDir { path })
    }

    fn console_tail(&self) -> String {
        let mut text = String::new();
        for f in ["console.log", "qemu.log"] {
            let s = std::fs::read_to_string(self.path.join(f)).unwrap_or_default();
            let lines: Vec<&str> = s.lines().collect();
            let from = lines.len().saturating_sub(30);
            for l in &lines[from..] {
                text.push_str(&format!("  {f}: {}\n", l.trim_end_matches('\r')));
            }
        }
        text
    }
}

impl Drop for RunDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

fn file(path: &Path, create: bool) -> Result<std::fs::File, RigError> {
    std::fs::OpenOptions::new()
        .create(create)
        .truncate(create)
        .write(true)
        .open(path)
        .map_err(|e| RigError::io(path, e))
}

/// The qemu process; killed and reaped when dropped, and killed by the kernel if this
/// process dies first, so no boot outlives its test.
struct Guard(std::process::Child);

impl Guard {
    fn spawn(cmd: &mut Command) -> Result<Guard, RigError> {
        use std::os::unix::process::CommandExt;
        #[allow(
            unsafe_code,
            reason = "pre_exec runs between fork and exec; prctl(PR_SET_PDEATHSIG) is async-signal-safe"
        )]
        // SAFETY: the closure only makes one async-signal-safe system call.
        unsafe {
            cmd.pre_exec(|| {
                nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGKILL)
                    .map_err(std::io::Error::from)
            });
        }
        cmd.spawn()
            .map(Guard)
            .map_err(|e| RigError::io(Path::new("qemu-system-x86_64"), e))
    }
}

impl Drop for Guard {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
        }
        let _ = self.0.wait();
    }
}

/// Follows a file the guest appends to, copying what is new.
struct Tail {
    path: PathBuf,
    at: u64,
}

impl Tail {
    fn new(path: PathBuf) -> Tail {
        Tail { path, at: 0 }
    }

    fn pump(&mut self, to: &mut dyn Write) {
        let Ok(mut f) = std::fs::File::open(&self.path) else {
            return;
        };
        if f.seek(std::io::SeekFrom::Start(self.at)).is_err() {
            return;
        }
        let mut buf = Vec::new();
        if let Ok(n) = f.read_to_end(&mut buf) {
            self.at += n as u64;
            let _ = to.write_all(&buf);
            let _ = to.flush();
        }
    }
}

/// Runs `script` with `sh -c` and returns its standard output; an error carries the exit
/// status, standard error and standard output (where a script's `2>&1` sent its error).
/// For tests' guest-side setup (`ip link …`).
pub fn sh(script: &str) -> Result<String, Failed> {
    let out = Command::new("sh")
        .args(["-c", script])
        .output()
        .map_err(|e| Failed::from(format!("sh -c {script:?}: {e}")))?;
    if !out.status.success() {
        let stdout = String::from_utf8_lossy(&out.stdout);
        return Err(format!(
            "sh -c {script:?}: {}: {}{}{}",
            out.status,
            String::from_utf8_lossy(&out.stderr).trim(),
            if stdout.trim().is_empty() {
                ""
            } else {
                "\nstandard output:\n"
            },
            stdout.trim()
        )
        .into());
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The `main` of a kernel test binary: in the guest, runs `trials` as libtest would; on
/// the host, boots `rig` and runs this binary inside it with the same arguments. In the
/// guest trials run one at a time unless `--test-threads` says otherwise.
/// Listing (`--list`) happens on the host without a boot.
pub fn harness(rig: &Rig, trials: Vec<Trial>) -> ExitCode {
    let mut args = libtest_mimic::Arguments::from_args();
    // One trial at a time: the guest has few CPUs and trials measure timing.
    if in_guest() && args.test_threads.is_none() {
        args.test_threads = Some(1);
    }
    if in_guest() || args.list {
        return libtest_mimic::run(&args, trials).exit_code();
    }
    let outcome = std::env::current_exe()
        .map_err(|e| RigError::io(Path::new("/proc/self/exe"), e))
        .and_then(|exe| rig.run(&exe, &std::env::args_os().skip(1).collect::<Vec<_>>()));
    match outcome {
        Ok(0) => ExitCode::SUCCESS,
        Ok(rc) => {
            eprintln!("kernel-rig: the tests in the guest exited with {rc}");
            ExitCode::FAILURE
        }
        // A guest that booted but did not finish is the tests' failure, wherever it runs.
        Err(e @ RigError::Timeout { .. }) => {
            eprintln!("kernel-rig: FAILED: {e}");
            ExitCode::FAILURE
        }
        Err(e) if in_ci() => {
            eprintln!("kernel-rig: FAILED: the kernel test rig cannot run here (CI is set):\n{e}");
            ExitCode::FAILURE
        }
        Err(e) => {
            let bar = "!".repeat(78);
            eprintln!(
                "{bar}\n!! kernel-rig: THE KERNEL TESTS BELOW DID NOT RUN: the rig cannot start here.\n\
                 !! {e}\n!! (with CI set this is a failure)\n{bar}"
            );
            let ignored = trials
                .into_iter()
                .map(|t| t.with_ignored_flag(true))
                .collect();
            libtest_mimic::run(&args, ignored).exit_code()
        }
    }
}
