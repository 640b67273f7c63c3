//! `hwgw run` and `hwgw check`: a deployment loaded, built, served on its control socket,
//! watched by systemd, reloaded on SIGHUP and stopped on SIGTERM/SIGINT with every output
//! at its safe value.

use crate::config::Deployment;
use crate::control::ControlServer;
use crate::deploy::Gateway;
use crate::types::Types;
use nix::sys::signal::{SigSet, Signal};
use sd_notify::NotifyState;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

/// Looks at the gateway's health four times a watchdog interval and feeds the watchdog at
/// each look that finds nothing wrong since the look before (see [`Gateway::health_since`]);
/// says why in STATUS when it is not (once per change). So systemd restarts hwgw when no
/// look finds it healthy for a whole interval, and a look that does not feed costs a
/// quarter interval: at a feed every half interval, one withheld feed left the next
/// exactly one interval after the last, and a look a few milliseconds late lost the race
/// with systemd's timeout.
fn watchdog(
    gw: Arc<Gateway>,
    interval: std::time::Duration,
    stop: Arc<std::sync::atomic::AtomicBool>,
    running: String,
) {
    let mut last: Option<Result<(), String>> = None;
    let mut looks = crate::health::Looks::new();
    while !stop.load(std::sync::atomic::Ordering::Acquire) {
        let health = gw.health_since(&mut looks);
        if last.as_ref() != Some(&health) {
            match &health {
                Ok(()) => {
                    tracing::info!("healthy");
                    let _ = sd_notify::notify(&[NotifyState::Status(&running)]);
                }
                Err(why) => {
                    tracing::error!("unhealthy, not feeding the watchdog: {why}");
                    let _ = sd_notify::notify(&[NotifyState::Status(&format!("unhealthy: {why}"))]);
                }
            }
            last = Some(health.clone());
        }
        if health.is_ok() {
            let _ = sd_notify::notify(&[NotifyState::Watchdog]);
        }
        std::thread::sleep(interval / 4);
    }
}

/// The deployment's text and the name errors give it: the file's, or the embedded demo's.
fn load(config: Option<&PathBuf>) -> Result<(String, String), String> {
    match config {
        None => Ok((crate::DEMO.to_string(), "<embedded demo>".to_string())),
        Some(p) => {
            let file = p.display().to_string();
            let text = std::fs::read_to_string(p).map_err(|e| {
                crate::config::ConfigError::Read {
                    file: file.clone(),
                    message: e.to_string(),
                }
                .to_string()
            })?;
            Ok((text, file))
        }
    }
}

fn build(config: Option<&PathBuf>, types: &Types) -> Result<(Gateway, Deployment), String> {
    let (text, file) = load(config)?;
    Gateway::from_text(&text, &file, types)
}

/// `hwgw check CONFIG`: every problem, or the summary and `ok`.
pub fn check(config: PathBuf, types: &Types) -> ExitCode {
    match build(Some(&config), types) {
        Ok((gw, _)) => {
            // A reader gone (`hwgw check x | head`) is no reason to panic: the verdict is
            // the exit code.
            use std::io::Write;
            let mut out = std::io::stdout().lock();
            let _ = write!(out, "{}", gw.summary())
                .and_then(|()| writeln!(out, "{}: ok", config.display()));
            ExitCode::SUCCESS
        }
        Err(e) => {
            use std::io::Write;
            let _ = writeln!(std::io::stderr().lock(), "{e}");
            ExitCode::FAILURE
        }
    }
}

/// Stops the gateway once: when asked, or when dropped (a panic unwinding through `run`
/// included), so no way out leaves the outputs as the last writer left them.
struct Stopper {
    gw: Arc<Gateway>,
    server: ControlServer,
    stopped: bool,
}

impl Stopper {
    /// No write may race the safe values: outputs refuse writes first (whatever a request
    /// under way still does), then the server lets requests finish for a bounded time and
    /// disconnects every client, then the gateway stops.
    fn stop(&mut self) {
        if std::mem::replace(&mut self.stopped, true) {
            return;
        }
        self.gw.hold_outputs();
        self.server.close();
        for line in self.gw.shutdown() {
            tracing::info!("{line}");
        }
    }
}

