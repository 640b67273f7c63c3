//! A stopped component's activity changed (RTT's setPeriod, setPriority) and slave
//! components stepped by their master, in order, on the master's thread (manual L747–752,
//! L4690–4700, L4725–4768, L4786–4803).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use rtt::activity::{ActivitySpec, SchedPolicy, ThreadOptions};
use rtt::{Component, Context, HookResult, InitialState, Runtime, RuntimeOptions};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Notes its name and a sequence number at each step.
struct Noting {
    name: &'static str,
    log: Arc<Mutex<Vec<(u64, &'static str)>>>,
    seq: Arc<std::sync::atomic::AtomicU64>,
}

impl Component for Noting {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let n = self.seq.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        self.log.lock().unwrap().push((n, self.name));
        Ok(())
    }
}

#[test]
fn slaves_step_in_order_after_their_master() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let log = Arc::new(Mutex::new(Vec::new()));
    let seq = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let add = |name: &'static str, spec: ActivitySpec| {
        let (log, seq) = (log.clone(), seq.clone());
        rt.add(name, spec, InitialState::Stopped, move |_| {
            Ok(Noting { name, log, seq })
        })
        .unwrap()
    };
    let master = add("master", ActivitySpec::periodic(Duration::from_millis(2)));
    let first = add("first", ActivitySpec::Slave);
    let second = add("second", ActivitySpec::Slave);
    let third = add("third", ActivitySpec::Slave);
    master.add_slave(&first).unwrap();
    master.add_slave(&second).unwrap();
    first.add_slave(&third).unwrap();
    // A master must not step itself, through its slaves or not; a slave needs a slave
    // activity.
    assert!(third.add_slave(&first).is_err());
    assert!(first.add_slave(&master).is_err());
    assert_eq!(master.slaves(), ["first", "second"]);
    for t in [&first, &second, &third] {
        t.start().unwrap();
    }
    master.start().unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while log.lock().unwrap().len() < 400 {
        assert!(std::time::Instant::now() < deadline, "100 master steps");
        std::thread::sleep(Duration::from_millis(5));
    }
    master.stop().unwrap();
    let log = log.lock().unwrap().clone();
    // Every master step, then first, then first's slave, then second: sequence numbers in
    // that order, round after round.
    let names: Vec<&str> = log.iter().map(|(_, n)| *n).collect();
    for (i, chunk) in names.chunks_exact(4).enumerate() {
        assert_eq!(chunk, ["master", "first", "third", "second"], "round {i}");
    }
    assert!(log.windows(2).all(|w| w[1].0 == w[0].0 + 1));
    // A slave taken out of the runtime is stepped no more.
    rt.remove("second").unwrap();
    assert_eq!(master.slaves(), ["first"]);
}

#[test]
fn a_stopped_components_period_and_thread_change_at_its_next_start() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let t = rt
        .add(
            "p",
            ActivitySpec::periodic(Duration::from_millis(50)),
            InitialState::Stopped,
            |_| Ok(Nothing),
        )
        .unwrap();
    t.start().unwrap();
    let e = t.set_period(Duration::from_millis(5)).unwrap_err();
    assert!(
        e.to_string().contains("cannot set_period in state Running"),
        "{e}"
    );
    t.stop().unwrap();
    t.set_period(Duration::from_millis(5)).unwrap();
    assert!(t.set_period(Duration::ZERO).is_err());
    let fifo = ThreadOptions {
        policy: SchedPolicy::Fifo,
        priority: 10,
        ..ThreadOptions::default()
    };
    t.set_thread(fifo.clone()).unwrap();
    match t.activity().current() {
        ActivitySpec::Periodic { period, thread, .. } => {
            assert_eq!(period, Duration::from_millis(5));
            assert_eq!(thread, fifo);
        }
        other => panic!("{other:?}"),
    }
    // The slave of a runtime has no thread to set.
    let s = rt
        .add("s", ActivitySpec::Slave, InitialState::Stopped, |_| {
            Ok(Nothing)
        })
        .unwrap();
    assert!(s.set_thread(ThreadOptions::default()).is_err());
    assert!(s.set_period(Duration::from_millis(1)).is_err());
}

struct Nothing;
impl Component for Nothing {}

/// Blocks in its own code (a read with no timeout) until its break hook lets it go.
struct Blocked {
    rx: std::sync::mpsc::Receiver<()>,
    entered: std::sync::mpsc::Sender<()>,
}

impl Component for Blocked {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let _ = self.entered.send(());
        let _ = self.rx.recv();
        Ok(())
    }
}

#[test]
fn the_break_hook_lets_a_stop_interrupt_a_blocked_step() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let (entered_tx, entered) = std::sync::mpsc::channel();
    let t = rt
        .add(
            "blocked",
            ActivitySpec::non_periodic(),
            InitialState::Stopped,
            move |iface| {
                let (tx, rx) = std::sync::mpsc::channel();
                let tx = Mutex::new(tx);
                iface.on_break(move || {
                    let _ = tx.lock().unwrap().send(());
                });
                Ok(Blocked {
                    rx,
                    entered: entered_tx,
                })
            },
        )
        .unwrap();
    t.start().unwrap();
    t.trigger();
    entered.recv_timeout(Duration::from_secs(20)).unwrap();
    // The step is blocked now; the stop breaks it and returns.
    let (done_tx, done) = std::sync::mpsc::channel();
    std::thread::spawn(move || done_tx.send(t.stop().map(|()| t.state())).unwrap());
    assert_eq!(
        done.recv_timeout(Duration::from_secs(20)).unwrap().unwrap(),
        rtt::TaskState::Stopped
    );
}

/// Finds its peer by the alias its deployment gave.
struct Looks(Arc<Mutex<Option<String>>>);
impl Component for Looks {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        *self.0.lock().unwrap() = Some(ctx.peer("device")?.name().to_string());
        Ok(())
    }
}

#[test]
fn a_peer_is_found_by_its_alias() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    rt.add(
        "press_io",
        ActivitySpec::Slave,
        InitialState::Stopped,
        |_| Ok(Nothing),
    )
    .unwrap();
    let seen = Arc::new(Mutex::new(None));
    let s = seen.clone();
    let t = rt
        .add(
            "looks",
            ActivitySpec::Slave,
            InitialState::PreOperational,
            move |_| Ok(Looks(s)),
        )
        .unwrap();
    assert!(t.configure().is_err(), "no peer \"device\" yet");
    t.set_peer_alias("device", "press_io");
    t.configure().unwrap();
    assert_eq!(seen.lock().unwrap().as_deref(), Some("press_io"));
}
