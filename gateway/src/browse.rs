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

use crate::control;
use serde_json::{Value, json};
use std::cell::RefCell;
use std::path::PathBuf;

/// Commands, for help and completion.
const COMMANDS: [(&str, &str); 14] = [
    (
        "ls",
        "list components, or the current component's interface",
    ),
    ("cd", "cd NAME enters a component; cd .. or cd / goes back"),
    ("get", "get NAME: an output port's last value or a property"),
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
    ("status", "device health and component timing"),
    ("devices", "every device name in the registry"),
    ("start", "start the current (or named) component"),
    ("stop", "stop the current (or named) component"),
    ("configure", "configure the current (or named) component"),
    ("recover", "recover the current (or named) component"),
    ("help", "this list"),
    ("quit", "leave (also: exit, Ctrl-D)"),
];

/// The console's state: where it is and how to reach the gateway.
pub struct Browser {
    socket: PathBuf,
    cwd: Option<String>,
}

fn pretty(v: &Value) -> String {
    serde_json::to_string_pretty(v).unwrap_or_default()
}

impl Browser {
    /// A console on the gateway at `socket`, at the top.
    pub fn new(socket: PathBuf) -> Self {
        Browser { socket, cwd: None }
    }

    /// The prompt: `hwgw:/> ` or `hwgw:/COMPONENT> `.
    pub fn prompt(&self) -> String {
        format!("hwgw:/{}> ", self.cwd.as_deref().unwrap_or(""))
    }

    fn ask(&self, req: Value) -> Result<Value, String> {
        let reply = control::request(&self.socket, req)
            .map_err(|e| format!("{}: {e}", self.socket.display()))?;
        control::outcome(&reply)
    }

    fn component<'a>(&'a self, named: Option<&'a str>) -> Result<&'a str, String> {
        named
            .or(self.cwd.as_deref())
            .ok_or_else(|| "no component: cd into one or name it".to_string())
    }

    fn describe(&self, c: &str) -> Result<Value, String> {
        self.ask(json!({"cmd": "describe", "component": c}))
    }