impl Drop for Stopper {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The signals that stop the gateway with its outputs safe: every one whose default is to
/// end the process and that a process may handle (SIGKILL and SIGSTOP it may not; faults
/// such as SIGSEGV are not requests to stop).
const STOPPING: [Signal; 12] = [
    Signal::SIGTERM,
    Signal::SIGINT,
    Signal::SIGQUIT,
    Signal::SIGUSR1,
    Signal::SIGUSR2,
    Signal::SIGALRM,
    Signal::SIGVTALRM,
    Signal::SIGPROF,
    Signal::SIGXCPU,
    Signal::SIGXFSZ,
    Signal::SIGIO,
    Signal::SIGPWR,
];

/// Blocks the stopping signals and SIGHUP in this thread (before any other exists, so every
/// thread inherits the mask and none is interrupted); they are taken by `sigwait`.
fn block_signals() -> nix::Result<SigSet> {
    let mut signals = SigSet::empty();
    for s in STOPPING.into_iter().chain([Signal::SIGHUP]) {
        signals.add(s);
    }
    signals.thread_block()?;
    Ok(signals)
}

/// `hwgw run [CONFIG]`: runs until a stopping signal.
pub fn run(config: Option<PathBuf>, socket: Option<PathBuf>, types: &Types) -> ExitCode {
    let signals = match block_signals() {
        Ok(s) => s,
        Err(e) => {
            eprintln!("hwgw: cannot block signals: {e}");
            return ExitCode::FAILURE;
        }
    };
    let (gw, d) = match build(config.as_ref(), types) {
        Ok(x) => x,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    if let Some(file) = &config {
        gw.set_file(file.clone());
    }
    let gw = Arc::new(gw);
    for line in gw.summary().lines() {
        tracing::info!("{line}");
    }
    let path = socket
        .or_else(|| d.control_socket.as_ref().map(PathBuf::from))
        .unwrap_or_else(crate::socket::default_server_socket);
    let server = match ControlServer::start(
        gw.clone(),
        &path,
        crate::control::Limits::of(&d).fit_descriptors(),
    ) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("hwgw: control socket: {e}");
            return ExitCode::FAILURE;
        }
    };
    // From here every way out of this function — a panic included — stops the gateway.
    let mut stopper = Stopper {
        gw: gw.clone(),
        server,
        stopped: false,
    };
    if let Err(e) = gw.record_thread_scope() {
        eprintln!("hwgw: thread_scope_vcd: {e}");
        stopper.stop();
        return ExitCode::FAILURE;
    }
    if let Err(e) = gw.start() {
        eprintln!("hwgw: {e}");
        stopper.stop();
        return ExitCode::FAILURE;
    }
    // Requests are answered from here on: none sees the gateway before it started.
    if let Err(e) = stopper.server.open() {
        eprintln!("hwgw: control socket: {e}");
        stopper.stop();
        return ExitCode::FAILURE;
    }
    tracing::info!(
        "running; control socket {}",
        stopper.server.path().display()
    );
    let status = format!(
        "running {} components; control socket {}",
        gw.runtime().components().len(),
        stopper.server.path().display()
    );
    if let Err(e) = sd_notify::notify(&[NotifyState::Ready, NotifyState::Status(&status)]) {
        tracing::warn!("cannot notify systemd: {e}");
    }
    let stop_watchdog = Arc::new(std::sync::atomic::AtomicBool::new(false));
    if let Some(interval) = sd_notify::watchdog_enabled() {
        tracing::info!("systemd watchdog every {interval:?}, fed while healthy");
        let (g, s, running) = (gw.clone(), stop_watchdog.clone(), status.clone());
        let spawned = std::thread::Builder::new()
            .name("hwgw-watchdog".into())
            .spawn(move || watchdog(g, interval, s, running));
        if let Err(e) = spawned {
            // Unfed, systemd will stop and restart hwgw: the outputs go safe either way.
            tracing::error!("cannot start the watchdog thread: {e}");
        }
    }
    loop {
        match signals.wait() {
            Ok(Signal::SIGHUP) => crate::reload::log_reload("SIGHUP", &gw.reload()),
            Ok(sig) => {
                tracing::info!("{sig}: stopping");
                break;
            }
            Err(e) => {
                tracing::error!("waiting for signals failed: {e}; stopping");
                break;
            }
        }
    }
    let _ = sd_notify::notify(&[
        NotifyState::Stopping,
        NotifyState::Status("stopping: outputs to safe values"),
    ]);
    stop_watchdog.store(true, std::sync::atomic::Ordering::Release);
    stopper.stop();
    tracing::info!("stopped");
    ExitCode::SUCCESS
}
