//! The `hwgw` command line: `run`, `check`, and the one-shot commands that talk to a
//! running gateway. A user's own binary with extra component types is
//! `fn main() -> ExitCode { hwgw::cli::main(my_types) }`.

use crate::config::Deployment;
use crate::control::{self, ControlServer};
use crate::deploy::Gateway;
use crate::types::Types;
use clap::{Parser, Subcommand};
use nix::sys::signal::{SigSet, Signal};
use sd_notify::NotifyState;
use serde_json::{Value, json};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

#[derive(Parser)]
#[command(
    name = "hwgw",
    version,
    about = "Hardware-IO gateway: Orocos device interfaces over Linux buses"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a deployment (with no file: the embedded demo on simulated cards).
    Run {
        /// The deployment file.
        config: Option<PathBuf>,
        /// Control socket path (overrides the file's control_socket).
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Check a deployment file: print every error and exit 1, or exit 0.
    Check {
        /// The deployment file.
        config: PathBuf,
    },
    /// List components, or describe one.
    Ls {
        /// A component to describe.
        component: Option<String>,
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// An interactive console on a running gateway (cd, ls, get, set, call, TAB completion).
    Browse {
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Device health and component states and timing.
    Status {
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Print each new value of an output port as it comes (Ctrl-C to stop).
    Watch {
        component: String,
        port: String,
        /// Stop after this many values.
        #[arg(long)]
        count: Option<u64>,
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Run a lifecycle command on a component: configure, start, stop, cleanup, recover.
    Lifecycle {
        command: String,
        component: String,
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// List the devices in the registry.
    Devices {
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Read an output port's last value or a property.
    Get {
        component: String,
        /// A port name, or `property:NAME`.
        name: String,
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Write an input port or a property (VALUE is JSON; anything else is taken as text).
    Set {
        component: String,
        /// A port name, or `property:NAME`.
        name: String,
        /// The value (JSON; anything else is taken as text). Negative numbers are values.
        #[arg(allow_negative_numbers = true)]
        value: String,
        #[arg(long)]
        socket: Option<PathBuf>,
    },
    /// Call an operation (each ARG is JSON; anything else is taken as text).
    Call {
        component: String,
        operation: String,
        /// Negative numbers are arguments, not options.
        #[arg(allow_negative_numbers = true)]
        args: Vec<String>,
        #[arg(long)]
        socket: Option<PathBuf>,
    },
}

fn json_arg(s: &str) -> Value {
    serde_json::from_str(s).unwrap_or_else(|_| Value::String(s.to_string()))
}

fn target(name: &str) -> (&'static str, &str) {
    match name.strip_prefix("property:") {
        Some(p) => ("property", p),
        None => ("port", name),
    }
}

/// Logs to the journal when systemd runs us (JOURNAL_STREAM is set), else to stderr.
fn init_logging() {
    use tracing_subscriber::prelude::*;
    let filter =
        || tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    if std::env::var_os("JOURNAL_STREAM").is_some()
        && let Ok(journal) = tracing_journald::layer()
    {
        tracing_subscriber::registry()
            .with(filter())
            .with(journal.with_field_prefix(None))
            .init();
        return;
    }
    tracing_subscriber::fmt()
        .with_env_filter(filter())
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}

/// Feeds the systemd watchdog every half interval while the gateway is healthy; says why
/// in STATUS when it is not (once per change).
fn watchdog(
    gw: Arc<Gateway>,
    interval: std::time::Duration,
    stop: Arc<std::sync::atomic::AtomicBool>,
) {
    let mut last: Option<Result<(), String>> = None;
    while !stop.load(std::sync::atomic::Ordering::Acquire) {
        let health = gw.health();
        if last.as_ref() != Some(&health) {
            match &health {
                Ok(()) => {
                    tracing::info!("healthy");
                    let _ = sd_notify::notify(&[NotifyState::Status("running")]);
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
        std::thread::sleep(interval / 2);
    }
}

/// Runs the command line with component `types` available to deployments.
pub fn main(types: Types) -> ExitCode {
    init_logging();
    let cli = Cli::parse();
    let (socket, req) = match cli.command {
        Command::Run { config, socket } => return run(config, socket, &types),
        Command::Check { config } => return check(config, &types),
        Command::Ls {
            component: None,
            socket,
        } => (socket, json!({"cmd": "ls"})),
        Command::Ls {
            component: Some(c),
            socket,
        } => (socket, json!({"cmd": "describe", "component": c})),
        Command::Devices { socket } => (socket, json!({"cmd": "devices"})),
        Command::Status { socket } => (socket, json!({"cmd": "status"})),
        Command::Browse { socket } => {
            let path = socket.unwrap_or_else(control::default_socket);
            return match crate::browse::run(path) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("hwgw: {e} (is hwgw running? `hwgw run` starts it)");
                    ExitCode::FAILURE
                }
            };
        }
        Command::Lifecycle {
            command,
            component,
            socket,
        } => (socket, json!({"cmd": command, "component": component})),
        Command::Watch {
            component,
            port,
            count,
            socket,
        } => {
            return watch(
                socket.unwrap_or_else(control::default_socket),
                component,
                port,
                count,
            );
        }
        Command::Get {
            component,
            name,
            socket,
        } => {
            let (kind, n) = target(&name);
            (
                socket,
                json!({"cmd": "get", "component": component, kind: n}),
            )
        }
        Command::Set {
            component,
            name,
            value,
            socket,
        } => {
            let (kind, n) = target(&name);
            (
                socket,
                json!({"cmd": "set", "component": component, kind: n, "value": json_arg(&value)}),
            )
        }
        Command::Call {
            component,
            operation,
            args,
            socket,
        } => {
            let args: Vec<Value> = args.iter().map(|a| json_arg(a)).collect();
            (
                socket,
                json!({"cmd": "call", "component": component, "operation": operation, "args": args}),
            )
        }
    };
    let path = socket.unwrap_or_else(control::default_socket);
    match control::request(&path, req) {
        Ok(reply) => match control::outcome(&reply) {
            Ok(v) => {
                println!("{}", serde_json::to_string_pretty(&v).unwrap_or_default());
                ExitCode::SUCCESS
            }
            Err(message) => {
                eprintln!("hwgw: {message}");
                ExitCode::FAILURE
            }
        },
        Err(e) => {
            eprintln!(
                "hwgw: {}: {e} (is hwgw running? `hwgw run` starts it)",
                path.display()
            );
            ExitCode::FAILURE
        }
    }
}

/// SIGHUP: reads the deployment again and applies what may change at run time.
fn reload_with(gw: &Gateway, config: Option<&PathBuf>, current: &mut Deployment) {
    let Some(path) = config else {
        tracing::warn!("SIGHUP: running the embedded default; there is no file to reload");
        return;
    };
    let new = match Deployment::load(path) {
        Ok((d, _)) => d,
        Err(e) => {
            tracing::error!(
                "SIGHUP: {} not reloaded, still running the previous version:\n{e}",
                path.display()
            );
            return;
        }
    };
    let (lines, applied) = gw.reload(current, &new);
    for line in lines {
        tracing::info!("SIGHUP: {line}");
    }
    // What was applied is now current; refused changes stay pending until a restart.
    for (cur, n) in current.components.iter_mut().zip(&new.components) {
        if applied.contains(&n.name) {
            cur.properties = n.properties.clone();
        }
    }
}

fn watch(path: PathBuf, component: String, port: String, count: Option<u64>) -> ExitCode {
    let mut req = json!({"id": 1, "cmd": "watch", "component": component, "port": port});
    if let Some(n) = count {
        req["count"] = json!(n);
    }
    let result = control::stream(&path, req, |line| {
        match (line.get("event"), line.get("error")) {
            (Some(ev), _) => println!("{}", ev["value"]),
            (_, Some(e)) => {
                eprintln!(
                    "hwgw: {}",
                    e.get("message").and_then(Value::as_str).unwrap_or("error")
                );
                return false;
            }
            _ => {}
        }
        true
    });
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("hwgw: {}: {e}", path.display());
            ExitCode::FAILURE
        }
    }
}

fn load(config: Option<&PathBuf>) -> Result<(Deployment, String, String), String> {
    match config {
        None => Deployment::parse(crate::DEMO, "<embedded demo>")
            .map(|d| (d, crate::DEMO.to_string(), "<embedded demo>".to_string()))
            .map_err(|e| e.to_string()),
        Some(p) => Deployment::load(p)
            .map(|(d, text)| (d, text, p.display().to_string()))
            .map_err(|e| e.to_string()),
    }
}

fn build(config: Option<&PathBuf>, types: &Types) -> Result<(Gateway, Deployment), String> {
    let (d, text, file) = load(config)?;
    let gw = Gateway::build(&d, &file, &text, types).map_err(|problems| {
        problems
            .iter()
            .map(|p| p.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    })?;
    Ok((gw, d))
}

fn check(config: PathBuf, types: &Types) -> ExitCode {
    match build(Some(&config), types) {
        Ok((gw, _)) => {
            print!("{}", gw.summary());
            println!("{}: ok", config.display());
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("{e}");
            ExitCode::FAILURE
        }
    }
}

fn run(config: Option<PathBuf>, socket: Option<PathBuf>, types: &Types) -> ExitCode {
    // Signals are taken by sigwait below: block them before any thread exists, so every
    // thread inherits the mask and none is interrupted.
    let mut signals = SigSet::empty();
    for s in [Signal::SIGTERM, Signal::SIGINT, Signal::SIGHUP] {
        signals.add(s);
    }
    if let Err(e) = signals.thread_block() {
        eprintln!("hwgw: cannot block signals: {e}");
        return ExitCode::FAILURE;
    }
    let (gw, mut d) = match build(config.as_ref(), types) {
        Ok(x) => x,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    let gw = Arc::new(gw);
    for line in gw.summary().lines() {
        tracing::info!("{line}");
    }
    let path = socket
        .or_else(|| d.control_socket.as_ref().map(PathBuf::from))
        .unwrap_or_else(control::default_socket);
    let server = match ControlServer::start(gw.clone(), &path) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("hwgw: control socket {}: {e}", path.display());
            return ExitCode::FAILURE;
        }
    };
    if let Err(e) = gw.start() {
        eprintln!("hwgw: {e}");
        for line in gw.shutdown() {
            tracing::info!("{line}");
        }
        return ExitCode::FAILURE;
    }
    tracing::info!("running; control socket {}", server.path().display());
    let status = format!(
        "running {} components; control socket {}",
        gw.runtime().components().len(),
        server.path().display()
    );
    if let Err(e) = sd_notify::notify(&[NotifyState::Ready, NotifyState::Status(&status)]) {
        tracing::warn!("cannot notify systemd: {e}");
    }
    let stop_watchdog = Arc::new(std::sync::atomic::AtomicBool::new(false));
    if let Some(interval) = sd_notify::watchdog_enabled() {
        tracing::info!("systemd watchdog every {interval:?}, fed while healthy");
        let (g, s) = (gw.clone(), stop_watchdog.clone());
        std::thread::spawn(move || watchdog(g, interval, s));
    }
    loop {
        match signals.wait() {
            Ok(Signal::SIGHUP) => reload_with(&gw, config.as_ref(), &mut d),
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
    drop(server);
    for line in gw.shutdown() {
        tracing::info!("{line}");
    }
    tracing::info!("stopped");
    ExitCode::SUCCESS
}