    /// Whether `name` in component `c` is a property (else a port).
    fn is_property(&self, c: &str, name: &str) -> Result<bool, String> {
        let d = self.describe(c)?;
        let props = d["properties"].as_array().cloned().unwrap_or_default();
        Ok(props.iter().any(|p| p["path"] == name))
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
            "status" => self.ask(json!({"cmd": "status"})).map(|v| pretty(&v)),
            "devices" => self.ask(json!({"cmd": "devices"})).map(|v| {
                v.as_array()
                    .map(|a| {
                        a.iter()
                            .map(|d| {
                                format!(
                                    "{:<12} {}",
                                    d["interface"].as_str().unwrap_or(""),
                                    d["name"].as_str().unwrap_or("")
                                )
                            })
                            .collect::<Vec<_>>()
                            .join("\n")
                    })
                    .unwrap_or_default()
            }),
            "start" | "stop" | "configure" | "recover" | "cleanup" => self
                .component(args.first().copied())
                .and_then(|c| self.ask(json!({"cmd": cmd, "component": c})))
                .map(|v| v.as_str().unwrap_or("").to_string()),
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
            let list = self.ask(json!({"cmd": "ls"}))?;
            return Ok(list
                .as_array()
                .map(|a| {
                    a.iter()
                        .map(|c| {
                            format!(
                                "{:<24} {}",
                                c["name"].as_str().unwrap_or(""),
                                c["state"].as_str().unwrap_or("")
                            )
                        })
                        .collect::<Vec<_>>()
                        .join("\n")
                })
                .unwrap_or_default());
        };
        let d = self.describe(c)?;
        let mut out = vec![format!("{c} [{}]", d["state"].as_str().unwrap_or(""))];
        out.push("ports:".into());
        for p in d["ports"].as_array().into_iter().flatten() {
            let name = p["name"].as_str().unwrap_or("");
            let value = if p["direction"] == "output" {
                self.ask(json!({"cmd": "get", "component": c, "port": name}))
                    .map(|v| v.to_string())
                    .unwrap_or_default()
            } else {
                String::new()
            };
            out.push(format!(
                "  {:<3} {:<16} {:<8} {:<12} {}",
                if p["direction"] == "output" {
                    "out"
                } else {
                    "in"
                },
                name,
                p["type_name"].as_str().unwrap_or(""),
                value,
                p["doc"].as_str().unwrap_or("")
            ));
        }
        out.push("operations:".into());
        for o in d["operations"].as_array().into_iter().flatten() {
            let args: Vec<String> = o["args"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|a| {
                    format!(
                        "{}: {}",
                        a["name"].as_str().unwrap_or(""),
                        a["type_name"].as_str().unwrap_or("")
                    )
                })
                .collect();
            out.push(format!(
                "  {}({}) -> {}  {}",
                o["name"].as_str().unwrap_or(""),
                args.join(", "),
                o["result"].as_str().unwrap_or(""),
                o["doc"].as_str().unwrap_or("")
            ));
        }
        out.push("properties:".into());
        for p in d["properties"].as_array().into_iter().flatten() {
            out.push(format!(
                "  {:<16} = {:<12} {}",
                p["path"].as_str().unwrap_or(""),
                p["value"].to_string(),
                p["doc"].as_str().unwrap_or("")
            ));
        }
        Ok(out.join("\n"))
    }

    fn cd(&mut self, to: Option<&str>) -> Result<String, String> {
        match to {
            None | Some("/") | Some("..") => {
                self.cwd = None;
                Ok(String::new())
            }
            Some(c) => {
                self.describe(c)?;
                self.cwd = Some(c.to_string());
                Ok(String::new())
            }
        }
    }

    fn get(&self, name: &str) -> Result<String, String> {
        let c = self.component(None)?;
        let key = if self.is_property(c, name)? {
            "property"
        } else {
            "port"
        };
        self.ask(json!({"cmd": "get", "component": c, key: name}))
            .map(|v| pretty(&v))
    }

    fn set(&self, name: &str, value: &str) -> Result<String, String> {
        let c = self.component(None)?;
        let key = if self.is_property(c, name)? {
            "property"
        } else {
            "port"
        };
        let v: Value =
            serde_json::from_str(value).unwrap_or_else(|_| Value::String(value.to_string()));
        self.ask(json!({"cmd": "set", "component": c, key: name, "value": v}))
            .map(|_| String::new())
    }

    fn call(&self, op: &str, args: &[&str]) -> Result<String, String> {
        let c = self.component(None)?;
        let args: Vec<Value> = args
            .iter()
            .map(|a| serde_json::from_str(a).unwrap_or_else(|_| Value::String(a.to_string())))
            .collect();
        self.ask(json!({"cmd": "call", "component": c, "operation": op, "args": args}))
            .map(|v| pretty(&v))
    }

    fn watch(&self, port: &str, n: u64) -> Result<String, String> {
        let c = self.component(None)?;
        let mut lines = Vec::new();
        let mut error = None;
        control::stream(
            &self.socket,
            json!({"id": 1, "cmd": "watch", "component": c, "port": port, "count": n}),
            |v| {
                if let Some(e) = v.get("error") {
                    error = Some(e["message"].as_str().unwrap_or("error").to_string());
                    return false;
                }
                if let Some(ev) = v.get("event") {
                    lines.push(ev["value"].to_string());
                }
                true
            },
        )
        .map_err(|e| e.to_string())?;
        match error {
            Some(e) => Err(e),
            None => Ok(lines.join("\n")),
        }
    }

    /// Completion candidates for the word ending at `pos` in `line`: (start of the word,
    /// candidates). Asks the gateway for the names that exist now.
    pub fn complete(&self, line: &str, pos: usize) -> (usize, Vec<String>) {
        let head = &line[..pos.min(line.len())];
        let start = head.rfind(char::is_whitespace).map_or(0, |i| i + 1);
        let word = &head[start..];
        let before: Vec<&str> = head[..start].split_whitespace().collect();
        let names: Vec<String> = match (before.as_slice(), self.cwd.as_deref()) {
            ([], None) => COMMANDS.iter().map(|(c, _)| c.to_string()).collect(),
            ([], Some(c)) => {
                let mut v: Vec<String> = COMMANDS.iter().map(|(c, _)| c.to_string()).collect();
                v.extend(self.names(c, &["operations"]));
                v
            }
            (["cd"] | ["ls"] | ["start"] | ["stop"] | ["configure"] | ["recover"], _) => {
                self.components()
            }
            (["get"], Some(c)) | (["watch"], Some(c)) => self.names(c, &["ports", "properties"]),
            (["set"], Some(c)) => self.names(c, &["ports", "properties"]),
            (["call"], Some(c)) => self.names(c, &["operations"]),
            _ => Vec::new(),
        };
        let mut hits: Vec<String> = names.into_iter().filter(|n| n.starts_with(word)).collect();
        hits.sort();
        hits.dedup();
        (start, hits)
    }

    fn components(&self) -> Vec<String> {
        self.ask(json!({"cmd": "ls"}))
            .ok()
            .and_then(|v| {
                v.as_array().map(|a| {
                    a.iter()
                        .filter_map(|c| c["name"].as_str().map(String::from))
                        .collect()
                })
            })
            .unwrap_or_default()
    }

    fn names(&self, c: &str, sections: &[&str]) -> Vec<String> {
        let Ok(d) = self.describe(c) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        for s in sections {
            let key = if *s == "properties" { "path" } else { "name" };
            out.extend(
                d[*s]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|x| x[key].as_str().map(String::from)),
            );
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
pub fn run(socket: PathBuf) -> Result<(), String> {
    let browser = Browser::new(socket);
    // Fail early, with a clear message, when nobody is listening.
    browser.ask(json!({"cmd": "ls"}))?;
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
