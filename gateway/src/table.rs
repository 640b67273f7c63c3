//! What the CLI and the browser print for people: aligned tables and a component's
//! interface, from the protocol's typed answers (`--json` prints the answers instead).

use crate::protocol::{ComponentEntry, Description, StatusReport};
use device_interface::RegistryEntry;
use serde_json::Value;

/// `rows` under `headers`, each column as wide as its widest cell, two spaces apart; the
/// last column is not padded.
pub fn table(headers: &[&str], rows: &[Vec<String>]) -> String {
    let mut all = vec![headers.iter().map(|h| h.to_string()).collect()];
    all.extend(rows.iter().cloned());
    align(&all).join("\n")
}

/// `rows` as lines, each column as wide as its widest cell, two spaces apart; the last
/// column is not padded.
fn align(rows: &[Vec<String>]) -> Vec<String> {
    let mut widths: Vec<usize> = Vec::new();
    for row in rows {
        for (i, cell) in row.iter().enumerate() {
            let n = cell.chars().count();
            match widths.get_mut(i) {
                Some(w) => *w = (*w).max(n),
                None => widths.push(n),
            }
        }
    }
    rows.iter()
        .map(|cells| {
            let last = cells.len().saturating_sub(1);
            let mut s = String::new();
            for (i, c) in cells.iter().enumerate() {
                s.push_str(c);
                if i != last {
                    let pad = widths[i].saturating_sub(c.chars().count());
                    s.push_str(&" ".repeat(pad + 2));
                }
            }
            s.trim_end().to_string()
        })
        .collect()
}

/// An operation's signature in the protocol's types: `read(channel: u32) -> f64`, or
/// `write(channel: u32, value: f64)` for one that answers nothing.
pub fn signature(o: &rtt::operation::OperationInfo) -> String {
    let args: Vec<String> = o
        .args
        .iter()
        .map(|a| format!("{}: {}", a.name, a.type_name))
        .collect();
    if o.result.is_empty() {
        format!("{}({})", o.name, args.join(", "))
    } else {
        format!("{}({}) -> {}", o.name, args.join(", "), o.result)
    }
}

/// `hwgw ls`: every component and its state.
pub fn components(list: &[ComponentEntry]) -> String {
    let rows: Vec<Vec<String>> = list
        .iter()
        .map(|c| vec![c.name.clone(), flagged(c.state, c.warning)])
        .collect();
    table(&["COMPONENT", "STATE"], &rows)
}

/// A state, with the warning flag when it is up: `running (warning)`.
fn flagged(s: rtt::TaskState, warning: bool) -> String {
    if warning {
        format!("{} (warning)", state(s))
    } else {
        state(s)
    }
}

/// `hwgw devices`: every registry name.
pub fn devices(list: &[RegistryEntry]) -> String {
    let rows: Vec<Vec<String>> = list
        .iter()
        .map(|e| {
            vec![
                e.interface.to_string(),
                e.info.name.clone(),
                e.info.owner.clone(),
                e.info.alias_of.clone().unwrap_or_default(),
            ]
        })
        .collect();
    table(&["INTERFACE", "NAME", "CARD", "ALIAS OF"], &rows)
}

/// The real-time log's levels, then its counters.
pub fn log_levels(levels: &crate::protocol::LogLevels) -> String {
    let rows: Vec<Vec<String>> = levels
        .areas
        .iter()
        .map(|a| vec![a.name.clone(), a.level.to_string()])
        .collect();
    let c = levels.counters;
    format!(
        "{}\nreal-time log: {} written, {} dropped (queue full), {} waiting",
        table(&["COMPONENT", "LEVEL"], &rows),
        c.written,
        c.dropped,
        c.queued
    )
}

fn state(s: rtt::TaskState) -> String {
    serde_json::to_value(s)
        .ok()
        .and_then(|v| v.as_str().map(String::from))
        .unwrap_or_else(|| s.to_string())
}

/// A duration in µs for people: `850 µs`, `12.3 ms`, `1.20 s`.
fn micros(us: f64) -> String {
    if us < 1000.0 {
        format!("{us:.0} µs")
    } else if us < 1e6 {
        format!("{:.1} ms", us / 1e3)
    } else {
        format!("{:.2} s", us / 1e6)
    }
}

