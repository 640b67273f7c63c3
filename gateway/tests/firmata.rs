//! `hwgw` on `config/firmata.toml` against the genuine StandardFirmata on a simulated Uno
//! (its port a stable name linked to the simulator's pty): inputs driven in the simulator
//! read through `hwgw get`, outputs and PWM written by `hwgw set` and by a component seen
//! on the simulated pins; the board unplugged and back on another pty behind the same name,
//! set up again by itself; the safe values on the pins after SIGTERM; then pyfirmata2, an
//! independent Firmata client, on the same board reads the same values.
#![allow(clippy::unwrap_used, reason = "test code")]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use testkit::peers::PYTHON;
use testkit::uno::pyfirmata2;
use testkit::{Service, SimUno, TempDir, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// One simulation at a time (each takes a whole core of the two).
static ONE: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn one() -> std::sync::MutexGuard<'static, ()> {
    ONE.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/firmata.toml");

/// config/firmata.toml on `pty`, with a blinker component toggling d8 every 100 ms.
fn deployment(dir: &TempDir, pty: &str) -> std::path::PathBuf {
    let text = std::fs::read_to_string(CONFIG).unwrap();
    let line = "port = \"/dev/ttyACM0\"";
    assert!(text.contains(line), "config/firmata.toml names its port so");
    let text = text.replace(line, &format!("port = \"{pty}\""))
        + "\n[[component]]\nname = \"blink\"\ntype = \"blinker\"\n\
           activity = { type = \"periodic\", period_ms = 100 }\n\
           properties = { device = \"uno\", bit = 0 }\n";
    let path = dir.path().join("firmata.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// pyfirmata2 on `pty`: A0 as it reports it (a fraction of the reference), pin 2's level,
/// and PWM pin 5 written to 0.25.
const PYFIRMATA: &str = r#"
import json, sys, time, pyfirmata2
board = pyfirmata2.Arduino(sys.argv[1])
seen = {}
a0 = board.get_pin('a:0:i')
a0.register_callback(lambda v: seen.__setitem__('a0', v))
a0.enable_reporting()
d2 = board.get_pin('d:2:i')
d2.register_callback(lambda v: seen.__setitem__('d2', v))
d2.enable_reporting()
board.samplingOn(19)
p5 = board.get_pin('d:5:p')
p5.write(0.25)
end = time.time() + 10
while len(seen) < 2 and time.time() < end:
    time.sleep(0.01)
time.sleep(0.2)
print(json.dumps(seen))
sys.stdout.flush()
sys.stdin.readline()
board.exit()
"#;

/// `hwgw status --json` of the running gateway.
fn status(gw: &Service) -> String {
    gw.out(&["status", "--json"]).unwrap_or_default()
}

/// `hwgw get uno.<port> <name>` as printed.
fn get(gw: &Service, port: &str, name: &str) -> Option<String> {
    gw.out(&["get", &format!("uno.{port}"), name]).ok()
}

/// Inputs driven in the simulator, read with hwgw get: the four digital inputs (pin 4's
/// pull-up on, as the deployment asks) and A0, A1 in volts.
fn inputs_through_hwgw(gw: &Service, sim: &mut SimUno) {
    assert!(sim.pullup(4).unwrap(), "d4's pull-up on the board");
    for (pin, name) in [(2, "button"), (3, "d3"), (4, "d4"), (7, "d7")] {
        for level in [true, false] {
            sim.input(pin, level).unwrap();
            wait_until(&format!("{name} {level}"), || {
                get(gw, "di", name).as_deref() == Some(if level { "true" } else { "false" })
            });
        }
    }
    sim.input(2, true).unwrap();
    wait_until("button on", || {
        get(gw, "di", "button").as_deref() == Some("true")
    });
    for (ch, mv, name) in [(1u8, 1234u32, "a1"), (0, 2500, "a0")] {
        sim.adc(ch, mv).unwrap();
        let volts = f64::from(mv * 1023 / 5000) / 1023.0 * 5.0;
        wait_until(&format!("{name} at {volts} V"), || {
            get(gw, "ai", name).and_then(|v| v.parse::<f64>().ok()) == Some(volts)
        });
    }
}

/// The board unplugged and plugged back on another pty behind the same stable name (the
/// next simulation started first, so the kernel cannot hand it the number just freed):
/// offline, then back by itself with the outputs hwgw holds, without a restart.
fn replugged(gw: &Service, sim: SimUno, link: &Path) -> SimUno {
    let mut next = SimUno::start().unwrap();
    assert_ne!(sim.pty(), next.pty());
    drop(sim);
    wait_until("the board offline", || {
        let s = status(gw);
        s.contains("\"link\"") && !s.contains("\"link\": \"online\"")
    });
    std::fs::remove_file(link).unwrap();
    std::os::unix::fs::symlink(next.pty(), link).unwrap();
    wait_until("the board back online", || {
        status(gw).contains("\"link\": \"online\"")
    });
    wait_until("the LED restored", || next.pin(13).unwrap().level);
    wait_until("pwm5 restored", || {
        (next.pin(5).unwrap().duty - 65.0 / 256.0).abs() < 0.002
    });
    let edges = next.pin(8).unwrap().edges;
    wait_until("pin 8 blinking again", || {
        next.pin(8).unwrap().edges >= edges + 4
    });
    let s = status(gw);
    assert!(s.contains("\"reopens\": 1"), "{s}");
    next
}

#[test]
fn hwgw_and_pyfirmata2_on_standard_firmata() {
    let _one = one();
    let py = pyfirmata2().unwrap();
    let sim = SimUno::start().unwrap();
    let dir = TempDir::new("firmata-gw");
    // The port by a stable name (as /dev/serial/by-id/… or udev/65-hwgw.rules give).
    let link = dir.path().join("uno");
    std::os::unix::fs::symlink(sim.pty(), &link).unwrap();
    let config = deployment(&dir, link.to_str().unwrap());
    let gw = Service::start(HWGW, "firmata", &[config.as_os_str()], &[]).unwrap();
    let mut s = String::new();
    wait_until("the board online", || {
        s = status(&gw);
        s.contains("\"link\": \"online\"")
    });
    assert!(
        s.contains("StandardFirmata.ino 2.4 (protocol 2.4), 20 pins"),
        "{s}"
    );
    let mut sim = sim;
    inputs_through_hwgw(&gw, &mut sim);
    let volts = 511.0 / 1023.0 * 5.0;
    // Outputs and PWM written with hwgw set, seen on the pins.
    gw.out(&["set", "uno.do", "led", "true"]).unwrap();
    wait_until("pin 13 high", || sim.pin(13).unwrap().level);
    gw.out(&["set", "uno.ao", "pwm5", "0.25"]).unwrap();
    // 0.25 of 255 is 64 (rounded); timer 0's fast PWM is high for (64 + 1) / 256.
    wait_until("pin 5 at 65/256", || {
        (sim.pin(5).unwrap().duty - 65.0 / 256.0).abs() < 0.002
    });
    // The blinker component toggles d8 (pin 8) through the card.
    let edges = sim.pin(8).unwrap().edges;
    wait_until("pin 8 blinking", || sim.pin(8).unwrap().edges >= edges + 4);
    let mut sim = replugged(&gw, sim, &link);
    sim.input(2, true).unwrap();
    sim.adc(0, 2500).unwrap();

    // SIGTERM: the blinker stops first, then every output goes to its safe value.
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    let edges = sim.pin(8).unwrap().edges;
    for pin in [8, 12, 13, 5, 6] {
        let p = sim.pin(pin).unwrap();
        assert!(
            p.output && !p.level,
            "pin {pin} after stop: {p:?}\n{}",
            stopped.log
        );
    }
    wait_until("pin 5 quiet at 0", || sim.pin(5).unwrap().duty == 0.0);
    assert_eq!(
        sim.pin(8).unwrap().edges,
        edges,
        "nothing moves pin 8 after the stop"
    );

    // pyfirmata2 on the same board, the same stimulus: the same values.
    let mut py = Command::new(PYTHON)
        .env("PYTHONPATH", &py)
        .args(["-c", PYFIRMATA, sim.pty().to_str().unwrap()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(py.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    // pyfirmata2 writes round(0.25 × 255) = 64 as hwgw does (the pin was at 0 after
    // hwgw's stop): high for 65/256 (checked while it runs).
    let pwm = sim.pin(5).unwrap();
    drop(py.stdin.take());
    assert!(py.wait().unwrap().success(), "pyfirmata2 failed");
    assert!((pwm.duty - 65.0 / 256.0).abs() < 0.002, "{pwm:?}");
    let seen: serde_json::Value = serde_json::from_str(&line).unwrap();
    assert_eq!(seen["d2"], serde_json::Value::Bool(true), "{seen}");
    let a0 = seen["a0"].as_f64().unwrap();
    // pyfirmata2 gives the fraction of 1023 rounded to 4 places: the same code, 511.
    assert_eq!((a0 * 1023.0).round(), 511.0, "{seen}");
    assert!((a0 - volts / 5.0).abs() <= 0.5e-4, "{seen}");
}

/// config/firmata.toml asking for an analog input the Uno lacks (A6): `hwgw run` fails at
/// start, naming the key and what the board has, and exits.
#[test]
fn hwgw_run_refuses_a_board_without_what_the_deployment_asks() {
    let _one = one();
    let sim = SimUno::start().unwrap();
    let dir = TempDir::new("firmata-refused");
    let text = std::fs::read_to_string(CONFIG).unwrap();
    let (port, analog) = (
        "port = \"/dev/ttyACM0\"",
        "analog_in = [{ channel = 0 }, { channel = 1 }]",
    );
    assert!(text.contains(port) && text.contains(analog));
    let text = text
        .replace(port, &format!("port = \"{}\"", sim.pty().display()))
        .replace(analog, "analog_in = [{ channel = 0 }, { channel = 6 }]");
    let config = dir.path().join("firmata.toml");
    std::fs::write(&config, text).unwrap();
    let mut child = Command::new(HWGW)
        .arg("run")
        .arg(&config)
        .arg("--socket")
        .arg(dir.path().join("hwgw.sock"))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.path().join("hwgw.log")).unwrap())
        .spawn()
        .unwrap();
    // The hand-shake takes the banner's 2 s and the replies': it exits well within 60 s.
    let end = std::time::Instant::now() + std::time::Duration::from_secs(60);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if std::time::Instant::now() > end {
            let _ = child.kill();
            panic!("hwgw run did not exit on a refused board");
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    let log = std::fs::read_to_string(dir.path().join("hwgw.log")).unwrap();
    assert!(!status.success(), "{log}");
    assert!(
        log.contains(
            "firmata.analog_in[1].channel: the board has no A6 (its analog channels: A0 (pin 14)"
        ),
        "{log}"
    );
}
