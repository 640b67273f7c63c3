//! ClientThread and OwnThread semantics, send/collect, failures, and the dynamic interface.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use rtt::component::{CallOrIntrospect, IntrospectError};
use rtt::operation::{CallError, ExecutionThread};
use rtt::port::{ConnPolicy, FlowStatus, InputPort, OutputPort};
use rtt::{ActivitySpec, Component, Context, HookResult, Runtime, RuntimeOptions, TaskContext};
use serde_json::json;
use std::sync::{Arc, Mutex};
use std::thread::ThreadId;
use std::time::{Duration, Instant};

#[derive(Default)]
struct Seen {
    log: Mutex<Vec<String>>,
    threads: Mutex<Vec<(String, ThreadId)>>,
}

struct Counter {
    count: i64,
    seen: Arc<Seen>,
    input: InputPort<f64>,
    output: OutputPort<f64>,
}

impl Component for Counter {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.seen
            .log
            .lock()
            .unwrap()
            .push(format!("update {}", self.count));
        self.seen
            .threads
            .lock()
            .unwrap()
            .push(("update".into(), std::thread::current().id()));
        let mut x = 0.0;
        if self.input.read(&mut x) == FlowStatus::NewData {
            self.output.write(&(x + self.count as f64));
        }
        Ok(())
    }
}

fn counter(rt: &Runtime, name: &str, spec: ActivitySpec) -> (TaskContext, Arc<Seen>) {
    let seen = Arc::new(Seen::default());
    let s = seen.clone();
    let t = rt
        .add(name, spec, rtt::InitialState::Stopped, move |iface| {
            let s2 = s.clone();
            iface.own_operation(
                "add",
                "adds to the count, in the component's thread",
                &[("n", "amount")],
                move |c: &mut Counter, (n,): (i64,)| {
                    c.seen.log.lock().unwrap().push(format!("add {n}"));
                    c.seen
                        .threads
                        .lock()
                        .unwrap()
                        .push(("add".into(), std::thread::current().id()));
                    c.count += n;
                    c.count
                },
            )?;
            iface.own_operation("boom", "panics", &[], |_: &mut Counter, (): ()| -> i64 {
                panic!("boom")
            })?;
            iface.client_operation(
                "scale",
                "multiplies, in the caller's thread",
                &[("x", "value"), ("k", "factor")],
                move |(x, k): (f64, f64)| {
                    s2.threads
                        .lock()
                        .unwrap()
                        .push(("scale".into(), std::thread::current().id()));
                    x * k
                },
            )?;
            iface.properties().add("gain", 2.0f64, "a gain")?;
            Ok(Counter {
                count: 0,
                seen: s,
                input: iface.input("in", "numbers in")?,
                output: iface.output("out", "numbers plus the count")?,
            })
        })
        .unwrap();
    (t, seen)
}

fn runtime() -> Runtime {
    Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap()
}

#[test]
fn client_thread_runs_in_the_caller() {
    let rt = runtime();
    let (t, seen) = counter(&rt, "c", ActivitySpec::Slave);
    let scale = t.operation::<(f64, f64), f64>("scale").unwrap();
    // ClientThread runs whatever the component's state.
    assert_eq!(scale.call((3.0, 4.0)).unwrap(), 12.0);
    let mut h = scale.send((2.0, 2.0));
    assert_eq!(
        h.collect_if_done(),
        Some(Ok(4.0)),
        "ClientThread send is done at once"
    );
    assert_eq!(h.collect_if_done(), Some(Err(CallError::AlreadyCollected)));
    let threads = seen.threads.lock().unwrap();
    assert!(
        threads
            .iter()
            .all(|(_, id)| *id == std::thread::current().id())
    );
}

#[test]
fn own_thread_is_queued_and_runs_before_update() {
    let rt = runtime();
    let (t, seen) = counter(&rt, "c", ActivitySpec::Slave);
    let add = t.operation::<(i64,), i64>("add").unwrap();
    t.start().unwrap();
    let mut h = add.send((5,));
    assert_eq!(
        h.collect_if_done(),
        None,
        "nothing runs before the component steps"
    );
    t.step().unwrap();
    assert_eq!(h.collect_if_done(), Some(Ok(5)));
    assert_eq!(*seen.log.lock().unwrap(), vec!["add 5", "update 5"]);
}

