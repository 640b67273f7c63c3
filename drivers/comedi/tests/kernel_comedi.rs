//! The comedi card against the real kernel: comedi_test (analog outputs looped back to
//! the analog inputs) and comedi_parport on qemu's emulated parallel port in the kernel
//! rig. Outputs are checked by independent paths: comedilib called directly (not through
//! the card) for the analog loopback and `comedi_to_phys`, and qemu's own record of the
//! parallel port's register writes for the digital outputs.
#![allow(clippy::unwrap_used, reason = "test code")]

use device_interface::conformance;
use device_interface::time::MonotonicClock;
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut};
use driver_comedi::board::{Board, Daq, comedilib_to_phys};
use driver_comedi::bus::ComediBus;
use driver_comedi::card::ComediCard;
use driver_comedi::config::ComediConfig;
use kernel_rig::{Failed, Trial};
use rtt::{Runtime, RuntimeOptions};
use std::sync::Arc;
use std::time::{Duration, Instant};
use testkit::{ComediBoard, PortTrace, wait_for};

const PATIENCE: Duration = Duration::from_secs(10);
const TEST_BOARD: &str = "/dev/comedi0";
const PARPORT: &str = "/dev/comedi1";

fn wait(what: &str, f: impl FnMut() -> bool) -> Result<(), Failed> {
    wait_for(what, PATIENCE, f).map_err(Failed::from)
}

fn built(section: &str) -> Result<driver_comedi::plugin::Built, Failed> {
    let config: ComediConfig = toml::from_str(section)?;
    driver_comedi::plugin::card(&config, Arc::new(MonotonicClock))
        .map_err(|e| Failed::from(format!("{}: {}", e.key.unwrap_or_default(), e.message)))
}

/// A card of `section`, its bus side running on a periodic component.
struct Up {
    card: Arc<ComediCard>,
    task: rtt::TaskContext,
    _rt: Runtime,
}

fn up(section: &str) -> Result<Up, Failed> {
    let built = built(section)?;
    let card = built.card.clone();
    let rt = Runtime::new(
        Arc::new(device_interface::Registry::new()),
        RuntimeOptions::default(),
    )?;
    let task = run_bus(&rt, built.bus(), section_poll(section))?;
    // The step that opens the board polls it too.
    wait("the board open and polled", || {
        card.is_online() && card.counters().polls >= 1
    })?;
    Ok(Up {
        card,
        task,
        _rt: rt,
    })
}

fn section_poll(section: &str) -> Duration {
    let config: ComediConfig = toml::from_str(section).unwrap();
    Duration::from_millis(u64::from(config.poll_ms))
}

fn run_bus(rt: &Runtime, mut bus: ComediBus, period: Duration) -> Result<rtt::TaskContext, Failed> {
    let step = move || bus.step(Instant::now());
    let task = driver_api::periodic_bus(rt, "comedi", period, Default::default(), step)?
        .pop()
        .unwrap();
    task.start()?;
    Ok(task)
}

/// Waits for two more polls of `card` (one that began after now).
fn polled(card: &ComediCard) -> Result<(), Failed> {
    let from = card.counters().polls;
    wait("two more polls", || card.counters().polls >= from + 2)
}

