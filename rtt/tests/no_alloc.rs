//! The real-time paths allocate nothing: port write/read of pre-sized samples, a
//! ClientThread call, an OwnThread send and collect (on the caller's thread and on the
//! engine's), a write into a recording's journal, a real-time log call (written, filtered out, or dropped on a full queue),
//! and a whole periodic step (sleep, statistics, ThreadScope, engine, update). A counting global allocator counts per thread, so other tests running at the
//! same time cannot disturb the counts.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]
#![allow(
    unsafe_code,
    reason = "a GlobalAlloc implementation is unsafe by definition"
)]

use device_interface::Registry;
use driver_sim::{SimCard, SimConfig};
use rtt::port::{ConnPolicy, FlowStatus, InputPort, OutputPort, connect};
use rtt::{ActivitySpec, Component, Context, HookResult, Runtime, RuntimeOptions};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

struct Counting;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
    static FREES: Cell<u64> = const { Cell::new(0) };
}

// SAFETY: defers every call to the system allocator unchanged; only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as our caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        let _ = FREES.try_with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as our caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as our caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations() -> u64 {
    ALLOCATIONS.with(Cell::get)
}

/// Allocations made by `f` on this thread.
fn count(f: impl FnOnce()) -> u64 {
    let before = allocations();
    f();
    allocations() - before
}

/// Frees made by `f` on this thread.
fn frees(f: impl FnOnce()) -> u64 {
    let before = FREES.with(Cell::get);
    f();
    FREES.with(Cell::get) - before
}

struct Writes {
    out: OutputPort<f64>,
}

impl Component for Writes {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.out.write(&1.0);
        Ok(())
    }
}

/// A recording's (or a watch's) reader let go on another thread: the writer's next step
/// forgets the connection without freeing its samples — a later reader frees them.
#[test]
fn a_writer_never_frees_a_connection_a_dynamic_reader_let_go_of() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let task = rt
        .add("w", ActivitySpec::Slave, rtt::InitialState::Stopped, |i| {
            Ok(Writes {
                out: i.output("out", "ones")?,
            })
        })
        .unwrap();
    task.start().unwrap();
    let port = task.port("out").unwrap();
    let reader = port.stamped_reader(ConnPolicy::buffer(4096)).unwrap();
    task.step().unwrap();
    std::thread::spawn(move || drop(reader)).join().unwrap();
    assert_eq!(
        frees(|| task.step().unwrap()),
        0,
        "the writer freed the connection"
    );
    assert!(port.connections().is_empty());
    // The next reader let go of frees the first's samples, off the writer's thread.
    let again = port.stamped_reader(ConnPolicy::buffer(4)).unwrap();
    let freed = std::thread::spawn(move || frees(|| drop(again)))
        .join()
        .unwrap();
    assert!(freed > 2, "{freed}");
}

/// A port tapped into a journal (a recording): writing appends, full or not, without
/// allocating or freeing; the tap let go of off the writer's thread is freed there, not by
/// the writer.
#[test]
fn a_journal_tapped_write_allocates_and_frees_nothing() {
    use rtt::port::journal::{Journal, tap};
    let mut out = OutputPort::<f64>::new("o");
    let journal = Arc::new(Journal::new(64));
    let t = tap(&out, &journal, 0, "recording").unwrap();
    out.write(&0.5); // takes up the tap, and this thread its lane
    let n = count(|| {
        for i in 0..10_000 {
            // The journal fills at 64 and drops after: that must not allocate either.
            out.write(&f64::from(i));
        }
    });
    assert_eq!(n, 0);
    assert!(journal.dropped() > 0);
    std::thread::spawn(move || drop(t)).join().unwrap();
    assert_eq!(frees(|| out.write(&1.0)), 0, "the writer freed the tap");
    assert_eq!(journal.drain(usize::MAX, |_| {}), 64);
}

#[derive(Clone, Default, serde::Serialize, serde::Deserialize)]
struct Sample64 {
    values: [u64; 8],
}

#[test]
fn the_counter_counts() {
    assert_eq!(count(|| drop(std::hint::black_box(vec![0u8; 16]))), 1);
    assert_eq!(count(|| drop(std::hint::black_box(String::from("x")))), 1);
}

#[test]
fn port_write_read_allocates_nothing() {
    for policy in [
        ConnPolicy::data(),
        ConnPolicy::buffer(8),
        ConnPolicy::circular_buffer(4),
    ] {
        let mut out = OutputPort::<f64>::new("o");
        let mut inp = InputPort::<f64>::new("i");
        connect(&out, &inp, policy).unwrap();
        let mut x = 0.0;
        out.write(&1.0); // takes up the connection
        inp.read(&mut x);
        let n = count(|| {
            for i in 0..10_000 {
                out.write(&f64::from(i));
                // Buffers fill and drop on purpose: overflow must not allocate either.
                if i % 3 == 0 {
                    assert_ne!(inp.read(&mut x), FlowStatus::NoData);
                }
            }
        });
        assert_eq!(n, 0, "f64 {policy:?}");

        let mut out = OutputPort::<Sample64>::new("o");
        let mut inp = InputPort::<Sample64>::new("i");
        connect(&out, &inp, policy).unwrap();
        let mut s = Sample64::default();
        out.write(&s);
        inp.read(&mut s);
        let n = count(|| {
            for i in 0..10_000u64 {
                s.values[0] = i;
                out.write(&s);
                inp.read(&mut s);
            }
        });
        assert_eq!(n, 0, "64-byte struct {policy:?}");
    }
}