#[test]
fn own_thread_runs_on_the_component_thread_and_call_blocks() {
    let rt = runtime();
    let (t, seen) = counter(&rt, "c", ActivitySpec::non_periodic());
    let add = t.operation::<(i64,), i64>("add").unwrap();
    t.start().unwrap();
    assert_eq!(add.call((2,)).unwrap(), 2);
    assert_eq!(add.call((3,)).unwrap(), 5);
    let handles: Vec<_> = (0..10).map(|_| add.send((1,))).collect();
    let results: Vec<i64> = handles.into_iter().map(|h| h.collect().unwrap()).collect();
    assert_eq!(results, (6..=15).collect::<Vec<_>>());
    t.stop().unwrap();
    let threads = seen.threads.lock().unwrap();
    let me = std::thread::current().id();
    let adds: Vec<ThreadId> = threads
        .iter()
        .filter(|(w, _)| w == "add")
        .map(|(_, id)| *id)
        .collect();
    assert_eq!(adds.len(), 12);
    assert!(
        adds.iter().all(|id| *id != me && *id == adds[0]),
        "all on the one component thread"
    );
}

#[test]
fn calls_to_stopped_or_vanished_components_are_errors() {
    let rt = runtime();
    let (t, _) = counter(&rt, "c", ActivitySpec::Slave);
    let add = t.operation::<(i64,), i64>("add").unwrap();
    let e = add.call((1,)).unwrap_err();
    assert_eq!(
        e.to_string(),
        "operation \"add\" runs in component \"c\"'s thread, which is not running (state Stopped)"
    );
    // Queued, then stopped before running: cancelled, not hung.
    t.start().unwrap();
    let h = add.send((1,));
    t.stop().unwrap();
    assert!(matches!(h.collect(), Err(CallError::Cancelled { .. })));
    // The provider goes away entirely.
    drop(t);
    drop(rt);
    assert!(matches!(add.call((1,)), Err(CallError::Vanished { .. })));
}

#[test]
fn a_panicking_operation_is_an_error_and_the_component_runs_on() {
    let rt = runtime();
    let (t, _) = counter(&rt, "c", ActivitySpec::non_periodic());
    t.start().unwrap();
    let boom = t.operation::<(), i64>("boom").unwrap();
    assert_eq!(
        boom.call(()).unwrap_err(),
        CallError::Panicked {
            operation: "boom".into(),
            message: "boom".into()
        }
    );
    assert_eq!(
        t.operation::<(i64,), i64>("add")
            .unwrap()
            .call((7,))
            .unwrap(),
        7
    );
    assert_eq!(t.state(), rtt::TaskState::Running);
}

#[test]
fn dynamic_calls_and_their_errors() {
    let rt = runtime();
    let (t, _) = counter(&rt, "c", ActivitySpec::non_periodic());
    t.start().unwrap();
    assert_eq!(
        t.call_value("scale", vec![json!(1.5), json!(2)]).unwrap(),
        json!(3.0)
    );
    assert_eq!(t.call_value("add", vec![json!(4)]).unwrap(), json!(4));
    let e = t.call_value("scale", vec![json!(1.0)]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "operation \"scale\" takes (f64, f64): 1 arguments given, 2 expected"
    );
    let e = t
        .call_value("scale", vec![json!("x"), json!(1)])
        .unwrap_err();
    assert!(
        e.to_string()
            .contains("invalid type: string \"x\", expected f64"),
        "{e}"
    );
    let e = t.call_value("nope", vec![]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "\"c\" has no operation \"nope\"; it has: add, boom, scale"
    );
    assert!(matches!(
        e,
        CallOrIntrospect::Introspect(IntrospectError::NotFound { .. })
    ));
    let e = t.operation::<(i64,), f64>("add").err().unwrap();
    assert_eq!(
        e.to_string(),
        "operation \"add\" is fn(i64) -> i64, not fn(i64) -> f64"
    );
    let ops = t.operations();
    let add = ops.iter().find(|o| o.name == "add").unwrap();
    assert_eq!(add.thread, ExecutionThread::OwnThread);
    assert_eq!(
        (add.args[0].name.as_str(), add.args[0].doc.as_str()),
        ("n", "amount")
    );
    assert_eq!(add.doc, "adds to the count, in the component's thread");
}

