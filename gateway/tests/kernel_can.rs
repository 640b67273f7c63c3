//! `hwgw` with a SocketCAN card, in the kernel rig: the real binary on `config/can.toml`
//! over a real vcan, can-utils on the other end, the CLI in between.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use testkit::Candump;
use testkit::Service;
use testkit::wait::wait_ok;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/can.toml");

/// `hwgw run config/can.toml` on a socket of its own.
fn start() -> Result<Service, Failed> {
    Ok(Service::start(HWGW, "can", &[CONFIG], &[])?)
}

/// `hwgw ARGS`, which must succeed: its standard output.
fn out(gw: &Service, args: &[&str]) -> Result<String, Failed> {
    Ok(gw.out(args)?)
}

/// SIGTERM; the log of a clean exit.
fn terminate(gw: Service) -> Result<String, Failed> {
    let stopped = gw.terminate();
    if !stopped.status.success() {
        return Err(format!("hwgw exited with {}: {}", stopped.status, stopped.log).into());
    }
    Ok(stopped.log)
}

/// `candump -L` of the frames matching `filter` (`id:mask`), until `n` or 3 s of silence.
fn candump(filter: &str, n: usize) -> Result<Candump, Failed> {
    Ok(Candump::start(&[
        "-n",
        &n.to_string(),
        "-T",
        "3000",
        &format!("vcan0,{filter}"),
    ])?)
}

fn frames(c: Candump) -> Result<Vec<String>, Failed> {
    Ok(c.frames()?.into_iter().map(|(_, f)| f).collect())
}

fn hwgw_reads_writes_and_leaves_safe_frames() -> Result<(), Failed> {
    sh("ip link add vcan0 type vcan && ip link set vcan0 up")?;
    let gw = start()?;

    // cansend -> the DBC-decoded values, through the CLI.
    let mirror = candump("210:7FF", 1)?;
    sh("cansend vcan0 100#3930F9C00B00FAFF && cansend vcan0 18FEEE05#822EFB00")?;
    wait_ok("Speed decoded", || {
        Ok(out(&gw, &["get", "can.ai", "Speed"])? == "123.45")
    })?;
    assert_eq!(out(&gw, &["get", "can.ai", "Torque"])?, "-60.0");
    assert_eq!(out(&gw, &["get", "can.ai", "Delta"])?, "-123.4");
    assert_eq!(out(&gw, &["get", "can.ai", "Coolant"])?, "90.0");
    assert_eq!(out(&gw, &["get", "can.di", "Enabled"])?, "true");
    assert_eq!(out(&gw, &["get", "can.di", "Mode_0"])?, "true");
    assert_eq!(out(&gw, &["get", "can.di", "Mode_1"])?, "false");

    // The follow component wrote Speed to Mirror: sent on change, 12345 little endian.
    assert_eq!(frames(mirror)?, ["210#3930"]);

    // hwgw set -> the Command frame, every 10 ms, with the exact bytes.
    out(&gw, &["set", "can.ao", "Setpoint", "-12.3"])?;
    out(&gw, &["set", "can.do", "Run", "true"])?;
    // Both reached the card (read back through the ports) before the capture starts.
    wait_ok("the setpoint and Run on the card", || {
        Ok(out(&gw, &["get", "can.ao", "Setpoint"])? == "-12.3"
            && out(&gw, &["get", "can.do", "Run"])? == "true")
    })?;
    let got = frames(candump("200:7FF", 5)?)?;
    assert_eq!(got, vec!["200#FF850100"; 5]);

    // Counters and status.
    let counters = out(&gw, &["call", "can", "counters"])?;
    assert!(counters.contains("\"rx_frames\": 2"), "{counters}");
    assert!(counters.contains("\"link_up\": true"), "{counters}");
    let status = out(&gw, &["status"])?;
    assert!(
        status.contains("socketcan") && status.contains("vcan0"),
        "{status}"
    );

    // SIGTERM: the safe values go out before the bus stops.
    let command = candump("200:7FF", 1000)?;
    let mirror = candump("210:7FF", 10)?;
    let log = terminate(gw)?;
    let command = frames(command)?;
    assert_eq!(
        command.last().map(String::as_str),
        Some("200#00000000"),
        "{log}"
    );
    assert_eq!(
        frames(mirror)?.last().map(String::as_str),
        Some("210#0000"),
        "{log}"
    );
    Ok(())
}

