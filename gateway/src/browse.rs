//! `hwgw browse`: an interactive console on a running gateway, in the spirit of the Orocos
//! TaskBrowser.
//!
//! At the top (`/`) it lists components; `cd NAME` enters one, where `ls` shows its ports
//! (with values), operations (with their documentation) and properties, and names can be
//! read, written and called directly. TAB completes commands and the names the gateway
//! reports at that moment; history is kept in `$XDG_STATE_HOME/hwgw/history` (or
//! `~/.local/state/hwgw/history`).
//!
//! ```text
//! hwgw:/> cd follow
//! hwgw:/follow> ls
//! hwgw:/follow> get out
//! hwgw:/follow> set gain 0.25
//! hwgw:/follow> call is_on
//! ```
//!
//! [`Browser`] holds the logic (a command line in, text out, completion candidates) so it can
//! be tested without a terminal; [`run`] is the terminal loop around it.

use crate::client::Client;
use crate::protocol::{ComponentEntry, Description, Request, StatusReport, Target, json_arg};
use crate::table;
use std::cell::RefCell;
use std::path::PathBuf;

/// Commands, for help and completion.
const COMMANDS: [(&str, &str); 22] = [
    (
        "ls",
        "list components, or the current component's interface",
    ),
    ("cd", "cd NAME enters a component; cd .. or cd / goes back"),
    ("get", "get NAME: a port's current value or a property"),
    (
        "set",
        "set NAME VALUE: write an input port or a property (VALUE is JSON)",
    ),
    (
        "call",
        "call OPERATION [ARG…]: call an operation (ARGs are JSON)",
    ),
    (
        "watch",
        "watch PORT [N]: print the next N (default 10) new values",
    ),
    (
        "status",
        "device health, card counters and component timing",
    ),
    ("devices", "every device name in the registry"),
    ("start", "start the current (or named) component"),
    ("stop", "stop the current (or named) component"),
    ("configure", "configure the current (or named) component"),
    ("recover", "recover the current (or named) component"),
    (
        "load",
        "load NAME TYPE [--period-ms MS] [--property K=V]…: a component into the running deployment",
    ),
    (
        "unload",
        "unload NAME: stopped, cleaned up, its connections closed",
    ),
    (
        "connect",
        "connect FROM TO [--policy JSON]: ports, prints the id",
    ),
    ("disconnect", "disconnect ID: close a connection"),
    (
        "set-period",
        "set-period NAME MS: a stopped component's period",
    ),
    (
        "set-priority",
        "set-priority NAME other|fifo [PRIO]: a stopped component's thread",
    ),
    ("changes", "the run-time changes since the file was read"),
    ("save", "save FILE: the running deployment into a new file"),
    ("help", "this list"),
    ("quit", "leave (also: exit, Ctrl-D)"),
];

/// The console's state: where it is and how to reach the gateway.
pub struct Browser {
    client: Client,
    cwd: Option<String>,
}

fn pretty(v: &serde_json::Value) -> String {
    serde_json::to_string_pretty(v).unwrap_or_default()
}

impl Browser {
    /// A console on the gateway at `socket`, at the top.
    pub fn new(socket: PathBuf) -> Self {
        Self::with_client(Client::new(socket))
    }

    /// A console through `client`, at the top.
    pub fn with_client(client: Client) -> Self {
        Browser { client, cwd: None }
    }

    /// The prompt: `hwgw:/> ` or `hwgw:/COMPONENT> `.
    pub fn prompt(&self) -> String {
        format!("hwgw:/{}> ", self.cwd.as_deref().unwrap_or(""))
    }

    fn ask(&self, req: &Request) -> Result<serde_json::Value, String> {
        self.client.request(req).map_err(|e| e.to_string())
    }

    fn component<'a>(&'a self, named: Option<&'a str>) -> Result<&'a str, String> {
        named
            .or(self.cwd.as_deref())
            .ok_or_else(|| "no component: cd into one or name it".to_string())
    }

    fn describe(&self, c: &str) -> Result<Description, String> {
        self.client
            .typed(&Request::Describe {
                component: c.to_string(),
            })
            .map_err(|e| e.to_string())
    }

    /// `name` in component `c` as a property when it is one, else as a port.
    fn target(&self, c: &str, name: &str) -> Result<Target, String> {
        let d = self.describe(c)?;
        Ok(if d.properties.iter().any(|p| p.path == name) {
            Target::Property(name.to_string())
        } else {
            Target::from_name(name)
        })
    }

