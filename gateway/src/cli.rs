//! The `hwgw` command line: `run`, `check`, and the one-shot commands that talk to a
//! running gateway. Lists print as aligned tables for people, or as JSON with `--json`
//! for scripts; `set` and `lifecycle` print nothing when they succeed (one line with
//! `--verbose`), `call` prints the operation's value or exits 1 with its error; no command
//! waits for a reply longer than `--timeout` (default 10 s). A user's own binary with
//! extra component types or drivers is `fn main() -> ExitCode { hwgw::cli::main(my_types) }`.

use crate::client::{Client, ClientError};
use crate::protocol::{ComponentEntry, Description, Request, StatusReport, Target, json_arg};
use crate::table;
use crate::types::Types;
use clap::{Parser, Subcommand};
use serde_json::Value;
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Parser)]
#[command(
    name = "hwgw",
    version,
    about = "Hardware-IO gateway: Orocos device interfaces over Linux buses"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Control socket path (default: the service's /run/hwgw/hwgw.sock, or a user's own;
    /// see `hwgw::socket`).
    #[arg(long, global = true)]
    socket: Option<PathBuf>,
    /// Print the gateway's answer as JSON (for scripts) instead of a table.
    #[arg(long, global = true)]
    json: bool,
    /// Say what a command that succeeded did (`set`, `lifecycle`: one line).
    #[arg(long, short, global = true)]
    verbose: bool,
    /// Seconds to wait for a reply (default 10).
    #[arg(long, global = true, value_name = "SECONDS")]
    timeout: Option<f64>,
}

#[derive(Subcommand)]
enum Command {
    /// Run a deployment (with no file: the embedded demo on simulated cards).
    Run {
        /// The deployment file.
        config: Option<PathBuf>,
    },
    /// Check a deployment file: print every error and exit 1, or exit 0.
    Check {
        /// The deployment file.
        config: PathBuf,
    },
    /// List components, or describe one (`B/follow`: one of gateway B, through Zenoh).
    Ls {
        /// A component to describe.
        component: Option<String>,
        /// Every gateway's components (Zenoh), each named `gateway/component`.
        #[arg(long, conflicts_with = "component")]
        all: bool,
        /// The run-time changes (load, unload, connect, disconnect) since the deployment
        /// file was read.
        #[arg(long, conflicts_with_all = ["component", "all"])]
        changes: bool,
    },
    #[command(flatten)]
    Change(crate::cli_changes::ChangeCommand),
    /// An interactive console on a running gateway (cd, ls, get, set, call, TAB completion).
    Browse,
    /// Device health, card counters, component states and timing.
    Status {
        /// Also draw every activity's live lateness histogram into this new PNG or SVG.
        #[arg(long, value_name = "FILE")]
        plot: Option<PathBuf>,
    },
    /// Record ports and activity steps of the running gateway into a new MCAP file
    /// (Foxglove and PlotJuggler open it): until --duration or Ctrl-C, or the window
    /// around --trigger.
    Record(crate::recorder::cli::RecordArgs),
    /// Draw a recording into a new PNG or SVG file: port values, the activities' timing
    /// diagram, or their lateness histograms.
    Plot {
        /// The MCAP recording.
        recording: PathBuf,
        /// The new picture (.png or .svg).
        #[arg(long, short)]
        output: PathBuf,
        /// What to draw.
        #[arg(long, value_enum, default_value = "values")]
        kind: crate::recorder::cli::PlotKind,
        /// Only these ports (values); repeat for more.
        #[arg(long = "port", value_name = "PORT")]
        ports: Vec<String>,
        /// Start this long after the recording's start (values, timing).
        #[arg(long, value_parser = crate::recorder::cli::parse_duration)]
        from: Option<Duration>,
        /// Draw this long (values, timing).
        #[arg(long, value_parser = crate::recorder::cli::parse_duration)]
        span: Option<Duration>,
        /// Width in pixels.
        #[arg(long, default_value_t = 1280)]
        width: u32,
        /// Height in pixels.
        #[arg(long, default_value_t = 720)]
        height: u32,
    },
    /// Print each new value of an output port as it comes (Ctrl-C to stop).
    Watch {
        component: String,
        port: String,
        /// Stop after this many values.
        #[arg(long)]
        count: Option<u64>,
    },
    /// Run a lifecycle command on a component: configure, start, stop, cleanup, recover.
    Lifecycle { command: String, component: String },
    /// List the devices in the registry.
    Devices,
    /// The real-time log's level of every component and card, or set one's: `hwgw log
    /// meter debug` (levels: off, error, warn, info, debug, trace).
    Log {
        /// The component or card that logs.
        component: Option<String>,
        /// Its new level.
        #[arg(requires = "component")]
        level: Option<String>,
    },
    /// Read the deployment file again and rebuild only what changed (as `systemctl reload
    /// hwgw` does): prints what was applied and what needs a restart; with an error in the
    /// file nothing changes, the errors are printed and the exit code is 1.
    Reload,
    /// Read a port's value (an output's last value, an input's read-back) or a property.
    Get {
        component: String,
        /// A port name, or `property:NAME`.
        name: String,
    },
    /// Write an input port or a property (VALUE is JSON; anything else is taken as text).
    Set {
        component: String,
        /// A port name, or `property:NAME`.
        name: String,
        /// The value (JSON; anything else is taken as text). Negative numbers (-1e-300
        /// too) are values.
        #[arg(allow_hyphen_values = true)]
        value: String,
    },
    /// Call an operation (each ARG is JSON; anything else is taken as text).
    Call {
        component: String,
        operation: String,
        /// Negative numbers are arguments, not options (one in exponent form after `--`:
        /// `call x write 0 -- -1e-300`).
        #[arg(allow_negative_numbers = true)]
        args: Vec<String>,
    },
    /// Write the manual pages and shell completions into DIR (the Debian package's build).
    #[command(hide = true)]
    GenerateAssets {
        /// Where: DIR/man/*.1 and DIR/completions/.
        dir: PathBuf,
    },
}