/// A JSON value, compact, strings without quotes.
fn plain(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// A counter that is a list of records (a CAN card's messages) as a table of its own, a
/// column a field (named after the first record's); `None` for any other value.
fn rows_of(v: &Value) -> Option<String> {
    let list = v.as_array()?;
    let first = list.first()?.as_object()?;
    let columns: Vec<String> = first.keys().map(|k| k.to_uppercase()).collect();
    let rows: Vec<Vec<String>> = list
        .iter()
        .map(|r| {
            first
                .keys()
                .map(|k| match r.get(k) {
                    None | Some(Value::Null) => "-".into(),
                    Some(Value::Number(n)) if n.is_f64() => {
                        n.as_f64().map_or(n.to_string(), |x| format!("{x:.1}"))
                    }
                    Some(Value::Array(a)) => a.iter().map(plain).collect::<Vec<_>>().join(","),
                    Some(x) => plain(x),
                })
                .collect()
        })
        .collect();
    let columns: Vec<&str> = columns.iter().map(String::as_str).collect();
    Some(table(&columns, &rows))
}

/// `hwgw status`: health, then devices, cards and components.
pub fn status(s: &StatusReport) -> String {
    let mut out = vec![format!("health: {}", s.health), String::new()];
    let devices: Vec<Vec<String>> = s
        .devices
        .iter()
        .map(|d| {
            vec![
                d.name.clone(),
                d.interface.to_string(),
                d.status.to_string(),
                d.age_s.map_or("-".into(), |a| micros(a * 1e6)),
                d.last_error.clone().unwrap_or_default(),
            ]
        })
        .collect();
    out.push(table(
        &["DEVICE", "INTERFACE", "STATUS", "AGE", "LAST ERROR"],
        &devices,
    ));
    if !s.cards.is_empty() {
        out.push(String::new());
        let mut lists = Vec::new();
        let cards: Vec<Vec<String>> = s
            .cards
            .iter()
            .map(|c| {
                let counters: Vec<String> = c
                    .status
                    .counters
                    .iter()
                    .filter_map(|(k, v)| match rows_of(v) {
                        Some(rows) => {
                            lists.push(format!("{} {k}:\n{}", c.name, rows));
                            None
                        }
                        None => Some(format!("{k}={}", plain(v))),
                    })
                    .collect();
                vec![
                    c.name.clone(),
                    c.driver.clone(),
                    c.status.bus.clone(),
                    counters.join(" "),
                ]
            })
            .collect();
        out.push(table(&["CARD", "DRIVER", "BUS", "COUNTERS"], &cards));
        for l in lists {
            out.push(String::new());
            out.push(l);
        }
    }
    if !s.servers.is_empty() {
        out.push(String::new());
        let servers: Vec<Vec<String>> = s
            .servers
            .iter()
            .map(|v| {
                let counters: Vec<String> = v
                    .status
                    .counters
                    .iter()
                    .map(|(k, x)| format!("{k}={}", plain(x)))
                    .collect();
                vec![v.name.clone(), v.status.bus.clone(), counters.join(" ")]
            })
            .collect();
        out.push(table(&["SERVER", "LISTEN", "COUNTERS"], &servers));
    }
    out.push(String::new());
    let components: Vec<Vec<String>> = s
        .components
        .iter()
        .map(|c| {
            vec![
                c.name.clone(),
                flagged(c.state, c.counters.warning),
                if c.healthy { "ok" } else { "overrunning" }.into(),
                c.steps.to_string(),
                c.overruns.to_string(),
                micros(c.lateness_p99_us),
                micros(c.step_mean_us),
                if c.realtime { "fifo" } else { "other" }.into(),
                c.counters.last_error.clone().unwrap_or_default(),
            ]
        })
        .collect();
    out.push(table(
        &[
            "COMPONENT",
            "STATE",
            "HEALTH",
            "STEPS",
            "OVERRUNS",
            "LATE P99",
            "STEP MEAN",
            "SCHED",
            "LAST ERROR",
        ],
        &components,
    ));
    out.push(String::new());
    let c = &s.control;
    out.push(format!(
        "control socket: {} clients connected ({} since start, {} turned away, {} idle closed), {} requests ({} errors, {} under way), {} accept failures",
        c.connected,
        c.clients,
        c.refused,
        c.idle_closed,
        c.requests,
        c.errors,
        c.under_way,
        c.accept_failures
    ));
    out.join("\n")
}

/// A component's interface: its ports (with `values`, one per port, where known), its
/// operations and its properties.
pub fn description(d: &Description, values: &[Option<Value>]) -> String {
    let mut out = vec![format!("{} [{}]", d.name, state(d.state))];
    out.push("ports:".into());
    let mut rows = Vec::new();
    for (i, p) in d.ports.iter().enumerate() {
        let current = values.get(i).cloned().flatten();
        // A value with a name (a DBC value description) shows it.
        let named = current
            .as_ref()
            .and_then(|v| p.values.iter().find(|n| n.value == *v))
            .map(|n| format!(" ({})", n.name))
            .unwrap_or_default();
        let value = current.map(|v| format!("{v}{named}")).unwrap_or_default();
        let dir = match p.direction {
            rtt::component::Direction::Output => "out",
            rtt::component::Direction::Input => "in",
        };
        let links = match p.connections {
            0 => String::new(),
            1 => "1 connection".to_string(),
            n => format!("{n} connections"),
        };
        rows.push(vec![
            dir.into(),
            p.name.clone(),
            p.type_name.clone(),
            value,
            links,
            p.doc.clone(),
        ]);
    }
    for (line, p) in align(&rows).into_iter().zip(&d.ports) {
        out.push(format!("  {line}"));
        // Named values on a line of their own, under the port's.
        if !p.values.is_empty() {
            let names: Vec<String> = p
                .values
                .iter()
                .map(|n| format!("{} = {}", n.value, n.name))
                .collect();
            out.push(format!("      values: {}", names.join(", ")));
        }
    }
    out.push("operations:".into());
    let ops: Vec<Vec<String>> = d
        .operations
        .iter()
        .map(|o| vec![signature(o), o.doc.clone()])
        .collect();
    out.extend(align(&ops).into_iter().map(|l| format!("  {l}")));
    out.push("properties:".into());
    out.extend(value_rows(&d.properties));
    if !d.attributes.is_empty() {
        out.push("attributes:".into());
        out.extend(value_rows(&d.attributes));
    }
    out.extend(services(d));
    if !d.peers.is_empty() {
        out.push("peers:".into());
        out.extend(d.peers.iter().map(|(a, t)| format!("  {a} -> {t}")));
    }
    out.join("\n")
}

/// Properties or attributes, a line each: `path: type  = value  doc`, aligned.
fn value_rows(list: &[rtt::property::PropertyInfo]) -> Vec<String> {
    let rows: Vec<Vec<String>> = list
        .iter()
        .map(|p| {
            vec![
                format!("{}: {}", p.path, p.type_name),
                format!("= {}", p.value),
                p.doc.clone(),
            ]
        })
        .collect();
    align(&rows).into_iter().map(|l| format!("  {l}")).collect()
}

/// The provided and required services of a description, when it has any: each provided
/// service with its members, each requirement with its binding and whether it is ready.
fn services(d: &Description) -> Vec<String> {
    let mut out = Vec::new();
    if !d.provides.is_empty() {
        out.push("provides:".into());
        for p in &d.provides {
            let members: Vec<&str> = p
                .operations
                .iter()
                .chain(&p.ports)
                .map(String::as_str)
                .collect();
            out.push(format!("  {}: {}", p.name, members.join(", ")));
        }
    }
    if !d.requires.is_empty() {
        out.push("requires:".into());
        let rows: Vec<Vec<String>> = d
            .requires
            .iter()
            .map(|r| {
                let what = match &r.kind {
                    rtt::service::RequiredKind::Service { operations } => operations.join(", "),
                    rtt::service::RequiredKind::Devices {
                        interface,
                        multiplicity,
                    } => format!("{multiplicity} {interface}"),
                };
                let binding = if r.bound_to.is_empty() {
                    if r.optional {
                        "unbound (optional)"
                    } else {
                        "unbound"
                    }
                    .to_string()
                } else {
                    format!(
                        "-> {} ({})",
                        r.bound_to.join(", "),
                        if r.ready { "ready" } else { "not ready" }
                    )
                };
                let counts = if r.lost + r.back > 0 {
                    format!("lost {}, back {}", r.lost, r.back)
                } else {
                    String::new()
                };
                vec![r.name.clone(), binding, what, counts]
            })
            .collect();
        out.extend(align(&rows).into_iter().map(|l| format!("  {l}")));
    }
    out
}

/// What a reload did, a line each: applied, then what needs a restart, then the errors.
pub fn reload(r: &crate::protocol::ReloadReport) -> String {
    let mut out = Vec::new();
    out.extend(r.applied.iter().cloned());
    out.extend(r.restart.iter().map(|l| format!("not applied: {l}")));
    if !r.errors.is_empty() {
        out.push(if r.applied.is_empty() {
            "nothing changed; the deployment has errors:".to_string()
        } else {
            "errors:".to_string()
        });
        out.extend(r.errors.iter().map(|l| format!("  {l}")));
    }
    out.join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn columns_align() {
        let t = table(
            &["A", "LONGER", "C"],
            &[
                vec!["xxxx".into(), "y".into(), "z".into()],
                vec!["x".into(), "yy".into(), "".into()],
            ],
        );
        assert_eq!(t, "A     LONGER  C\nxxxx  y       z\nx     yy");
    }

    #[test]
    fn signatures_are_in_the_protocols_types() {
        use rtt::operation::{ArgInfo, ExecutionThread, OperationInfo};
        let arg = |name: &str, t: &str| ArgInfo {
            name: name.into(),
            doc: String::new(),
            type_name: t.into(),
        };
        let mut op = OperationInfo {
            name: "read".into(),
            doc: String::new(),
            args: vec![arg("channel", "u32")],
            result: "f64".into(),
            thread: ExecutionThread::ClientThread,
        };
        assert_eq!(signature(&op), "read(channel: u32) -> f64");
        op.name = "write".into();
        op.args.push(arg("value", "f64"));
        op.result = String::new();
        assert_eq!(signature(&op), "write(channel: u32, value: f64)");
    }
}