    /// Runs one command line; returns the text to show, or `None` to leave.
    pub fn execute(&mut self, line: &str) -> Option<String> {
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some((&cmd, args)) = words.split_first() else {
            return Some(String::new());
        };
        let result = match cmd {
            "quit" | "exit" => return None,
            "help" => Ok(COMMANDS
                .iter()
                .map(|(c, d)| format!("{c:<10} {d}"))
                .collect::<Vec<_>>()
                .join("\n")),
            "ls" => self.ls(args.first().copied()),
            "cd" => self.cd(args.first().copied()),
            "get" => match args {
                [name] => self.get(name),
                _ => Err("usage: get NAME".into()),
            },
            "set" => match args {
                [name, value @ ..] if !value.is_empty() => self.set(name, &value.join(" ")),
                _ => Err("usage: set NAME VALUE".into()),
            },
            "call" => match args {
                [op, rest @ ..] => self.call(op, rest),
                _ => Err("usage: call OPERATION [ARG…]".into()),
            },
            "watch" => match args {
                [port] => self.watch(port, 10),
                [port, n] => n
                    .parse()
                    .map_err(|_| format!("{n:?}: expected a count"))
                    .and_then(|n| self.watch(port, n)),
                _ => Err("usage: watch PORT [N]".into()),
            },
            "status" => self
                .client
                .typed::<StatusReport>(&Request::Status)
                .map(|s| table::status(&s))
                .map_err(|e| e.to_string()),
            "devices" => self
                .client
                .typed::<crate::protocol::DeviceList>(&Request::Devices)
                .map(|d| table::devices(&d))
                .map_err(|e| e.to_string()),
            "start" | "stop" | "configure" | "recover" | "cleanup" => {
                self.component(args.first().copied()).and_then(|c| {
                    let req = serde_json::from_value::<Request>(
                        serde_json::json!({"cmd": cmd, "component": c}),
                    )
                    .map_err(|e| e.to_string())?;
                    self.ask(&req).map(|v| v.as_str().unwrap_or("").to_string())
                })
            }
            "load" | "unload" | "connect" | "disconnect" | "save" | "set-period"
            | "set-priority" => crate::cli_changes::parse(&words).and_then(|c| {
                crate::cli_changes::run(&self.client, c, true)
                    .map(Option::unwrap_or_default)
                    .map_err(|e| e.to_string())
            }),
            "changes" => self
                .client
                .typed::<Vec<String>>(&Request::Changes)
                .map(|l| l.join("\n"))
                .map_err(|e| e.to_string()),
            // In a component, a bare operation name calls it.
            op if self.cwd.is_some() => self.call(op, args),
            other => Err(format!("unknown command {other:?}; type help")),
        };
        Some(match result {
            Ok(text) => text,
            Err(e) => format!("error: {e}"),
        })
    }

    fn ls(&self, named: Option<&str>) -> Result<String, String> {
        let Some(c) = named.or(self.cwd.as_deref()) else {
            let list: Vec<ComponentEntry> = self
                .client
                .typed(&Request::Ls { all: false })
                .map_err(|e| e.to_string())?;
            return Ok(table::components(&list));
        };
        let d = self.describe(c)?;
        let values = self.client.port_values(c, &d);
        Ok(table::description(&d, &values))
    }

    fn cd(&mut self, to: Option<&str>) -> Result<String, String> {
        match to {
            None | Some("/") | Some("..") => {
                self.cwd = None;
                Ok(String::new())
            }
            Some(c) => {
                // Inside a component, its peers' aliases lead to them.
                let aliased = match &self.cwd {
                    Some(here) => self
                        .describe(here)?
                        .peers
                        .into_iter()
                        .find(|(a, _)| a == c)
                        .map(|(_, t)| t),
                    None => None,
                };
                let c = aliased.as_deref().unwrap_or(c);
                self.describe(c)?;
                self.cwd = Some(c.to_string());
                Ok(String::new())
            }
        }
    }

    fn get(&self, name: &str) -> Result<String, String> {
        let c = self.component(None)?;
        let target = self.target(c, name)?;
        self.ask(&Request::Get {
            component: c.to_string(),
            target,
        })
        .map(|v| pretty(&v))
    }

    fn set(&self, name: &str, value: &str) -> Result<String, String> {
        let c = self.component(None)?;
        let target = self.target(c, name)?;
        self.ask(&Request::Set {
            component: c.to_string(),
            target,
            value: json_arg(value),
        })
        .map(|_| String::new())
    }

    fn call(&self, op: &str, args: &[&str]) -> Result<String, String> {
        let c = self.component(None)?;
        self.ask(&Request::Call {
            component: c.to_string(),
            operation: op.to_string(),
            args: args.iter().map(|a| json_arg(a)).collect(),
        })
        .and_then(|v| {
            crate::client::call_result(&format!("{c}.{op}"), v).map_err(|e| e.to_string())
        })
        // An operation that answers nothing (a write done) shows nothing.
        .map(|v| {
            if v.is_null() {
                String::new()
            } else {
                pretty(&v)
            }
        })
    }

