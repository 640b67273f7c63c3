//! A user's server type, registered in `ServerTypes` as a binary of its own would: built
//! from its top-level section over the registry, named by its key, its problems located
//! under the section; without it, its section is an unknown key that says what exists.

#![allow(clippy::unwrap_used, reason = "test code")]

use driver_api::{CardError, Server, ServerContext};
use hwgw::deploy::Gateway;
use hwgw::types::Types;

/// A user's server type: `[echo] at = "…"`, listening nowhere but where it is told.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct EchoConfig {
    at: String,
    #[serde(default)]
    devices: Vec<String>,
}

struct Echo {
    name: String,
    at: String,
    running: std::sync::atomic::AtomicBool,
}

impl Server for Echo {
    fn name(&self) -> &str {
        &self.name
    }
    fn start(&self) -> Result<String, driver_api::ServerError> {
        self.running
            .store(true, std::sync::atomic::Ordering::Relaxed);
        Ok(self.at.clone())
    }
    fn stop(&self) {
        self.running
            .store(false, std::sync::atomic::Ordering::Relaxed);
    }
    fn address(&self) -> Option<String> {
        let running = self.running.load(std::sync::atomic::Ordering::Relaxed);
        running.then(|| self.at.clone())
    }
}

fn echo(c: &EchoConfig, ctx: &mut ServerContext<'_>) -> Result<Box<dyn Server>, Vec<CardError>> {
    // Every device it names must be registered by then (the cards are built first).
    let problems: Vec<CardError> = c
        .devices
        .iter()
        .enumerate()
        .filter(|(_, d)| ctx.registry().digital_out().lookup(d).is_err())
        .map(|(i, d)| CardError::at(format!("devices[{i}]"), format!("no {d:?}")))
        .collect();
    if !problems.is_empty() {
        return Err(problems);
    }
    Ok(Box::new(Echo {
        name: ctx.name().to_string(),
        at: c.at.clone(),
        running: Default::default(),
    }))
}

const CARD: &str = "[[card]]\nname = \"s\"\ndriver = \"sim\"\n[card.sim]\ndigital_outputs = 2\n";

#[test]
fn a_users_server_type_is_built_from_its_section_and_named_by_its_key() {
    let mut types = Types::builtin();
    assert!(types.servers.register("echo", echo));
    assert!(
        !types.servers.register("echo", echo),
        "a name is taken once"
    );
    assert!(
        !types.servers.register("card", echo),
        "the deployment's keys are taken"
    );
    assert_eq!(
        types.servers.names(),
        [
            "echo",
            "modbus_server",
            "server.foxglove",
            "server.metrics",
            "server.mqtt",
            "server.opcua",
            "server.web"
        ]
    );
    let text = format!("{CARD}[echo]\nat = \"here\"\ndevices = [\"s\"]\n");
    let (gw, _) = Gateway::from_text(&text, "e.toml", &types).unwrap();
    assert_eq!(gw.server_address("echo"), None);
    gw.start().unwrap();
    assert_eq!(gw.server_address("echo").as_deref(), Some("here"));
    gw.shutdown();
    // Its problems are located under its section, as a card's are.
    let text = format!("{CARD}[echo]\nat = \"here\"\ndevices = [\"s\", \"t\"]\nport = 1\n");
    let Err(e) = Gateway::from_text(&text, "e.toml", &types) else {
        panic!("an unknown key taken");
    };
    assert!(
        e.starts_with("e.toml:9:1: echo.port: unknown field `port`"),
        "{e}"
    );
    let text = format!("{CARD}[echo]\nat = \"here\"\ndevices = [\"s\", \"t\"]\n");
    let Err(e) = Gateway::from_text(&text, "e.toml", &types) else {
        panic!("a missing device taken");
    };
    assert_eq!(e, "e.toml:8:17: echo.devices[1]: no \"t\"");
    // Without the type, the section is an unknown key that says what exists.
    let Err(e) = Gateway::from_text(&text, "e.toml", &Types::builtin()) else {
        panic!("a server type this build lacks taken");
    };
    assert!(
        e.starts_with("e.toml:6:2: echo: unknown key \"echo\""),
        "{e}"
    );
    assert!(
        e.ends_with(
            "the servers of this build: modbus_server, server.foxglove, server.metrics, server.mqtt, server.opcua, server.web"
        ),
        "{e}"
    );
}

#[test]
fn a_users_server_type_under_server_is_asked_for_with_server_dot_its_name() {
    let mut types = Types::builtin();
    assert!(!types.servers.register("server", echo), "server is taken");
    assert!(!types.servers.register("server.", echo), "a name is needed");
    assert!(!types.servers.register("server.a.b", echo), "one level");
    assert!(types.servers.register("server.echo", echo));
    let text = format!("{CARD}[server.echo]\nat = \"there\"\ndevices = [\"s\"]\n");
    let (gw, _) = Gateway::from_text(&text, "e.toml", &types).unwrap();
    gw.start().unwrap();
    assert_eq!(gw.server_address("server.echo").as_deref(), Some("there"));
    gw.shutdown();
    let text = format!("{CARD}[server.echo]\nat = \"there\"\ndevices = [\"t\"]\n");
    let Err(e) = Gateway::from_text(&text, "e.toml", &types) else {
        panic!("a missing device taken");
    };
    assert_eq!(e, "e.toml:8:12: server.echo.devices[0]: no \"t\"");
}
