//! The manual's socket-device scenario (seed 000, L886–953) on a simulated card, stepped
//! by hand so every step is one reading: one missed packet → a warning, the component
//! still Running; five in a row → RunTimeError; `recover` → Running; corrupt data →
//! Exception; `recover` → the reset hook, Stopped (or PreOperational when the reset
//! fails); counters reset at cleanup (manual L832–884).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::{AnalogIn, DeviceError, Registry};
use driver_sim::{SimCard, SimConfig, SimFault};
use rtt::component::LifecycleError;
use rtt::faults::{FaultCounter, FaultPolicy};
use rtt::{
    ActivitySpec, Component, Context, HookError, HookResult, InitialState, Runtime, RuntimeOptions,
    TaskContext, TaskState,
};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};

/// Reads channel 0 of an analog input each step, as the manual's component reads its
/// socket: a missed reading counts against the policy; corrupt data is an exception.
struct SocketReader {
    device: Arc<dyn AnalogIn>,
    faults: FaultCounter,
    resets: Arc<AtomicU32>,
    reset_fails: Arc<AtomicBool>,
}

impl SocketReader {
    fn read(&mut self, ctx: &mut Context<'_>) {
        match self.device.read(0) {
            Ok(v) if v.is_finite() => self.faults.good(ctx),
            Ok(v) => ctx.exception(format!("corrupt data: {v}")),
            // The sim card's bus fault stands for the socket's garbled packet.
            Err(e @ DeviceError::Bus { .. }) => ctx.exception(format!("corrupt data: {e}")),
            Err(e) if e.is_transient() => self.faults.missed(ctx),
            Err(e) => ctx.exception(e.to_string()),
        }
    }
}

impl Component for SocketReader {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        self.read(ctx);
        Ok(())
    }
    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        self.read(ctx);
    }
    fn reset_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.resets.fetch_add(1, Ordering::SeqCst);
        if self.reset_fails.load(Ordering::SeqCst) {
            return Err(HookError::new("the socket cannot be reopened"));
        }
        Ok(())
    }
}

struct Rig {
    card: Arc<SimCard>,
    task: TaskContext,
    resets: Arc<AtomicU32>,
    reset_fails: Arc<AtomicBool>,
    _rt: Runtime,
}

fn rig() -> Rig {
    let registry = Arc::new(Registry::new());
    let card = SimCard::new(&SimConfig::demo(), Arc::new(rtt::time::MonotonicClock)).unwrap();
    card.register(&registry, "sim").unwrap();
    // The sim card's inputs are fresh once it has stepped.
    card.step();
    let rt = Runtime::new(registry.clone(), RuntimeOptions::default()).unwrap();
    let (resets, reset_fails) = (
        Arc::new(AtomicU32::new(0)),
        Arc::new(AtomicBool::new(false)),
    );
    let (r, f) = (resets.clone(), reset_fails.clone());
    let task = rt
        .add(
            "socket",
            ActivitySpec::Slave,
            InitialState::Stopped,
            move |_| {
                Ok(SocketReader {
                    device: registry.analog_in().lookup("sim").unwrap(),
                    faults: FaultCounter::new(FaultPolicy::default()),
                    resets: r,
                    reset_fails: f,
                })
            },
        )
        .unwrap();
    Rig {
        card,
        task,
        resets,
        reset_fails,
        _rt: rt,
    }
}

impl Rig {
    /// One packet: the card steps (a reading arrives, unless a fault says otherwise), the
    /// component steps.
    fn packet(&self) {
        self.card.step();
        self.task.step().unwrap();
    }
}

