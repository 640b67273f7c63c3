//! Services provided and required: a camera component provides `camera`, a vision
//! component requires it; bound, typed, checked; the provider stopped and started again is
//! seen by the requirer as `service_lost` / `service_back`, counted; required devices with
//! multiplicity on a simulated card going offline and back.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::{DigitalOut, Registry};
use driver_sim::{SimCard, SimConfig, SimFault};
use rtt::component::LifecycleError;
use rtt::service::{
    BindError, Multiplicity, OperationAt, RequiredDevices, RequiredKind, RequiredOperation,
};
use rtt::{
    ActivitySpec, Component, Context, HookResult, InitialState, Runtime, RuntimeOptions,
    TaskContext,
};
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

struct Camera {
    width: Arc<AtomicU32>,
}
impl Component for Camera {}

fn camera(rt: &Runtime, name: &str) -> (TaskContext, Arc<AtomicU32>) {
    let width = Arc::new(AtomicU32::new(0));
    let w = width.clone();
    let task = rt
        .add(
            name,
            ActivitySpec::Slave,
            InitialState::Stopped,
            move |iface| {
                let mut svc = iface.provides("camera");
                svc.own_operation(
                    "set_resolution",
                    "sets the resolution",
                    &[("width", ""), ("height", "")],
                    |c: &mut Camera, (w, _h): (u32, u32)| {
                        c.width.store(w, Ordering::SeqCst);
                        w > 0
                    },
                )?
                .client_operation("name", "the camera's model", &[], |()| "cam".to_string())?;
                let _frames = svc.output::<u64>("frames", "frames taken")?;
                Ok(Camera { width: w })
            },
        )
        .unwrap();
    (task, width)
}

#[derive(Default)]
struct Seen {
    lost: AtomicU64,
    back: AtomicU64,
    calls_ok: AtomicU64,
    not_ready: AtomicU64,
}

struct Vision {
    set_resolution: RequiredOperation<(u32, u32), bool>,
    seen: Arc<Seen>,
}

impl Component for Vision {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if self.set_resolution.ready() {
            if let Ok(true) = self.set_resolution.call((640, 480)) {
                self.seen.calls_ok.fetch_add(1, Ordering::SeqCst);
            }
        } else if self.set_resolution.call((640, 480)).is_err() {
            self.seen.not_ready.fetch_add(1, Ordering::SeqCst);
        }
        Ok(())
    }
    fn service_lost(&mut self, _: &mut Context<'_>, service: &str) {
        assert_eq!(service, "camera");
        self.seen.lost.fetch_add(1, Ordering::SeqCst);
    }
    fn service_back(&mut self, _: &mut Context<'_>, service: &str) {
        assert_eq!(service, "camera");
        self.seen.back.fetch_add(1, Ordering::SeqCst);
    }
}

fn vision(rt: &Runtime) -> (TaskContext, Arc<Seen>) {
    let seen = Arc::new(Seen::default());
    let s = seen.clone();
    let task = rt
        .add(
            "vision",
            ActivitySpec::Slave,
            InitialState::PreOperational,
            move |iface| {
                let set_resolution = iface
                    .requires("camera")
                    .operation::<(u32, u32), bool>("set_resolution")?;
                Ok(Vision {
                    set_resolution,
                    seen: s,
                })
            },
        )
        .unwrap();
    (task, seen)
}

fn runtime() -> Runtime {
    Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap()
}

#[test]
fn provided_members_are_named_under_the_service() {
    let rt = runtime();
    let (cam, _) = camera(&rt, "cam0");
    let provided = cam.provided();
    assert_eq!(provided.len(), 1);
    assert_eq!(provided[0].name, "camera");
    assert_eq!(provided[0].operations, ["set_resolution", "name"]);
    assert_eq!(provided[0].ports, ["frames"]);
    assert!(cam.port("camera.frames").is_ok());
    cam.start().unwrap();
    // Called by its full name, as the control socket does.
    assert_eq!(
        cam.call_value("camera.name", vec![]).unwrap(),
        serde_json::json!("cam")
    );
}