/// The DBC file as CANdb++ writes them: Windows-1252 (°), a message pseudo-placed for
/// unplaced signals, names repeated across messages, an IEEE float, a 64-bit unsigned
/// value, a Motorola signal, simple multiplexing, value tables, comments over lines and a
/// cycle time from an attribute. `\xB0` is the degree sign in Windows-1252.
const VEHICLE_DBC: &[u8] = b"VERSION \"\"\r
\r
NS_ :\r
\tNS_DESC_\r
\tCM_\r
\tBA_DEF_\r
\tBA_\r
\tVAL_\r
\tSIG_VALTYPE_\r
\r
BS_:\r
\r
BU_: ECU GW\r
\r
BO_ 256 EngineData: 8 ECU\r
 SG_ Counter : 0|4@1+ (1,0) [0|15] \"\" GW\r
 SG_ CRC : 8|8@1+ (1,0) [0|255] \"\" GW\r
 SG_ OilTemp : 16|8@1+ (1,-40) [-40|215] \"\xB0C\" GW\r
 SG_ Level : 24|32@1+ (1,0) [0|100] \"%\" GW\r
\r
BO_ 257 Brake: 8 ECU\r
 SG_ Counter : 0|4@1+ (1,0) [0|15] \"\" GW\r
 SG_ CRC : 8|8@1+ (1,0) [0|255] \"\" GW\r
 SG_ Pressure : 23|16@0+ (0.1,0) [0|6553.5] \"bar\" GW\r
\r
BO_ 258 Odometer: 8 ECU\r
 SG_ Total : 0|64@1+ (1,0) [0|18446744073709551615] \"m\" GW\r
\r
BO_ 259 Diag : 4 ECU\r
 SG_ Page M : 0|8@1+ (1,0) [0|255] \"\" GW\r
 SG_ Volts m1 : 8|16@1+ (0.001,0) [0|65.535] \"V\" GW\r
 SG_ Amps m2 : 8|16@1- (0.01,0) [-327.68|327.67] \"A\" GW\r
\r
BO_ 260 Event: 1 ECU\r
 SG_ Alarm : 0|1@1+ (1,0) [0|1] \"\" GW\r
\r
BO_ 512 Command: 2 GW\r
 SG_ Gear : 0|3@1+ (1,0) [0|7] \"\" ECU\r
 SG_ Lamp : 8|1@1+ (1,0) [0|1] \"\" ECU\r
\r
BO_ 3221225472 VECTOR__INDEPENDENT_SIG_MSG: 0 Vector__XXX\r
 SG_ Orphan : 0|8@1+ (1,0) [0|0] \"\" Vector__XXX\r
\r
CM_ BO_ 260 \"Sent on change only\";\r
CM_ SG_ 256 OilTemp \"Oil temperature in \xB0C,\r
at the sump\";\r
BA_DEF_ BO_  \"GenMsgCycleTime\" INT 0 65535;\r
BA_DEF_DEF_  \"GenMsgCycleTime\" 0;\r
BA_ \"GenMsgCycleTime\" BO_ 256 100;\r
VAL_ 512 Gear 0 \"P\" 1 \"R\" 2 \"N\" 3 \"D\" ;\r
VAL_ 512 Lamp 0 \"off\" 1 \"on\" ;\r
SIG_VALTYPE_ 256 Level : 1;\r
";

/// A deployment of [`VEHICLE_DBC`] on `vcan1`: everything received, Command sent.
const VEHICLE_TOML: &str = r#"
[[card]]
name = "can"
driver = "socketcan"
sample_period_ms = 10
safe_analog_out = [0.0]
safe_digital_out_on = []

[card.socketcan]
interface = "vcan1"
dbc = "vehicle.dbc"

[[card.socketcan.rx]]
message = "EngineData"

[[card.socketcan.rx]]
message = "Brake"

[[card.socketcan.rx]]
message = "Odometer"

[[card.socketcan.rx]]
message = "Diag"

[[card.socketcan.rx]]
message = "Event"

[[card.socketcan.tx]]
message = "Command"
cycle_ms = 10
"#;

/// `hwgw get COMPONENT PORT` as a number.
fn number(gw: &Service, component: &str, port: &str) -> Result<f64, Failed> {
    let text = out(gw, &["get", component, port])?;
    Ok(text
        .trim()
        .parse::<f64>()
        .map_err(|e| format!("get {component} {port}: {text:?}: {e}"))?)
}

/// The card's message states from `hwgw status --json`, by name: (received, stale).
fn messages(gw: &Service) -> Result<Vec<(String, u64, bool)>, Failed> {
    let status: serde_json::Value = serde_json::from_str(&out(gw, &["--json", "status"])?)?;
    let list = status["cards"][0]["counters"]["messages"]
        .as_array()
        .ok_or_else(|| format!("no messages in {status}"))?;
    Ok(list
        .iter()
        .map(|m| {
            (
                m["name"].as_str().unwrap_or("").to_string(),
                m["received"].as_u64().unwrap_or(0),
                m["stale"].as_bool().unwrap_or(false),
            )
        })
        .collect())
}