#[test]
fn the_socket_device_scenario() {
    let r = rig();
    r.task.start().unwrap();
    r.packet();
    assert_eq!(r.task.state(), TaskState::Running);
    assert!(!r.task.counters().warning);

    // One missed packet: a warning, still Running.
    r.card.set_fault(SimFault::Stale);
    r.packet();
    let c = r.task.counters();
    assert_eq!(r.task.state(), TaskState::Running);
    assert!(c.warning && c.warnings == 1, "{c:?}");
    // The next good one clears it.
    r.card.set_fault(SimFault::None);
    r.packet();
    assert!(!r.task.counters().warning);
    assert_eq!(r.task.counters().warnings, 1);

    // Five missed in a row: RunTimeError at the fifth.
    r.card.set_fault(SimFault::Offline);
    for i in 1..=4 {
        r.packet();
        assert_eq!(r.task.state(), TaskState::Running, "after {i} missed");
    }
    r.packet();
    assert_eq!(r.task.state(), TaskState::RunTimeError);
    assert_eq!(r.task.counters().runtime_errors, 1);
    assert_eq!(r.task.counters().warnings, 2, "raised once for the run");
    // Still missing: the error hook steps, the state stays.
    r.packet();
    assert_eq!(r.task.state(), TaskState::RunTimeError);
    // recover → Running (the supervisor's command; the device is back).
    r.card.set_fault(SimFault::None);
    r.task.recover().unwrap();
    assert_eq!(r.task.state(), TaskState::Running);
    r.packet();
    assert!(!r.task.counters().warning);

    // Corrupt data: Exception, with the reason kept.
    r.card.set_fault(SimFault::Bus("checksum mismatch".into()));
    r.packet();
    assert_eq!(r.task.state(), TaskState::Exception);
    let c = r.task.counters();
    assert_eq!(c.exceptions, 1);
    assert!(
        c.last_error
            .as_deref()
            .unwrap_or("")
            .contains("corrupt data"),
        "{c:?}"
    );
    // recover → the reset hook → Stopped; it starts again.
    r.card.set_fault(SimFault::None);
    r.task.recover().unwrap();
    assert_eq!(r.resets.load(Ordering::SeqCst), 1);
    assert_eq!(r.task.state(), TaskState::Stopped);
    r.task.start().unwrap();
    r.packet();
    assert_eq!(r.task.state(), TaskState::Running);

    // Counters start again from zero at cleanup.
    r.task.stop().unwrap();
    r.task.cleanup().unwrap();
    let c = r.task.counters();
    assert_eq!(
        (c.warnings, c.runtime_errors, c.exceptions, c.failed_hooks),
        (0, 0, 0, 0),
        "{c:?}"
    );
    assert!(c.last_error.is_none() && !c.warning);
}

#[test]
fn a_failed_reset_leaves_the_component_to_be_configured_again() {
    let r = rig();
    r.task.start().unwrap();
    r.card.set_fault(SimFault::Bus("garbage".into()));
    r.packet();
    assert_eq!(r.task.state(), TaskState::Exception);
    r.reset_fails.store(true, Ordering::SeqCst);
    let e = r.task.recover().unwrap_err();
    assert!(
        matches!(
            e,
            LifecycleError::HookFailed {
                hook: "reset_hook",
                ..
            }
        ),
        "{e}"
    );
    assert_eq!(r.task.state(), TaskState::PreOperational);
    r.reset_fails.store(false, Ordering::SeqCst);
    r.card.set_fault(SimFault::None);
    r.task.configure().unwrap();
    r.task.start().unwrap();
    r.packet();
    assert_eq!(r.task.state(), TaskState::Running);
}

struct Raises;
impl Component for Raises {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        ctx.exception("the hardware answered with nonsense");
        Ok(())
    }
}

#[test]
fn any_hook_can_raise_an_exception() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let t = rt
        .add("raises", ActivitySpec::Slave, InitialState::Stopped, |_| {
            Ok(Raises)
        })
        .unwrap();
    let e = t.start().unwrap_err();
    assert!(
        e.to_string()
            .contains("start_hook raised an exception: the hardware answered with nonsense"),
        "{e}"
    );
    assert_eq!(t.state(), TaskState::Exception);
    assert_eq!(t.counters().exceptions, 1);
}