#[test]
fn an_unbound_requirement_refuses_configure_and_names_it() {
    let rt = runtime();
    let (vision, _) = vision(&rt);
    let e = vision.configure().unwrap_err();
    assert!(matches!(&e, LifecycleError::Unbound { requirement, .. } if requirement == "camera"));
    assert!(e.to_string().contains("\"camera\""), "{e}");
    let info = vision.required();
    assert_eq!(info[0].name, "camera");
    assert_eq!(
        info[0].kind,
        RequiredKind::Service {
            operations: vec!["set_resolution(u32, u32) -> bool".into()]
        }
    );
    assert!(info[0].bound_to.is_empty() && !info[0].ready && !info[0].optional);
}

#[test]
fn a_binding_of_the_wrong_type_or_to_nothing_is_refused_whole() {
    let rt = runtime();
    let (vision, _) = vision(&rt);
    // A provider whose set_resolution takes one argument.
    let other = rt
        .add(
            "cam1",
            ActivitySpec::Slave,
            InitialState::Stopped,
            |iface| {
                iface.provides("camera").client_operation(
                    "set_resolution",
                    "",
                    &[("width", "")],
                    |(w,): (u32,)| w > 0,
                )?;
                Ok(Camera {
                    width: Arc::default(),
                })
            },
        )
        .unwrap();
    let e = vision
        .bind_service("camera", &other, "camera", false)
        .unwrap_err();
    assert_eq!(
        e,
        BindError::WrongType {
            at: Box::new(OperationAt {
                component: "vision".into(),
                provider: "cam1".into(),
                service: "camera".into(),
                operation: "set_resolution".into(),
            }),
            provided: "(u32) -> bool".into(),
            required: "(u32, u32) -> bool".into(),
        }
    );
    let e = vision
        .bind_service("camera", &other, "lens", false)
        .unwrap_err();
    assert!(e.to_string().contains("provides: camera"), "{e}");
    let e = vision
        .bind_service("lens", &other, "camera", false)
        .unwrap_err();
    assert!(e.to_string().contains("requires: camera"), "{e}");
    // Nothing was bound by the refusals.
    assert!(vision.required()[0].bound_to.is_empty());
    assert!(vision.configure().is_err());
}

#[test]
fn loss_and_return_of_the_provider_are_told_and_counted() {
    let rt = runtime();
    let (cam, width) = camera(&rt, "cam0");
    let (vision, seen) = vision(&rt);
    vision.bind_service("camera", &cam, "camera", true).unwrap();
    assert!(
        vision.required()[0].bound_to.is_empty(),
        "a check binds nothing"
    );
    vision
        .bind_service("camera", &cam, "camera", false)
        .unwrap();
    vision.configure().unwrap();
    cam.start().unwrap();
    vision.start().unwrap();

    // The camera's OwnThread operation runs when the camera steps: step it from a thread
    // while vision calls.
    let stepper = {
        let cam = cam.clone();
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let s = stop.clone();
        (
            std::thread::spawn(move || {
                while !s.load(Ordering::SeqCst) {
                    let _ = cam.step();
                    std::thread::yield_now();
                }
            }),
            stop,
        )
    };
    vision.step().unwrap();
    assert_eq!(seen.calls_ok.load(Ordering::SeqCst), 1);
    assert_eq!(width.load(Ordering::SeqCst), 640);
    assert_eq!(seen.lost.load(Ordering::SeqCst), 0);

    cam.stop().unwrap();
    vision.step().unwrap();
    vision.step().unwrap();
    assert_eq!(seen.lost.load(Ordering::SeqCst), 1, "told once");
    assert_eq!(seen.not_ready.load(Ordering::SeqCst), 2);
    let info = &vision.required()[0];
    assert!(!info.ready);
    assert_eq!((info.lost, info.back), (1, 0));
    assert_eq!(info.bound_to, ["cam0.camera"]);

    cam.start().unwrap();
    vision.step().unwrap();
    assert_eq!(seen.back.load(Ordering::SeqCst), 1);
    assert_eq!(seen.calls_ok.load(Ordering::SeqCst), 2);
    let info = &vision.required()[0];
    assert!(info.ready);
    assert_eq!((info.lost, info.back), (1, 1));
    stepper.1.store(true, Ordering::SeqCst);
    stepper.0.join().unwrap();
}

