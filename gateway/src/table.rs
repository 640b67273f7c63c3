//! What the CLI and the browser print for people: aligned tables and a component's
//! interface, from the protocol's typed answers (`--json` prints the answers instead).

use crate::protocol::{ComponentEntry, Description, StatusReport};
use device_interface::RegistryEntry;
use serde_json::Value;

/// `rows` under `headers`, each column as wide as its widest cell, two spaces apart; the
/// last column is not padded.
pub fn table(headers: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = headers.iter().map(|h| h.chars().count()).collect();
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let line = |cells: &mut dyn Iterator<Item = &str>| {
        let cells: Vec<&str> = cells.collect();
        let last = cells.len().saturating_sub(1);
        let mut s = String::new();
        for (i, c) in cells.iter().enumerate() {
            if i == last {
                s.push_str(c);
            } else {
                let pad = widths[i].saturating_sub(c.chars().count());
                s.push_str(c);
                s.push_str(&" ".repeat(pad + 2));
            }
        }
        s.trim_end().to_string()
    };
    let mut out = vec![line(&mut headers.iter().copied())];
    for row in rows {
        out.push(line(&mut row.iter().map(String::as_str)));
    }
    out.join("\n")
}

/// `hwgw ls`: every component and its state.
pub fn components(list: &[ComponentEntry]) -> String {
    let rows: Vec<Vec<String>> = list
        .iter()
        .map(|c| vec![c.name.clone(), state(c.state)])
        .collect();
    table(&["COMPONENT", "STATE"], &rows)
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
                state(c.state),
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
        out.push(format!(
            "  {:<3} {:<16} {:<8} {:<12} {:<14} {}",
            dir, p.name, p.type_name, value, links, p.doc
        ));
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
    for o in &d.operations {
        let args: Vec<String> = o
            .args
            .iter()
            .map(|a| format!("{}: {}", a.name, a.type_name))
            .collect();
        out.push(format!(
            "  {}({}) -> {}  {}",
            o.name,
            args.join(", "),
            o.result,
            o.doc
        ));
    }
    out.push("properties:".into());
    for p in &d.properties {
        out.push(format!(
            "  {:<16} = {:<12} {}",
            p.path,
            p.value.to_string(),
            p.doc
        ));
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
}