#[test]
fn ports_by_name_with_dynamic_values() {
    let rt = runtime();
    let (t, _) = counter(&rt, "c", ActivitySpec::Slave);
    let names: Vec<String> = t.ports().into_iter().map(|p| p.name).collect();
    assert_eq!(names, vec!["in", "out"]);
    let mut w = t.port("in").unwrap().writer(ConnPolicy::buffer(4)).unwrap();
    let mut r = t
        .port("out")
        .unwrap()
        .reader(ConnPolicy::buffer(4))
        .unwrap();
    assert_eq!(r.read(), (FlowStatus::NoData, None));
    t.start().unwrap();
    t.operation::<(i64,), i64>("add").unwrap().send((10,));
    w.write(json!(1.5)).unwrap();
    t.step().unwrap();
    assert_eq!(r.read(), (FlowStatus::NewData, Some(json!(11.5))));
    assert_eq!(
        t.port("out").unwrap().last_value().unwrap(),
        Some(json!(11.5))
    );
    let e = w.write(json!("fast")).unwrap_err();
    assert!(
        e.to_string()
            .starts_with("port \"in\": expected f64: invalid type: string"),
        "{e}"
    );
    let e = t
        .port("out")
        .unwrap()
        .writer(ConnPolicy::data())
        .err()
        .unwrap();
    assert_eq!(
        e.to_string(),
        "port \"out\" is an output port; writing needs an input port"
    );
    let e = t.port("speed").err().unwrap();
    assert_eq!(
        e.to_string(),
        "\"c\" has no port \"speed\"; it has: in, out"
    );
    // Properties by path.
    t.properties().set_value("gain", json!(3.5)).unwrap();
    assert_eq!(t.properties().get_value("gain").unwrap(), json!(3.5));
}

#[test]
fn named_values_are_listed_and_written_by_name() {
    use rtt::component::NamedValue;
    let rt = runtime();
    let named = |name: &str, value| NamedValue {
        name: name.into(),
        value,
    };
    let (t, _) = counter(&rt, "c", ActivitySpec::Slave);
    let port = t.port("in").unwrap();
    assert!(port.info().values.is_empty());
    assert!(port.name_values(vec![named("P", json!(0.0)), named("D", json!(3.0))]));
    // Once only.
    assert!(!port.name_values(vec![]));
    assert_eq!(
        t.port("in").unwrap().info().values,
        [named("P", json!(0.0)), named("D", json!(3.0))]
    );
    // A name is written as its value, a number as itself; a name the port does not have is
    // refused as any string is.
    let mut w = port.writer(ConnPolicy::buffer(4)).unwrap();
    let mut r = t
        .port("out")
        .unwrap()
        .reader(ConnPolicy::buffer(4))
        .unwrap();
    t.start().unwrap();
    let e = w.write(json!("X")).unwrap_err();
    assert!(
        e.to_string()
            .starts_with("port \"in\": expected f64 or one of P, D: invalid type: string"),
        "{e}"
    );
    w.write(json!("D")).unwrap();
    t.step().unwrap();
    assert_eq!(r.read(), (FlowStatus::NewData, Some(json!(3.0))));
    w.write(json!(1.0)).unwrap();
    t.step().unwrap();
    assert_eq!(r.read(), (FlowStatus::NewData, Some(json!(1.0))));

    // The builder names a port's values; a port it does not have is an error listing those
    // it has.
    struct One;
    impl Component for One {}
    let e = rt
        .add(
            "h",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                let _a: InputPort<f64> = iface.input("a", "")?;
                iface.name_values("b", vec![])?;
                Ok(One)
            },
        )
        .err()
        .unwrap();
    assert!(
        e.to_string().contains("has no port \"b\"; it has: a"),
        "{e}"
    );
    let h = rt
        .add(
            "k",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                let _a: InputPort<f64> = iface.input("a", "")?;
                iface.name_values("a", vec![named("on", json!(1.0))])?;
                Ok(One)
            },
        )
        .unwrap();
    assert_eq!(
        h.port("a").unwrap().info().values,
        [named("on", json!(1.0))]
    );
}