#[test]
fn pre_sized_vec_samples_allocate_nothing() {
    for policy in [
        ConnPolicy::data(),
        ConnPolicy::buffer(4),
        ConnPolicy::circular_buffer(2),
    ] {
        let sample = vec![0.0f64; 64];
        let mut out = OutputPort::with_sample("o", sample.clone());
        let mut inp = InputPort::with_sample("i", sample.clone());
        connect(&out, &inp, policy).unwrap();
        let mut got = sample.clone();
        let mut v = vec![0.0f64; 64];
        out.write(&v);
        inp.read(&mut got);
        let n = count(|| {
            for i in 0..5_000 {
                v.truncate(1 + i % 64);
                v.resize(64 - i % 7, i as f64);
                out.write(&v);
                assert_eq!(inp.read(&mut got), FlowStatus::NewData);
            }
        });
        assert_eq!(n, 0, "{policy:?}");
        assert_eq!(got, v);
    }
}

struct Loop {
    i: InputPort<f64>,
    o: OutputPort<f64>,
    scale: rtt::operation::OperationCaller<(f64,), f64>,
    steps: u64,
    at: Arc<[AtomicU64; 2]>,
}

impl Component for Loop {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut x = 0.0;
        self.i.read(&mut x);
        let y = self.scale.call((x,)).unwrap_or(0.0);
        self.o.write(&y);
        self.steps += 1;
        // Allocations on this thread, sampled at two steps far apart: everything the
        // activity does between them (sleep, statistics, ThreadScope, queue, update)
        // must allocate nothing.
        match self.steps {
            20 => self.at[0].store(allocations(), Ordering::SeqCst),
            220 => self.at[1].store(allocations(), Ordering::SeqCst),
            _ => {}
        }
        Ok(())
    }
}

#[test]
fn client_call_and_periodic_step_allocate_nothing() {
    let registry = Arc::new(Registry::new());
    let card = SimCard::new(&SimConfig::demo(), Arc::new(rtt::time::MonotonicClock)).unwrap();
    card.register(&registry, "sim").unwrap();
    registry.digital_out().alias("ThreadScope", "sim").unwrap();
    let rt = Runtime::new(
        registry,
        RuntimeOptions {
            thread_scope: true,
            ..Default::default()
        },
    )
    .unwrap();
    let helper = rt
        .add(
            "helper",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                iface.client_operation("scale", "doubles", &[("x", "")], |(x,): (f64,)| 2.0 * x)?;
                Ok(Nothing)
            },
        )
        .unwrap();
    let scale = helper.operation::<(f64,), f64>("scale").unwrap();
    scale.call((1.0,)).unwrap();
    assert_eq!(
        count(|| for i in 0..10_000 {
            scale.call((f64::from(i),)).unwrap();
        }),
        0,
        "ClientThread call"
    );

    let at = Arc::new([AtomicU64::new(0), AtomicU64::new(0)]);
    let a = at.clone();
    let t = rt
        .add(
            "loop",
            ActivitySpec::periodic(Duration::from_millis(1)),
            rtt::InitialState::Stopped,
            move |iface| {
                Ok(Loop {
                    i: iface.input("in", "")?,
                    o: iface.output("out", "")?,
                    scale,
                    steps: 0,
                    at: a,
                })
            },
        )
        .unwrap();
    let mut w = t.port("in").unwrap().writer(ConnPolicy::data()).unwrap();
    let mut r = t.port("out").unwrap().reader(ConnPolicy::data()).unwrap();
    t.start().unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while at[1].load(Ordering::SeqCst) == 0 {
        w.write(serde_json::json!(1.5)).unwrap();
        r.read();
        assert!(
            Instant::now() < deadline,
            "periodic activity did not reach 220 steps"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    t.stop().unwrap();
    let (a0, a1) = (at[0].load(Ordering::SeqCst), at[1].load(Ordering::SeqCst));
    assert_eq!(a1 - a0, 0, "200 periodic steps allocated {} times", a1 - a0);
}

struct Nothing;
impl Component for Nothing {}

struct Requirer {
    scale: rtt::service::RequiredOperation<(f64,), f64>,
}
impl Component for Requirer {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if self.scale.ready() {
            self.scale.call((1.0,))?;
        }
        Ok(())
    }
}