fn analog_outputs_read_back_on_the_inputs_in_physical_units() -> Result<(), Failed> {
    let _board = ComediBoard::comedi_test(TEST_BOARD)?;
    // Channels 0–3 in range 0 (±10 V), 4–7 in range 1 (±5 V), outputs and inputs alike.
    let up = up(&format!(
        r#"device = "{TEST_BOARD}"
        poll_ms = 2
        analog_in = [{{ channels = [0, 1, 2, 3], range = 0 }}, {{ channels = [4, 5, 6, 7], range = 1 }}]
        analog_out = [{{ channels = [0, 1, 2, 3], range = 0 }}, {{ channels = [4, 5, 6, 7], range = 1 }}]"#
    ))?;
    let c = &*up.card;
    let mut bare = Board::open(TEST_BOARD)?;
    let desc = bare.describe()?;
    for (ch, range, lo, hi) in [(0u32, 0u32, -10.0, 10.0), (5, 1, -5.0, 5.0)] {
        assert_eq!(AnalogIn::range(c, ch)?.lowest, lo);
        assert_eq!(AnalogIn::range(c, ch)?.highest, hi);
        let comedi_range = desc.subdevices[0].channels[ch as usize].ranges[range as usize];
        for value in [lo, hi, 0.0, lo / 3.0, hi * 0.6180, hi - 1e-3] {
            c.write(ch, value)?;
            let raw = c.read_back_raw(ch)? as u32;
            // The board has it: comedilib reads it back on the analog input, directly.
            assert_eq!(bare.data_read(0, ch, range, 0)?, raw, "ch{ch} {value} V");
            polled(c)?;
            assert_eq!(c.read_raw(ch)?, i64::from(raw), "ch{ch} {value} V");
            let ours = c.read(ch)?;
            let theirs = comedilib_to_phys(raw, &comedi_range, 65535);
            assert_eq!(ours, theirs, "ch{ch} raw {raw}: hwgw, comedi_to_phys");
            if value == lo || value == hi {
                assert_eq!(ours, value, "a range end is exact");
            }
        }
    }
    // Every raw value comedi_to_phys converts, hwgw does alike (the whole 16-bit table).
    let scale = AnalogIn::scale(c, 0)?;
    let r0 = desc.subdevices[0].channels[0].ranges[0];
    for raw in 0..=65535u32 {
        let (ours, theirs) = (
            scale.to_physical(i64::from(raw)),
            comedilib_to_phys(raw, &r0, 65535),
        );
        assert_eq!(ours, theirs, "raw {raw}");
    }
    // A range selected at run time: channel 0's output is at 10 V - 1 mV in ±10 V; read in
    // ±5 V the same raw value is near +5 V.
    c.select_range(0, 1)?;
    polled(c)?;
    let raw = c.read_raw(0)?;
    assert_eq!(AnalogIn::range(c, 0)?.highest, 5.0);
    assert!((c.read(0)? - (raw as f64 / 65535.0 * 10.0 - 5.0)).abs() < 1e-9);
    up.task.stop()?;
    Ok(())
}

fn a_board_that_goes_away_is_offline_and_back_when_configured() -> Result<(), Failed> {
    let board = ComediBoard::comedi_test(TEST_BOARD)?;
    let up = up(&format!(
        r#"device = "{TEST_BOARD}"
        poll_ms = 2
        analog_in = [{{ channels = [2] }}]
        analog_out = [{{ channels = [2] }}]"#
    ))?;
    let c = &*up.card;
    c.write(0, 2.5)?;
    let written = c.read_back_raw(0)?;
    polled(c)?;
    board.remove()?;
    wait("the card offline", || !c.is_online())?;
    assert!(matches!(c.read_raw(0), Err(DeviceError::Offline)));
    assert!(matches!(c.write(0, 1.0), Err(DeviceError::Offline)));
    // The bus thread counts the fall just after the card shows it.
    wait("the fall counted", || c.counters().went_offline >= 1)?;
    let status = c.counters();
    assert_eq!(status.went_offline, 1);
    let why = status.last_error.unwrap_or_default();
    assert!(why.contains(TEST_BOARD), "{why}");
    // Attached again: comedi_test starts with its outputs at 0; the card opens it and
    // writes back what was last written to it.
    board.configure()?;
    wait("the card online again", || c.is_online())?;
    polled(c)?;
    assert_eq!(c.counters().opened, 2);
    assert_eq!(
        c.read_raw(0)?,
        written,
        "the output written before it went away"
    );
    let mut bare = Board::open(TEST_BOARD)?;
    assert_eq!(i64::from(bare.data_read(0, 2, 0, 0)?), written);
    up.task.stop()?;
    Ok(())
}

fn parport_data_lines_as_digital_out_seen_by_qemu() -> Result<(), Failed> {
    let _board = ComediBoard::parport(PARPORT)?;
    let trace = PortTrace::open()?;
    let before = trace.data_writes()?.len();
    let up = up(&format!(
        r#"device = "{PARPORT}"
        poll_ms = 5
        output = [{{ subdevice = 0 }}]
        input = [{{ subdevice = 1 }}]"#
    ))?;
    let c = &*up.card;
    polled(c)?;
    assert_eq!(c.output_count(), 8);
    assert_eq!(c.input_count(), 5);
    // Opening found the data lines inputs (comedi_parport attaches them so, with the
    // port's data register at 0, which they read), and latched what they read, once,
    // before they drive: the lines keep their level.
    let opened: Vec<u8> = trace.data_writes()?[before..]
        .iter()
        .map(|w| w.value)
        .collect();
    assert_eq!(opened, [0x00], "one latch of the levels the lines had");
    assert_eq!(c.check_sequence(0, 7)?, 0x00);
    c.set_sequence(0, 7, 0)?;
    trace.wait_data(0x00, PATIENCE)?;
    for (bit, on) in [(0, true), (7, true), (0, false), (3, true)] {
        c.set_bit(bit, on)?;
    }
    trace.wait_data(0x88, PATIENCE)?;
    // A sequence of the eight lines is one write of the data register.
    let n = trace.data_writes()?.len();
    c.set_sequence(0, 7, 0x5a)?;
    trace.wait_data(0x5a, PATIENCE)?;
    assert_eq!(
        trace.data_writes()?.len(),
        n + 1,
        "one write for the sequence"
    );
    assert_eq!(c.check_sequence(0, 7)?, 0x5a);
    c.set_sequence(2, 5, 0b1111)?;
    trace.wait_data(0x7e, PATIENCE)?;
    // Each write hwgw made, in order, as qemu recorded them.
    let values: Vec<u8> = trace.data_writes()?[before..]
        .iter()
        .map(|w| w.value)
        .collect();
    assert_eq!(values, [0x00, 0x00, 0x01, 0x81, 0x80, 0x88, 0x5a, 0x7e]);
    // The status lines read as the port's status register has them (qemu's idle port).
    for bit in 0..5 {
        c.read_bit(bit)?;
    }
    up.task.stop()?;
    Ok(())
}