    fn watch(&self, port: &str, n: u64) -> Result<String, String> {
        let c = self.component(None)?;
        let mut lines = Vec::new();
        self.client
            .watch(
                c,
                port,
                Some(n),
                Some(self.client.timeout().max(crate::protocol::HEARTBEAT * 2)),
                |v| {
                    lines.push(v.to_string());
                    true
                },
            )
            .map_err(|e| e.to_string())?;
        Ok(lines.join("\n"))
    }

    /// Completion candidates for the word ending at `pos` in `line`: (start of the word,
    /// candidates). Asks the gateway for the names that exist now.
    pub fn complete(&self, line: &str, pos: usize) -> (usize, Vec<String>) {
        let head = &line[..pos.min(line.len())];
        let start = head.rfind(char::is_whitespace).map_or(0, |i| i + 1);
        let word = &head[start..];
        let before: Vec<&str> = head[..start].split_whitespace().collect();
        let commands = || COMMANDS.iter().map(|(c, _)| c.to_string());
        let names: Vec<String> = match (before.as_slice(), self.cwd.as_deref()) {
            ([], None) => commands().collect(),
            ([], Some(c)) => commands()
                .chain(self.names(c, false, true, false))
                .collect(),
            (["cd"] | ["ls"] | ["start"] | ["stop"] | ["configure"] | ["recover"], _) => {
                self.components()
            }
            (["get"] | ["watch"] | ["set"], Some(c)) => self.names(c, true, false, true),
            (["call"], Some(c)) => self.names(c, false, true, false),
            _ => Vec::new(),
        };
        let mut hits: Vec<String> = names.into_iter().filter(|n| n.starts_with(word)).collect();
        hits.sort();
        hits.dedup();
        (start, hits)
    }

    fn components(&self) -> Vec<String> {
        self.client
            .typed::<Vec<ComponentEntry>>(&Request::Ls { all: false })
            .map(|l| l.into_iter().map(|c| c.name).collect())
            .unwrap_or_default()
    }

    /// Names in component `c`: its ports, operations and properties, as asked.
    fn names(&self, c: &str, ports: bool, operations: bool, properties: bool) -> Vec<String> {
        let Ok(d) = self.describe(c) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        if ports {
            out.extend(d.ports.into_iter().map(|p| p.info.name));
        }
        if operations {
            out.extend(d.operations.into_iter().map(|o| o.name));
        }
        if properties {
            out.extend(d.properties.into_iter().map(|p| p.path));
        }
        out
    }
}

struct Helper(RefCell<Browser>);

impl rustyline::completion::Completer for Helper {
    type Candidate = String;
    fn complete(
        &self,
        line: &str,
        pos: usize,
        _: &rustyline::Context<'_>,
    ) -> rustyline::Result<(usize, Vec<String>)> {
        Ok(self.0.borrow().complete(line, pos))
    }
}
impl rustyline::hint::Hinter for Helper {
    type Hint = String;
}
impl rustyline::highlight::Highlighter for Helper {}
impl rustyline::validate::Validator for Helper {}
impl rustyline::Helper for Helper {}

fn history_file() -> Option<PathBuf> {
    let base = std::env::var_os("XDG_STATE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/state")))?;
    Some(base.join("hwgw/history"))
}

/// The interactive loop on a terminal.
pub fn run(client: Client) -> Result<(), String> {
    let browser = Browser::with_client(client);
    // Fail early, with a clear message, when nobody is listening.
    browser.ask(&Request::Ls { all: false })?;
    let mut editor = rustyline::Editor::<Helper, rustyline::history::DefaultHistory>::new()
        .map_err(|e| e.to_string())?;
    editor.set_helper(Some(Helper(RefCell::new(browser))));
    let history = history_file();
    if let Some(h) = &history {
        let _ = editor.load_history(h);
    }
    println!("hwgw browser: TAB completes, help lists commands, Ctrl-D leaves");
    loop {
        let prompt = editor
            .helper()
            .map(|h| h.0.borrow().prompt())
            .unwrap_or_default();
        match editor.readline(&prompt) {
            Ok(line) => {
                if !line.trim().is_empty() {
                    let _ = editor.add_history_entry(line.as_str());
                }
                let Some(h) = editor.helper() else { break };
                let out = h.0.borrow_mut().execute(&line);
                match out {
                    None => break,
                    Some(text) if text.is_empty() => {}
                    Some(text) => println!("{text}"),
                }
            }
            Err(rustyline::error::ReadlineError::Interrupted) => continue,
            Err(_) => break,
        }
    }
    if let Some(h) = &history {
        if let Some(dir) = h.parent() {
            let _ = std::fs::create_dir_all(dir);
        }
        let _ = editor.save_history(h);
    }
    Ok(())
}