/// The status of the card's devices in `hwgw status --json`, as (interface, status),
/// sorted by interface: each device is as healthy as its own messages.
fn card_status(gw: &Service) -> Result<Vec<(String, String)>, Failed> {
    let status: serde_json::Value = serde_json::from_str(&out(gw, &["--json", "status"])?)?;
    let list = status["devices"]
        .as_array()
        .ok_or_else(|| format!("no devices in {status}"))?;
    Ok(list
        .iter()
        .filter(|d| d["name"] == "can")
        .map(|d| {
            let text = |v: &serde_json::Value| v.as_str().unwrap_or("").to_string();
            (text(&d["interface"]), text(&d["status"]))
        })
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect())
}

/// The expected [`card_status`]: analog_in, analog_out, digital_in, digital_out.
fn health(statuses: &[&str; 4]) -> Vec<(String, String)> {
    let interfaces = ["analog_in", "analog_out", "digital_in", "digital_out"];
    let mut v: Vec<(String, String)> = interfaces
        .iter()
        .zip(statuses)
        .map(|(i, s)| (i.to_string(), s.to_string()))
        .collect();
    v.sort();
    v
}

/// `hwgw call can.ai read CHANNEL`: its value, or its error text (the command exits 1
/// with the operation's error on standard error).
fn read_channel(gw: &Service, channel: u32) -> Result<Result<f64, String>, Failed> {
    let o = gw.cli(&["call", "can.ai", "read", &channel.to_string()]);
    let text = String::from_utf8_lossy(&o.stdout).trim().to_string();
    if !o.status.success() {
        let err = String::from_utf8_lossy(&o.stderr).trim().to_string();
        if !err.starts_with("hwgw: can.ai.read: ") {
            return Err(format!("hwgw call can.ai read {channel}: {err}").into());
        }
        return Ok(Err(err));
    }
    Ok(text.parse::<f64>().map_err(|_| text))
}