#[test]
fn components_connect_by_name_and_types_are_checked() {
    let rt = runtime();
    let (a, _) = counter(&rt, "a", ActivitySpec::Slave);
    let (b, _) = counter(&rt, "b", ActivitySpec::Slave);
    let info = a
        .port("out")
        .unwrap()
        .connect_to(&*b.port("in").unwrap(), ConnPolicy::buffer(8))
        .unwrap();
    assert_eq!((info.from.as_str(), info.to.as_str()), ("out", "in"));
    let e = a
        .port("in")
        .unwrap()
        .connect_to(&*b.port("in").unwrap(), ConnPolicy::data())
        .unwrap_err();
    assert!(
        e.to_string()
            .contains("a connection goes from an output port to an input port"),
        "{e}"
    );

    struct Other {
        _i: InputPort<String>,
    }
    impl Component for Other {}
    let o = rt
        .add(
            "o",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                Ok(Other {
                    _i: iface.input("in", "text")?,
                })
            },
        )
        .unwrap();
    let e = a
        .port("out")
        .unwrap()
        .connect_to(&*o.port("in").unwrap(), ConnPolicy::data())
        .unwrap_err();
    assert!(e.to_string().contains("the types differ"), "{e}");

    let mut w = a.port("in").unwrap().writer(ConnPolicy::data()).unwrap();
    let mut r = b.port("out").unwrap().reader(ConnPolicy::data()).unwrap();
    a.start().unwrap();
    b.start().unwrap();
    w.write(json!(1.0)).unwrap();
    a.step().unwrap();
    b.step().unwrap();
    assert_eq!(r.read().1, Some(json!(1.0)));
    assert_eq!(a.port("out").unwrap().connections()[0].written, 1);
}

#[test]
fn event_ports_wake_a_non_periodic_component() {
    struct Echo {
        i: InputPort<u32>,
        o: OutputPort<u32>,
    }
    impl Component for Echo {
        fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
            let mut v = 0;
            while self.i.read(&mut v) == FlowStatus::NewData {
                self.o.write(&v);
            }
            Ok(())
        }
    }
    let rt = runtime();
    let t = rt
        .add(
            "echo",
            ActivitySpec::non_periodic(),
            rtt::InitialState::Stopped,
            |iface| {
                Ok(Echo {
                    i: iface.event_input("in", "wakes me")?,
                    o: iface.output("out", "echo")?,
                })
            },
        )
        .unwrap();
    let port_in = t.port("in").unwrap();
    let mut w = port_in.writer(ConnPolicy::buffer(16)).unwrap();
    let mut r = t
        .port("out")
        .unwrap()
        .reader(ConnPolicy::buffer(16))
        .unwrap();
    t.start().unwrap();
    for v in 1..=5u32 {
        w.write(json!(v)).unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            if let (FlowStatus::NewData, Some(x)) = r.read() {
                assert_eq!(x, json!(v));
                break;
            }
            assert!(
                Instant::now() < deadline,
                "event {v} did not wake the component"
            );
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    t.stop().unwrap();
    assert!(t.stats().steps >= 5);
}

struct Holder;
impl Component for Holder {}

/// A started component `name` on `spec` with OwnThread operation `echo`.
fn echo(rt: &Runtime, name: &str, spec: ActivitySpec) -> TaskContext {
    let t = rt
        .add(name, spec, rtt::InitialState::Stopped, |iface| {
            iface.own_operation(
                "echo",
                "its argument",
                &[("x", "")],
                |_: &mut Holder, (x,): (u32,)| x,
            )?;
            Ok(Holder)
        })
        .unwrap();
    t.start().unwrap();
    t
}