/// A component that does nothing but step.
struct Idle;

impl rtt::Component for Idle {}

fn thread_scope_on_the_parallel_port() -> Result<(), Failed> {
    let _board = ComediBoard::parport(PARPORT)?;
    let trace = PortTrace::open()?;
    let section = format!(
        r#"device = "{PARPORT}"
        poll_ms = 2
        output = [{{ subdevice = 0, initial = false }}]"#
    );
    let built = built(&section)?;
    let card = built.card.clone();
    let mut bus = built.bus();
    // Open before ThreadScope runs, so its first pulse finds the port.
    bus.step(Instant::now());
    assert!(card.is_online(), "{:?}", card.counters());
    let registry = Arc::new(device_interface::Registry::new());
    registry.register_card("lpt", card.devices())?;
    registry.alias(
        device_interface::Interface::DigitalOut,
        "ThreadScope",
        "lpt",
    )?;
    let from = trace.data_writes()?.len();
    let rt = Runtime::new(
        registry,
        RuntimeOptions {
            thread_scope: true,
            ..RuntimeOptions::default()
        },
    )?;
    // Thread 1: the card's own bus component; threads 2 and 3: two periodic components.
    let io = run_bus(&rt, bus, Duration::from_millis(2))?;
    let mut tasks = Vec::new();
    for (name, ms) in [("fast", 1), ("slow", 3)] {
        let t = rt.add(
            name,
            rtt::ActivitySpec::periodic(Duration::from_millis(ms)),
            rtt::InitialState::Stopped,
            |_| Ok(Idle),
        )?;
        t.start()?;
        tasks.push(t);
    }
    let rises = |writes: &[testkit::comedi::PortWrite], bit: u32| {
        let mut last = false;
        let mut n = 0;
        for w in writes {
            let on = w.value >> bit & 1 == 1;
            n += usize::from(on && !last);
            last = on;
        }
        n
    };
    wait("20 pulses of each thread on the port", || {
        trace
            .data_writes()
            .is_ok_and(|w| (1..=3).all(|b| rises(&w[from..], b) >= 20))
    })?;
    for t in &tasks {
        t.stop()?;
    }
    io.stop()?;
    let writes = trace.data_writes()?;
    let writes = &writes[from..];
    // Every write is one thread's edge: exactly one line changes, and all end low.
    let mut prev = 0u8;
    for (i, w) in writes.iter().enumerate() {
        assert_eq!(
            (w.value ^ prev).count_ones(),
            1,
            "write {i}: {prev:#04x} → {:#04x}",
            w.value
        );
        assert_eq!(
            w.value & !0b1110,
            0,
            "write {i}: {:#04x} has a line no thread owns",
            w.value
        );
        prev = w.value;
    }
    assert_eq!(prev, 0, "a line left high");
    let (fast, slow) = (rises(writes, 2), rises(writes, 3));
    println!(
        "ThreadScope on the port: {} writes; pulses: bus {}, fast {fast}, slow {slow}",
        writes.len(),
        rises(writes, 1)
    );
    assert_eq!(rt.thread_scope().errors(), 0);
    Ok(())
}