#[test]
fn a_required_operations_ready_call_and_the_engines_look_allocate_nothing() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let provider = rt
        .add(
            "provider",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                iface.provides("math").client_operation(
                    "scale",
                    "doubles",
                    &[("x", "")],
                    |(x,): (f64,)| 2.0 * x,
                )?;
                Ok(Nothing)
            },
        )
        .unwrap();
    let mut scale = None;
    let t = rt
        .add(
            "requirer",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                let op = iface.requires("math").operation::<(f64,), f64>("scale")?;
                scale = Some(op.clone());
                Ok(Requirer { scale: op })
            },
        )
        .unwrap();
    let scale = scale.unwrap();
    t.bind_service("math", &provider, "math", false).unwrap();
    provider.start().unwrap();
    t.start().unwrap();
    t.step().unwrap();
    assert_eq!(scale.call((2.0,)), Ok(4.0));
    assert_eq!(
        count(|| for i in 0..10_000 {
            assert!(scale.ready());
            scale.call((f64::from(i),)).unwrap();
        }),
        0,
        "ready() and call() of a required ClientThread operation"
    );
    assert_eq!(
        count(|| for _ in 0..1_000 {
            t.step().unwrap();
        }),
        0,
        "a slave step that looks at a bound requirement and calls it"
    );
}

/// Runs `scale` in its own thread and notes, each call, the allocations its thread made
/// so far.
struct Engine {
    engine_allocations: Arc<AtomicU64>,
}
impl Component for Engine {}

/// A component with OwnThread operation `scale` on `spec`; the allocations its engine
/// thread has made, as of its last call.
fn own_thread_scaler(rt: &Runtime, spec: ActivitySpec) -> (rtt::TaskContext, Arc<AtomicU64>) {
    let seen = Arc::new(AtomicU64::new(0));
    let s = seen.clone();
    let t = rt
        .add("engine", spec, rtt::InitialState::Stopped, move |iface| {
            iface.own_operation(
                "scale",
                "doubles, in the component's thread",
                &[("x", "")],
                |c: &mut Engine, (x,): (f64,)| {
                    c.engine_allocations.store(allocations(), Ordering::SeqCst);
                    2.0 * x
                },
            )?;
            Ok(Engine {
                engine_allocations: s,
            })
        })
        .unwrap();
    t.start().unwrap();
    (t, seen)
}

/// An OwnThread call, on both threads: the caller's `send` (claim a pooled slot, queue it,
/// wake the engine) and `collect` (spin, park, take), the engine's wake-up, step and run.
/// Also a send whose handle is dropped unread, and a result polled for.
#[test]
fn an_own_thread_send_allocates_nothing_on_either_thread() {
    for (spec, calls) in [
        (ActivitySpec::non_periodic(), 10_000u32),
        (ActivitySpec::periodic(Duration::from_micros(500)), 300),
    ] {
        let label = format!("{spec:?}");
        let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
        let (t, engine) = own_thread_scaler(&rt, spec);
        let scale = t.operation::<(f64,), f64>("scale").unwrap();
        // Warm up: the first calls meet the thread's first park and first wake-up.
        for i in 0..50 {
            assert_eq!(scale.call((f64::from(i),)), Ok(2.0 * f64::from(i)));
        }
        let before = engine.load(Ordering::SeqCst);
        let on_caller = count(|| {
            for i in 0..calls {
                let x = f64::from(i);
                assert_eq!(scale.send((x,)).collect(), Ok(2.0 * x), "{label}");
                // Sent and dropped: the slot comes back once the engine has run it.
                drop(scale.send((x,)));
                let mut h = scale.send((x,));
                while h.collect_if_done().is_none() {
                    std::hint::spin_loop();
                }
            }
        });
        // One more call, so the engine notes its count after the dropped ones ran.
        scale.call((0.0,)).unwrap();
        let on_engine = engine.load(Ordering::SeqCst) - before;
        assert_eq!(on_caller, 0, "{label}: the caller's sends allocated");
        assert_eq!(on_engine, 0, "{label}: the engine's thread allocated");
        let counters = t.counters();
        assert_eq!(counters.call_slots_allocated, 0, "{label}");
        assert_eq!(counters.calls_refused, 0, "{label}");
        t.stop().unwrap();
    }
}

/// A log call pushes a fixed-size record; one the level leaves out builds nothing; one
/// that meets a full queue is dropped and counted. None allocates, with an operating
/// system's error among its arguments.
#[test]
fn a_real_time_log_call_allocates_nothing() {
    let area = rtt::log::Area::named("no_alloc_log");
    let refused = std::io::Error::from_raw_os_error(111);
    let other = std::io::Error::other("unit 7 answered exception 2");
    rtt::rt_log!(area, Info, "warm {}", 1u8);
    let n = count(|| {
        for i in 0..2 * rtt::log::QUEUE_CAPACITY {
            rtt::rt_log!(
                area,
                Warn,
                "unit {} failed {} times: {}, {}",
                7u8,
                i,
                rtt::log::Arg::io(&refused),
                rtt::log::Arg::io(&other)
            );
            rtt::rt_log!(area, Debug, "left out by the level {}", i);
        }
    });
    assert_eq!(n, 0);
    assert!(rtt::log::stats().dropped > 0, "the queue never filled");
}