fn a_vehicle_dbc_as_tools_write_it() -> Result<(), Failed> {
    sh("ip link add vcan1 type vcan && ip link set vcan1 up")?;
    let dir = testkit::TempDir::new("can-vehicle-files");
    std::fs::write(dir.path().join("vehicle.dbc"), VEHICLE_DBC)?;
    let toml = dir.path().join("vehicle.toml");
    std::fs::write(&toml, VEHICLE_TOML)?;
    let gw = Service::start(HWGW, "can-vehicle", &[&toml], &[])?;

    // Counter and CRC are in two messages: each is Message__Signal; the others keep
    // their names, and the summary says so.
    let log = gw.log_text();
    assert!(log.contains("EngineData__Counter"), "{log}");
    let ports = out(&gw, &["ls", "can.ai"])?;
    for p in [
        "EngineData__Counter",
        "EngineData__CRC",
        "Brake__Counter",
        "Brake__CRC",
        "OilTemp",
        "Level",
        "Pressure",
        "Total",
        "Page",
        "Volts",
        "Amps",
    ] {
        assert!(ports.contains(p), "{p}: {ports}");
    }
    // The comment (read as Windows-1252, over two lines) is OilTemp's port doc.
    assert!(
        ports.contains("channel 2: Oil temperature in \u{b0}C, at the sump"),
        "{ports}"
    );

    // Each value as cantools computes it: raw * factor + offset, floats from their bits,
    // 64-bit unsigned exact up to f64.
    let level = 72.25f32;
    let level_bytes = level.to_le_bytes();
    let engine = format!(
        "100#05AB82{:02X}{:02X}{:02X}{:02X}00",
        level_bytes[0], level_bytes[1], level_bytes[2], level_bytes[3]
    );
    sh(&format!(
        "cansend vcan1 {engine} && cansend vcan1 101#093C123400000000 && \
         cansend vcan1 102#FFFFFFFFFFFFFFFF && cansend vcan1 103#01393000"
    ))?;
    wait_ok("Volts decoded", || {
        Ok(number(&gw, "can.ai", "Volts")? != 0.0)
    })?;
    let expected = [
        ("EngineData__Counter", 5.0),
        ("EngineData__CRC", 171.0),
        ("OilTemp", 130.0 * 1.0 - 40.0),
        ("Level", f64::from(level)),
        ("Brake__Counter", 9.0),
        ("Brake__CRC", 60.0),
        ("Pressure", f64::from(0x1234u16) * 0.1),
        ("Total", u64::MAX as f64),
        ("Page", 1.0),
        ("Volts", 12345.0 * 0.001),
    ];
    for (port, want) in expected {
        assert_eq!(number(&gw, "can.ai", port)?, want, "{port}");
    }
    // Amps (mux value 2) has not come: its channel alone is stale; Volts reads.
    let amps = 10;
    let stale = read_channel(&gw, amps)?;
    assert!(
        stale.as_ref().is_err_and(|e| e.contains("stale")),
        "{stale:?}"
    );
    assert_eq!(read_channel(&gw, 9)?, Ok(12345.0 * 0.001));
    // Mux value 2: Amps -2.5 A (raw 0xFF06 signed), and Volts keeps its value.
    sh("cansend vcan1 103#0206FF00")?;
    wait_ok("Amps decoded", || Ok(read_channel(&gw, amps)?.is_ok()))?;
    assert_eq!(read_channel(&gw, amps)?, Ok(-250.0 * 0.01));
    wait_ok("Page 2 sampled", || {
        Ok(number(&gw, "can.ai", "Page")? == 2.0)
    })?;
    assert_eq!(number(&gw, "can.ai", "Amps")?, -250.0 * 0.01);
    assert_eq!(number(&gw, "can.ai", "Volts")?, 12345.0 * 0.001);

    // Event (on change, never sent) is stale alone: the devices are online but for the
    // digital inputs, whose one bit (Alarm) only Event carries. EngineData (GenMsgCycleTime
    // 100 ms) goes stale after its timeout; Brake (no cycle) does not.
    let listed = messages(&gw)?;
    assert!(
        listed.contains(&("Event".to_string(), 0, true)),
        "{listed:?}"
    );
    assert!(
        listed.contains(&("Brake".to_string(), 1, false)),
        "{listed:?}"
    );
    assert_eq!(
        card_status(&gw)?,
        health(&["online", "online", "stale", "online"])
    );
    wait_ok("EngineData stale after its GenMsgCycleTime timeout", || {
        Ok(messages(&gw)?.contains(&("EngineData".to_string(), 1, true)))
    })?;
    assert!(read_channel(&gw, 2)?.is_err(), "OilTemp");
    assert_eq!(read_channel(&gw, 6)?, Ok(f64::from(0x1234u16) * 0.1));
    assert_eq!(
        card_status(&gw)?,
        health(&["online", "online", "stale", "online"])
    );
    sh("cansend vcan1 104#01")?;
    wait_ok("Event received: the digital inputs online", || {
        Ok(card_status(&gw)? == health(&["online"; 4]))
    })?;
    let table = out(&gw, &["status"])?;
    assert!(table.contains("can messages:"), "{table}");
    // Every value was within its declared range (2^64 - 1 included).
    let counters = out(&gw, &["call", "can", "counters"])?;
    assert!(counters.contains("\"rx_out_of_range\": 0"), "{counters}");

    // Value names: describe lists them, set takes them.
    let described = out(&gw, &["ls", "can.ao"])?;
    assert!(
        described.contains("values: 0.0 = P, 1.0 = R, 2.0 = N, 3.0 = D"),
        "{described}"
    );
    out(&gw, &["set", "can.ao", "Gear", "D"])?;
    out(&gw, &["set", "can.do", "Lamp", "on"])?;
    wait_ok("Gear D and Lamp on read back", || {
        Ok(out(&gw, &["get", "can.ao", "Gear"])? == "3.0"
            && out(&gw, &["get", "can.do", "Lamp"])? == "true")
    })?;
    let got = frames(Candump::start(&["-n", "3", "-T", "3000", "vcan1,200:7FF"])?)?;
    assert_eq!(got, vec!["200#0301"; 3]);
    assert!(out(&gw, &["ls", "can.ao"])?.contains("3.0 (D)"));
    let refused = gw.cli(&["set", "can.ao", "Gear", "X"]);
    let text = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && text.contains("one of P, R, N, D"),
        "{text}"
    );
    // SIGTERM: Gear to its safe value P; Lamp, under the default policy "initial", back to
    // the value the frame carried before hwgw first wrote it (off) — not left on.
    let last = Candump::start(&["-n", "1000", "-T", "1000", "vcan1,200:7FF"])?;
    let log = terminate(gw)?;
    assert_eq!(
        frames(last)?.last().map(String::as_str),
        Some("200#0000"),
        "{log}"
    );
    assert!(!log.contains("left as hwgw last wrote it"), "{log}");
    Ok(())
}

