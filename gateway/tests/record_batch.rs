//! A `record` stream whose drain is larger than the client's line limit
//! ([`MAX_STREAM_LINE`](hwgw::client::MAX_STREAM_LINE)) — a component writing 40 samples of
//! 2 MiB at once, 80 MiB in one drain — goes out in several lines, and the recording goes
//! on: every sample of the burst reaches the file, nothing is lost, the recording ends by
//! its duration. In one process: a gateway with a type of its own, its control socket,
//! and `hwgw record`'s own function as the client.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::control::{ControlServer, Limits};
use hwgw::deploy::Gateway;
use hwgw::recorder::cli::{RecordArgs, record};
use recording::Item;
use rtt::component::IntrospectError;
use rtt::port::OutputPort;
use rtt::{Component, Context, HookResult, InterfaceBuilder};
use std::sync::Arc;
use std::time::Duration;

/// Samples in a burst.
const BURST: usize = 40;

/// Bytes of each.
const SIZE: usize = 2 << 20;

/// Once a recording taps its output, writes one small sample; once the recording has
/// taken that one (so the recording surely began before), a burst of large samples, once.
struct Bulk {
    blob: OutputPort<String>,
    state: Phase,
}

enum Phase {
    Waiting,
    Greeted,
    Done,
}

impl Bulk {
    fn new(iface: &mut InterfaceBuilder<Bulk>) -> Result<Bulk, IntrospectError> {
        Ok(Bulk {
            blob: iface.output("blob", "a small sample, then a burst of large ones")?,
            state: Phase::Waiting,
        })
    }
}

fn sample(k: usize) -> String {
    format!("{k:04}{}", "x".repeat(SIZE - 4))
}

impl Component for Bulk {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let taps = self.blob.connections();
        match self.state {
            Phase::Waiting if !taps.is_empty() => {
                self.blob.write(&"hello".to_string());
                self.state = Phase::Greeted;
            }
            Phase::Greeted if taps.iter().any(|c| c.read > 0) => {
                for k in 0..BURST {
                    self.blob.write(&sample(k));
                }
                self.state = Phase::Done;
            }
            _ => {}
        }
        Ok(())
    }
}

const DEPLOYMENT: &str = r#"
[[component]]
name = "bulk"
type = "bulk"
activity = { type = "periodic", period_ms = 100 }
"#;

#[test]
fn a_drain_larger_than_a_line_does_not_end_the_recording() {
    // One line holding the burst would be past the client's limit.
    let item = Item::Sample {
        port: 0,
        at_ns: u64::MAX,
        value: serde_json::Value::String(sample(0)),
    };
    let one = serde_json::to_vec(&item).unwrap().len() as u64;
    assert!(one * BURST as u64 > hwgw::client::MAX_STREAM_LINE);

    let dir = testkit::TempDir::new("record-batch");
    let mut types = hwgw::types::Types::builtin();
    assert!(types.components.register("bulk", |rt, name, spec| {
        rt.add(name, spec, rtt::InitialState::Stopped, Bulk::new)
    }));
    let d = Deployment::parse(DEPLOYMENT, "bulk.toml").unwrap();
    let gw = Arc::new(Gateway::build(&d, "bulk.toml", DEPLOYMENT, &types).unwrap());
    gw.start().unwrap();
    let socket = dir.path().join("hwgw.sock");
    let mut server = ControlServer::start(gw.clone(), &socket, Limits::default()).unwrap();
    server.open().unwrap();
    let client = hwgw::client::Client::new(&socket);
    let file = dir.path().join("bulk.mcap");
    let args = RecordArgs {
        file: file.clone(),
        ports: vec!["bulk.blob".into()],
        devices: false,
        no_steps: true,
        duration: Some(Duration::from_secs(1)),
        trigger: None,
        pre: Duration::ZERO,
        post: Duration::ZERO,
        buffer: 64,
        max_mb: 1024,
    };
    // Its own thread: `record` blocks SIGINT and SIGTERM on the thread it runs on.
    let said = std::thread::spawn(move || record(&client, args))
        .join()
        .unwrap()
        .unwrap_or_else(|e| panic!("the recording failed: {e}"));
    server.close();
    gw.shutdown();
    assert!(
        said.contains(", 0 lost,") && said.contains("ended: duration"),
        "{said}"
    );
    let rec = recording::read::Recording::read(&file).unwrap();
    assert_eq!(rec.truncated, None);
    // The burst, and the small sample before it unless that was stamped before the
    // recording began (a sample takes the start of the step that wrote it).
    let n = rec.messages;
    assert!(
        n == BURST as u64 || n == BURST as u64 + 1,
        "{n} messages: {said}"
    );
    assert!(said.contains(&format!(": {n} messages")), "{said}");
    assert_eq!(rec.not_numbers, n, "each sample is a string");
    assert_eq!(rec.metadata["lost"], "0");
}