#[test]
fn an_optional_service_lets_the_component_run_unbound() {
    let rt = runtime();
    let task = rt
        .add(
            "v",
            ActivitySpec::Slave,
            InitialState::PreOperational,
            |iface| {
                let _op = iface
                    .requires("camera")
                    .optional()
                    .operation::<(u32, u32), bool>("set_resolution")?;
                Ok(Camera {
                    width: Arc::default(),
                })
            },
        )
        .unwrap();
    task.configure().unwrap();
    task.start().unwrap();
    task.step().unwrap();
    assert_eq!(task.required()[0].lost, 0, "never bound, never lost");
}

struct Valves {
    valves: RequiredDevices<dyn DigitalOut>,
    lost: Arc<AtomicU64>,
    back: Arc<AtomicU64>,
}
impl Component for Valves {
    fn service_lost(&mut self, _: &mut Context<'_>, service: &str) {
        assert_eq!(service, "valves");
        assert!(!self.valves.ready());
        self.lost.fetch_add(1, Ordering::SeqCst);
    }
    fn service_back(&mut self, _: &mut Context<'_>, _: &str) {
        self.back.fetch_add(1, Ordering::SeqCst);
    }
}

#[test]
fn required_devices_bind_by_name_with_their_multiplicity_and_follow_health() {
    let registry = Arc::new(Registry::new());
    let mut config = SimConfig::demo();
    config.digital_outputs = 4;
    let card = SimCard::new(&config, Arc::new(rtt::time::MonotonicClock)).unwrap();
    card.register(&registry, "sim").unwrap();
    registry.digital_out().alias("press", "sim").unwrap();
    let rt = Runtime::new(registry, RuntimeOptions::default()).unwrap();
    let (lost, back) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let (l, b) = (lost.clone(), back.clone());
    let task = rt
        .add(
            "v",
            ActivitySpec::Slave,
            InitialState::PreOperational,
            move |iface| {
                Ok(Valves {
                    valves: iface.requires_devices::<dyn DigitalOut>(
                        "valves",
                        "1..2".parse::<Multiplicity>().unwrap(),
                    )?,
                    lost: l,
                    back: b,
                })
            },
        )
        .unwrap();
    assert!(task.configure().is_err(), "one at least");
    let names = |n: &[&str]| n.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let e = task
        .bind_devices("valves", &names(&["sim", "press", "other"]), false)
        .unwrap_err();
    assert!(e.to_string().contains("1..2 DigitalOut devices"), "{e}");
    let e = task
        .bind_devices("valves", &names(&["sim", "sim"]), false)
        .unwrap_err();
    assert!(e.to_string().contains("named twice"), "{e}");
    let e = task
        .bind_devices("valves", &names(&["nothing"]), false)
        .unwrap_err();
    assert!(matches!(e, BindError::Device { .. }), "{e}");
    task.bind_devices("valves", &names(&["sim", "press"]), false)
        .unwrap();
    let handle = task.required();
    assert_eq!(handle[0].bound_to, ["sim", "press"]);
    task.configure().unwrap();
    task.start().unwrap();
    task.step().unwrap();
    assert!(task.required()[0].ready);
    card.set_fault(SimFault::Offline);
    task.step().unwrap();
    assert_eq!(lost.load(Ordering::SeqCst), 1);
    card.set_fault(SimFault::None);
    task.step().unwrap();
    assert_eq!(back.load(Ordering::SeqCst), 1);
    assert_eq!(task.required()[0].bound_to, ["sim", "press"]);
}