/// True when a CAN_RAW or CAN_ISOTP receiver for standard id `id` is bound on `iface`
/// (the kernel's receive lists).
fn receiving(iface: &str, id: u32) -> bool {
    let list = std::fs::read_to_string("/proc/net/can/rcvlist_sff").unwrap_or_default();
    let id = format!("{id:03x}");
    list.lines().any(|l| {
        let mut w = l.split_whitespace();
        w.next() == Some(iface) && w.next() == Some(id.as_str())
    })
}

/// `hwgw call CARD request NAME HEX` sends a 100-byte request through the kernel's ISO-TP
/// and returns the 200-byte response that can-utils' isotpsend gives on the other end;
/// isotprecv there receives the request whole.
fn isotp_request_and_response_through_hwgw_call() -> Result<(), Failed> {
    sh("ip link add vcan2 type vcan && ip link set vcan2 up")?;
    let gw = Service::run_text(
        HWGW,
        "can-isotp",
        r#"
[[card]]
name = "diag"
driver = "socketcan"

[card.socketcan]
interface = "vcan2"
isotp = [
    { name = "ecu", tx_id = 0x7E0, rx_id = 0x7E8, timeout_ms = 10000, block_size = 4, st_min_us = 500 },
    { name = "mute", tx_id = 0x7E1, rx_id = 0x7E9, timeout_ms = 300 },
]
"#,
    )?;
    let request: Vec<u8> = (0..100u32).map(|i| (i * 7 + 3) as u8).collect();
    let response: Vec<u8> = (0..200u32).map(|i| (255 - i) as u8).collect();
    let hex = |b: &[u8]| b.iter().map(|x| format!("{x:02X}")).collect::<Vec<_>>();

    // The ECU's side: isotprecv takes one request on 0x7E0 (flow control on 0x7E8).
    let recv = std::process::Command::new("isotprecv")
        .args(["-s", "7E8", "-d", "7E0", "vcan2"])
        .stdout(std::process::Stdio::piped())
        .spawn()?;
    wait_ok("isotprecv bound", || Ok(receiving("vcan2", 0x7E0)))?;
    let call = std::process::Command::new(HWGW)
        .args(["call", "diag", "request", "ecu", &hex(&request).concat()])
        .arg("--socket")
        .arg(gw.dir().join("hwgw.sock"))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()?;
    let got = recv.wait_with_output()?;
    assert_eq!(
        String::from_utf8_lossy(&got.stdout).trim(),
        hex(&request).join(" ")
    );
    // hwgw waits for the answer on 0x7E8 (its socket bound before the request went out);
    // its flow control asks for blocks of 4 frames 500 µs apart (STmin 0xF5).
    let fc = Candump::start(&["-n", "1", "-T", "5000", "vcan2,7E0:7FF"])?;
    sh(&format!(
        "echo '{}' | isotpsend -s 7E8 -d 7E0 vcan2",
        hex(&response).join(" ")
    ))?;
    let fc: Vec<String> = fc.frames()?.into_iter().map(|(_, f)| f).collect();
    assert_eq!(fc, ["7E0#3004F5"]);
    let out = call.wait_with_output()?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        format!("\"{}\"", hex(&response).concat())
    );

    // Nobody answering: a timeout error, not a hang; a bad pair or bad hex: named.
    let mute = gw.cli(&["call", "diag", "request", "mute", "3E00"]);
    let err = String::from_utf8_lossy(&mute.stderr);
    assert!(err.contains("no response on 0x7e9 within 300ms"), "{err}");
    let none = gw.cli(&["call", "diag", "request", "nothing", "3E00"]);
    let err = String::from_utf8_lossy(&none.stderr);
    assert!(
        err.contains("no ISO-TP address pair \"nothing\" (there are: ecu, mute)"),
        "{err}"
    );
    let bad = gw.cli(&["call", "diag", "request", "ecu", "3G"]);
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("\"3G\" is not a hex byte"), "{err}");
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    Ok(())
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::vcan().module("can_isotp");
    kernel_rig::harness(
        &rig,
        vec![
            Trial::test(
                "hwgw_reads_writes_and_leaves_safe_frames",
                hwgw_reads_writes_and_leaves_safe_frames,
            ),
            Trial::test(
                "a_vehicle_dbc_as_tools_write_it",
                a_vehicle_dbc_as_tools_write_it,
            ),
            Trial::test(
                "isotp_request_and_response_through_hwgw_call",
                isotp_request_and_response_through_hwgw_call,
            ),
        ],
    )
}