fn conformance_kit_over_the_cards_interfaces() -> Result<(), Failed> {
    let _test = ComediBoard::comedi_test(TEST_BOARD)?;
    let _lpt = ComediBoard::parport(PARPORT)?;
    let ai = up(&format!(
        r#"device = "{TEST_BOARD}"
        poll_ms = 1
        analog_in = [{{ channels = [0, 1, 2, 3] }}, {{ channels = [4, 5], range = 1 }}]"#
    ))?;
    // The stimulus: comedilib writes the output of the channel, outside the card.
    let mut bare = Board::open(TEST_BOARD)?;
    let card = ai.card.clone();
    let mut stim = |ch: u32, raw: i64| {
        bare.data_write(1, [0, 1, 2, 3, 4, 5][ch as usize], 0, 0, raw as u32)
            .unwrap();
        polled(&card).unwrap();
    };
    conformance::check_analog_in(ai.card.as_ref(), Some(&mut stim)).assert_complete();
    ai.task.stop()?;
    drop(ai);
    let ao = up(&format!(
        r#"device = "{TEST_BOARD}"
        analog_out = [{{ channels = [0, 1] }}, {{ channels = [6, 7], range = 1 }}]"#
    ))?;
    conformance::check_analog_out(ao.card.as_ref()).assert_complete();
    ao.task.stop()?;
    // Polled once, at open: qemu's port flips its ACK and BUSY status lines at each read
    // of the status register, and the kit wants inputs that hold still while it runs.
    let lpt = up(&format!(
        r#"device = "{PARPORT}"
        poll_ms = 60000
        output = [{{ subdevice = 0 }}, {{ subdevice = 2 }}]
        input = [{{ subdevice = 1 }}]"#
    ))?;
    conformance::check_digital_out(lpt.card.as_ref()).assert_complete();
    conformance::check_digital_in(lpt.card.as_ref(), None).assert_pass();
    lpt.task.stop()?;
    Ok(())
}

fn a_missing_board_and_a_wrong_channel_are_named() -> Result<(), Failed> {
    let err = |section: String| {
        let config: ComediConfig = toml::from_str(&section).unwrap();
        match driver_comedi::plugin::card(&config, Arc::new(MonotonicClock)) {
            Ok(_) => panic!("built: {section}"),
            Err(e) => format!("{}: {}", e.key.unwrap_or_default(), e.message),
        }
    };
    // Nothing attached to comedi3.
    let e = err("device = \"/dev/comedi3\"\nanalog_in = [{}]".into());
    assert!(e.contains("device: comedi_open on /dev/comedi3"), "{e}");
    assert!(e.contains("/dev/comedi0, /dev/comedi1"), "{e}");
    // A failing call's error is its own, not an earlier one's: after comedi_open failed
    // with ENODEV, a bit-field call on an analog subdevice fails, and not as "gone".
    let _ = Board::open("/dev/comedi3");
    {
        let _board = ComediBoard::comedi_test(TEST_BOARD)?;
        let mut bare = Board::open(TEST_BOARD)?;
        let e = bare
            .bitfield(0, 0, 0, 0)
            .expect_err("bits of an AI subdevice");
        assert!(!e.gone(), "{e}");
        println!("bits of an AI subdevice: {e}");
    }
    // Not a comedi device: refused before comedilib opens it.
    let e = err("device = \"/dev/null\"\nanalog_in = [{}]".into());
    assert!(e.contains("comedi_open on /dev/null: not a comedi device: it is character device 1:3 (comedi's are character devices of major 98, /dev/comediN)"), "{e}");
    let _board = ComediBoard::comedi_test(TEST_BOARD)?;
    let e = err(format!(
        "device = \"{TEST_BOARD}\"\nanalog_in = [{{ channels = [8] }}]"
    ));
    assert!(
        e.contains("analog_in[0].channels: subdevice 0 (AI) has no channel 8 (it has 0..=7)"),
        "{e}"
    );
    let e = err(format!("device = \"{TEST_BOARD}\"\ninput = [{{}}]"));
    assert!(
        e.contains("has no DI or DIO subdevice (it has: 0 AI (8 channels), 1 AO (8 channels))"),
        "{e}"
    );
    let e = err(format!(
        "device = \"{TEST_BOARD}\"\nanalog_in = [{{ range = 2 }}]"
    ));
    assert!(
        e.contains("has no range 2 (its ranges: 0 [-10, 10] V, 1 [-5, 5] V)"),
        "{e}"
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::comedi(),
        vec![
            Trial::test(
                "analog_outputs_read_back_on_the_inputs_in_physical_units",
                analog_outputs_read_back_on_the_inputs_in_physical_units,
            ),
            Trial::test(
                "a_board_that_goes_away_is_offline_and_back_when_configured",
                a_board_that_goes_away_is_offline_and_back_when_configured,
            ),
            Trial::test(
                "parport_data_lines_as_digital_out_seen_by_qemu",
                parport_data_lines_as_digital_out_seen_by_qemu,
            ),
            Trial::test(
                "thread_scope_on_the_parallel_port",
                thread_scope_on_the_parallel_port,
            ),
            Trial::test(
                "conformance_kit_over_the_cards_interfaces",
                conformance_kit_over_the_cards_interfaces,
            ),
            Trial::test(
                "a_missing_board_and_a_wrong_channel_are_named",
                a_missing_board_and_a_wrong_channel_are_named,
            ),
        ],
    )
}