/// The command line's clap definition (the package's manual pages and completions are
/// generated from it: `hwgw generate-assets`).
pub(crate) fn command() -> clap::Command {
    <Cli as clap::CommandFactory>::command()
}

/// The log filter without `RUST_LOG`: info; the real-time log (target `hwgw_rt`) at every
/// level, each component's own level (`hwgw log`) deciding; and async-opcua's crates (the
/// OPC UA server) from warnings up — they log every connection at info.
const DEFAULT_LOG: &str = "info,hwgw_rt=trace,opcua_server=warn,opcua_core=warn,opcua_crypto=warn,opcua_types=warn,opcua_nodes=warn";

/// Logs to the journal when systemd runs us (JOURNAL_STREAM is set), else to stderr.
fn init_logging() {
    use tracing_subscriber::prelude::*;
    let filter = || {
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| DEFAULT_LOG.into())
    };
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

/// Prints `text` on standard output; false when nobody reads it any more (a closed pipe:
/// `hwgw watch … | head -2`), which ends the command quietly.
fn print(text: &str) -> bool {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{text}").and_then(|()| out.flush()).is_ok()
}

fn pretty(v: &Value) -> String {
    serde_json::to_string_pretty(v).unwrap_or_default()
}

/// Runs the command line with the component and driver `types` available to deployments.
pub fn main(types: Types) -> ExitCode {
    init_logging();
    let cli = Cli::parse();
    let path = cli
        .socket
        .clone()
        .unwrap_or_else(crate::socket::default_client_socket);
    let mut client = Client::new(path.clone());
    if let Some(s) = cli.timeout {
        match Duration::try_from_secs_f64(s) {
            Ok(d) if !d.is_zero() => client = client.with_timeout(d),
            _ => {
                eprintln!("hwgw: --timeout {s}: expected a number of seconds above 0");
                return ExitCode::FAILURE;
            }
        }
    }
    let result = match cli.command {
        Command::Run { config } => return crate::serve::run(config, cli.socket, &types),
        Command::Check { config } => return crate::serve::check(config, &types),
        Command::GenerateAssets { dir } => return crate::assets::run(command(), &dir),
        Command::Browse => {
            return match crate::browse::run(client) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("hwgw: {e}");
                    ExitCode::FAILURE
                }
            };
        }
        Command::Watch {
            component,
            port,
            count,
        } => {
            // Values come when they come; the gateway's heartbeat keeps a quiet watch
            // alive, and a gateway silent for longer than --timeout is taken for stuck.
            let silence = client.timeout().max(crate::protocol::HEARTBEAT * 2);
            client
                .watch(&component, &port, count, Some(silence), |v| {
                    print(&v.to_string())
                })
                .map(|_| None)
        }
        Command::Record(args) => {
            return finish(crate::recorder::cli::record(&client, args).map_err(|e| e.to_string()));
        }
        Command::Plot {
            recording,
            output,
            kind,
            ports,
            from,
            span,
            width,
            height,
        } => {
            let frame = plot::Frame {
                path: &output,
                size: plot::Size { width, height },
            };
            let span = plot::Span {
                from_s: from.map_or(0.0, |d| d.as_secs_f64()),
                span_s: span.map(|d| d.as_secs_f64()),
            };
            return finish(crate::recorder::cli::plot(
                &recording, kind, &ports, span, &frame,
            ));
        }
        Command::Status { plot: Some(output) } => {
            let frame = plot::Frame {
                path: &output,
                size: plot::Size::default(),
            };
            return finish(crate::recorder::cli::status_plot(&client, &frame));
        }
        command => one_shot(
            &client,
            command,
            Form {
                json: cli.json,
                verbose: cli.verbose,
            },
        ),
    };
    match result {
        Ok(Some(text)) => {
            print(&text);
            ExitCode::SUCCESS
        }
        Ok(None) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("hwgw: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Prints what a command says on success, or its error, as the exit code says.
fn finish(result: Result<String, String>) -> ExitCode {
    match result {
        Ok(text) => {
            print(&text);
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("hwgw: {e}");
            ExitCode::FAILURE
        }
    }
}

/// How a one-shot command prints its answer.
#[derive(Clone, Copy)]
struct Form {
    /// The gateway's answer as JSON.
    json: bool,
    /// A line for a command that otherwise prints nothing.
    verbose: bool,
}

/// `hwgw log [COMPONENT [LEVEL]]`: the real-time log's levels, one set first.
fn log_levels(
    client: &Client,
    component: Option<String>,
    level: Option<String>,
    json: bool,
) -> Result<String, ClientError> {
    let level = match level.as_deref().map(str::parse::<rtt::log::Level>) {
        Some(Err(e)) => {
            return Err(ClientError::Refused(crate::protocol::ErrorBody {
                kind: crate::protocol::ErrorKind::BadRequest,
                message: e.to_string(),
            }));
        }
        Some(Ok(l)) => Some(l),
        None => None,
    };
    let levels: crate::protocol::LogLevels = client.typed(&Request::Log { component, level })?;
    Ok(if json {
        pretty(&serde_json::to_value(&levels).unwrap_or_default())
    } else {
        table::log_levels(&levels)
    })
}

/// A one-shot command: the text to print.
fn one_shot(client: &Client, command: Command, form: Form) -> Result<Option<String>, ClientError> {
    let json = form.json;
    let text = match command {
        Command::Ls { changes: true, .. } => {
            let list: Vec<String> = client.typed(&Request::Changes)?;
            if json {
                pretty(&serde_json::to_value(&list).unwrap_or_default())
            } else {
                list.join("\n")
            }
        }
        Command::Change(c) => return crate::cli_changes::run(client, c, form.verbose),
        Command::Ls {
            component: None,
            all,
            ..
        } => {
            let list: Vec<ComponentEntry> = client.typed(&Request::Ls { all })?;
            if json {
                pretty(&serde_json::to_value(&list).unwrap_or_default())
            } else {
                table::components(&list)
            }
        }
        Command::Ls {
            component: Some(c), ..
        } => {
            let req = Request::Describe {
                component: c.clone(),
            };
            if json {
                pretty(&client.request(&req)?)
            } else {
                let d: Description = client.typed(&req)?;
                let values = client.port_values(&c, &d);
                table::description(&d, &values)
            }
        }
        Command::Status { .. } => {
            let s: StatusReport = client.typed(&Request::Status)?;
            if json {
                pretty(&serde_json::to_value(&s).unwrap_or_default())
            } else {
                table::status(&s)
            }
        }
        Command::Log { component, level } => log_levels(client, component, level, json)?,
        Command::Devices => {
            let list: crate::protocol::DeviceList = client.typed(&Request::Devices)?;
            if json {
                pretty(&serde_json::to_value(&list).unwrap_or_default())
            } else {
                table::devices(&list)
            }
        }
        Command::Reload => {
            let report: crate::protocol::ReloadReport = client.typed(&Request::Reload)?;
            let text = if json {
                pretty(&serde_json::to_value(&report).unwrap_or_default())
            } else {
                table::reload(&report)
            };
            if report.errors.is_empty() {
                text
            } else {
                // The report all the same (JSON on stdout for scripts), and exit 1.
                if json {
                    print(&text);
                }
                return Err(ClientError::Refused(crate::protocol::ErrorBody {
                    kind: crate::protocol::ErrorKind::Failed,
                    message: if json { "reload failed".into() } else { text },
                }));
            }
        }
        Command::Lifecycle { command, component } => {
            return lifecycle(client, &command, &component, form);
        }
        Command::Get { component, name } => pretty(&client.request(&Request::Get {
            component,
            target: Target::from_name(&name),
        })?),
        Command::Set {
            component,
            name,
            value,
        } => return set(client, component, &name, &value, form),
        Command::Call {
            component,
            operation,
            args,
        } => return call(client, component, operation, &args, form),
        Command::Run { .. }
        | Command::Check { .. }
        | Command::Browse
        | Command::Watch { .. }
        | Command::Record(_)
        | Command::Plot { .. }
        | Command::GenerateAssets { .. } => {
            return Ok(None);
        }
    };
    Ok(Some(text))
}

/// `lifecycle COMMAND COMPONENT`: nothing on success, the new state with `--verbose`.
fn lifecycle(
    client: &Client,
    command: &str,
    component: &str,
    form: Form,
) -> Result<Option<String>, ClientError> {
    let req: Request = serde_json::from_value(
        serde_json::json!({"cmd": command, "component": component}),
    )
    .ok()
    .filter(|r| {
        matches!(
            r,
            Request::Configure { .. }
                | Request::Start { .. }
                | Request::Stop { .. }
                | Request::Cleanup { .. }
                | Request::Recover { .. }
        )
    })
    .ok_or_else(|| {
        ClientError::Refused(crate::protocol::ErrorBody {
            kind: crate::protocol::ErrorKind::BadRequest,
            message: format!(
                "{command:?} is not a lifecycle command: configure, start, stop, cleanup or recover"
            ),
        })
    })?;
    let state = client.request(&req)?;
    Ok(if form.json {
        Some(pretty(&state))
    } else if form.verbose {
        Some(format!(
            "{component}: {}",
            state.as_str().unwrap_or_default()
        ))
    } else {
        None
    })
}

/// `set COMPONENT NAME VALUE`: nothing on success, what was written with `--verbose`.
fn set(
    client: &Client,
    component: String,
    name: &str,
    value: &str,
    form: Form,
) -> Result<Option<String>, ClientError> {
    // The answer is null: a set that returns wrote its value (an output's write reached
    // its device); a refused one is an error, and the exit code says so.
    let value = json_arg(value);
    let answer = client.request(&Request::Set {
        component: component.clone(),
        target: Target::from_name(name),
        value: value.clone(),
    })?;
    Ok(if form.json {
        Some(pretty(&answer))
    } else if form.verbose {
        Some(format!("{component}.{name} = {value}"))
    } else {
        None
    })
}

/// The arguments of a call as JSON, each as its operation declares it: an argument the
/// operation takes as a string is the text typed (`22F190`, `1001`: hex, not a number; a
/// JSON string literal is its content); the others are JSON, else text. An operation the
/// gateway cannot describe gets JSON-else-text throughout.
fn call_args(client: &Client, component: &str, operation: &str, args: &[String]) -> Vec<Value> {
    let types: Vec<String> = client
        .typed::<Description>(&Request::Describe {
            component: component.to_string(),
        })
        .ok()
        .and_then(|d| d.operations.into_iter().find(|o| o.name == operation))
        .map(|o| o.args.into_iter().map(|a| a.type_name).collect())
        .unwrap_or_default();
    args.iter()
        .enumerate()
        .map(
            |(i, a)| match (types.get(i).map(String::as_str), json_arg(a)) {
                (_, v @ Value::String(_)) => v,
                (Some("string"), _) => Value::String(a.clone()),
                (_, v) => v,
            },
        )
        .collect()
}

/// `call COMPONENT OPERATION ARGS…`: the operation's value (nothing for none), or its
/// error as the command's; `--json` prints the answer as the gateway gave it.
fn call(
    client: &Client,
    component: String,
    operation: String,
    args: &[String],
    form: Form,
) -> Result<Option<String>, ClientError> {
    let what = format!("{component}.{operation}");
    let args = call_args(client, &component, &operation, args);
    let answer = client.request(&Request::Call {
        component,
        operation,
        args,
    })?;
    if form.json {
        // The machine form: `{"Ok": …}` or `{"Err": …}`, and the exit code as the call went.
        print(&pretty(&answer));
        return crate::client::call_result(&what, answer).map(|_| None);
    }
    Ok(match crate::client::call_result(&what, answer)? {
        // An operation that answers nothing (a write done) prints nothing.
        Value::Null => None,
        value => Some(pretty(&value)),
    })
}