/// [`echo`] on a slave activity: its calls run only when it is stepped by hand.
fn stepped_echo(rt: &Runtime) -> TaskContext {
    echo(rt, "held", ActivitySpec::Slave)
}

/// More calls outstanding than an operation's pool of slots: each still gets its own
/// result, and the extra slots are counted.
#[test]
fn calls_beyond_the_slot_pool_are_answered_and_counted() {
    let rt = runtime();
    let t = stepped_echo(&rt);
    let echo = t.operation::<(u32,), u32>("echo").unwrap();
    let handles: Vec<_> = (0..10).map(|i| echo.send((i,))).collect();
    t.step().unwrap();
    let got: Vec<_> = handles.into_iter().map(|h| h.collect().unwrap()).collect();
    assert_eq!(got, (0..10).collect::<Vec<_>>());
    assert_eq!(t.counters().call_slots_allocated, 6);
    // The pool's slots are free again: no more allocations for 4 at a time.
    let handles: Vec<_> = (0..4).map(|i| echo.send((i,))).collect();
    t.step().unwrap();
    assert!(handles.into_iter().all(|h| h.collect().is_ok()));
    assert_eq!(t.counters().call_slots_allocated, 6);
}

/// A full queue refuses the call with an error that says so, counted; what was queued
/// runs, and the slot of the refused call is free again.
#[test]
fn a_full_call_queue_refuses_and_counts() {
    let rt = runtime();
    let t = stepped_echo(&rt);
    let echo = t.operation::<(u32,), u32>("echo").unwrap();
    let cap = rtt::operation::QUEUE_CAPACITY as u32;
    let queued: Vec<_> = (0..cap).map(|i| echo.send((i,))).collect();
    let e = echo.send((cap,)).collect().unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "operation \"echo\" was refused: component \"held\" has {cap} calls queued already"
        )
    );
    assert_eq!(t.counters().calls_refused, 1);
    t.step().unwrap();
    for (i, h) in queued.into_iter().enumerate() {
        assert_eq!(h.collect(), Ok(i as u32));
    }
    let h = echo.send((7,));
    t.step().unwrap();
    assert_eq!(h.collect(), Ok(7));
}

/// Handles dropped before their call ran, and calls cancelled by a stop: the slots come
/// back, and later calls get their own results.
#[test]
fn dropped_and_cancelled_calls_give_their_slots_back() {
    let rt = runtime();
    let t = stepped_echo(&rt);
    let echo = t.operation::<(u32,), u32>("echo").unwrap();
    for round in 0..3 {
        for i in 0..4 {
            drop(echo.send((i,)));
        }
        t.step().unwrap();
        let h = echo.send((round,));
        t.step().unwrap();
        assert_eq!(h.collect(), Ok(round));
    }
    let pending: Vec<_> = (0..4).map(|i| echo.send((i,))).collect();
    t.stop().unwrap();
    for h in pending {
        assert!(matches!(h.collect(), Err(CallError::Cancelled { .. })));
    }
    t.start().unwrap();
    let h = echo.send((9,));
    t.step().unwrap();
    assert_eq!(h.collect(), Ok(9));
    assert_eq!(t.counters().call_slots_allocated, 0);
}

/// Callers on many threads at once, more than the pool: every one gets its own answer.
#[test]
fn concurrent_callers_each_get_their_own_result() {
    let rt = runtime();
    let t = echo(&rt, "busy", ActivitySpec::non_periodic());
    let op = t.operation::<(u32,), u32>("echo").unwrap();
    std::thread::scope(|s| {
        for k in 0..8u32 {
            let echo = op.clone();
            s.spawn(move || {
                for i in 0..2_000u32 {
                    let x = k * 100_000 + i;
                    assert_eq!(echo.call((x,)), Ok(x));
                }
            });
        }
    });
    t.stop().unwrap();
}
