//! Required services bound by the deployment, as `hwgw check` and `hwgw run` build it
//! (`Gateway::from_text`): automatically where one component provides the service, by
//! name where several do, refused with file:line:col and key when the types differ or the
//! provider is missing; a service's port connected by its dotted name.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::deploy::Gateway;
use hwgw::types::Types;
use rtt::port::OutputPort;
use rtt::service::RequiredOperation;
use rtt::{Component, Context, HookResult, InitialState, InterfaceBuilder};

struct Camera {
    exposure: OutputPort<f64>,
    _model: rtt::property::Property<String>,
}
impl Component for Camera {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.exposure.write(&0.25);
        Ok(())
    }
}

fn camera(iface: &mut InterfaceBuilder<Camera>) -> Result<Camera, rtt::component::IntrospectError> {
    let model = iface
        .properties()
        .add("model", String::new(), "which camera")?;
    let mut svc = iface.provides("camera");
    svc.client_operation(
        "set_resolution",
        "",
        &[("width", ""), ("height", "")],
        |(w, h): (u32, u32)| w > 0 && h > 0,
    )?;
    Ok(Camera {
        exposure: svc.output("exposure", "seconds")?,
        _model: model,
    })
}

/// A camera of another make: its set_resolution takes one argument.
fn old_camera(
    iface: &mut InterfaceBuilder<Camera>,
) -> Result<Camera, rtt::component::IntrospectError> {
    let mut svc = iface.provides("camera");
    svc.client_operation("set_resolution", "", &[("width", "")], |(w,): (u32,)| w > 0)?;
    let exposure = svc.output("exposure", "seconds")?;
    Ok(Camera {
        exposure,
        _model: iface
            .properties()
            .add("model", String::new(), "which camera")?,
    })
}

struct Vision {
    _set_resolution: RequiredOperation<(u32, u32), bool>,
}
impl Component for Vision {}

fn types() -> Types {
    let mut t = Types::builtin();
    t.components.register("camera", |rt, name, spec| {
        rt.add(name, spec, InitialState::Stopped, camera)
    });
    t.components.register("old_camera", |rt, name, spec| {
        rt.add(name, spec, InitialState::Stopped, old_camera)
    });
    t.components.register("vision", |rt, name, spec| {
        rt.add(name, spec, InitialState::PreOperational, |iface| {
            Ok(Vision {
                _set_resolution: iface
                    .requires("camera")
                    .operation::<(u32, u32), bool>("set_resolution")?,
            })
        })
    });
    t
}

fn component(name: &str, kind: &str, extra: &str) -> String {
    format!(
        "[[component]]\nname = \"{name}\"\ntype = \"{kind}\"\nactivity = {{ type = \"periodic\", period_ms = 10 }}\n{extra}\n"
    )
}

fn build(text: &str) -> Result<Gateway, String> {
    Gateway::from_text(text, "services.toml", &types()).map(|(gw, _)| gw)
}

fn refused(text: &str) -> String {
    match build(text) {
        Ok(_) => panic!("built:\n{text}"),
        Err(e) => e,
    }
}

fn bound_to(gw: &Gateway, name: &str) -> Vec<String> {
    gw.runtime().component(name).unwrap().required()[0]
        .bound_to
        .clone()
}

#[test]
fn the_one_provider_is_bound_automatically() {
    let text = component("cam0", "camera", "") + &component("vision", "vision", "");
    let gw = build(&text).unwrap();
    assert_eq!(bound_to(&gw, "vision"), ["cam0.camera"]);
    assert!(gw.summary().contains("requires camera -> cam0.camera"));
}

#[test]
fn several_providers_need_a_name_and_the_named_one_is_bound() {
    let two = component("cam0", "camera", "") + &component("cam1", "camera", "");
    let e = refused(&(two.clone() + &component("vision", "vision", "")));
    assert!(
        e.contains("services.toml:11:1: component[2]: \"vision\" requires service \"camera\", which cam0, cam1 provide; say which with requires = { camera = \"cam0.camera\" }"),
        "{e}"
    );
    let gw = build(
        &(two
            + &component(
                "vision",
                "vision",
                "requires = { camera = \"cam1.camera\" }",
            )),
    )
    .unwrap();
    assert_eq!(bound_to(&gw, "vision"), ["cam1.camera"]);
}

#[test]
fn a_binding_of_the_wrong_type_is_refused_where_it_is_written() {
    let text = component("cam0", "old_camera", "")
        + &component(
            "vision",
            "vision",
            "requires = { camera = \"cam0.camera\" }",
        );
    let e = refused(&text);
    assert!(
        e.contains("services.toml:10:23: component[1].requires.camera: cam0.camera.set_resolution is (u32) -> bool, but \"vision\" requires (u32, u32) -> bool"),
        "{e}"
    );
    let text = component("cam0", "camera", "")
        + &component(
            "vision",
            "vision",
            "requires = { camera = \"cam9.camera\", lens = \"x\" }",
        );
    let e = refused(&text);
    assert!(
        e.contains("component[1].requires.camera: no component provides \"cam9.camera\"; provided here: cam0.camera"),
        "{e}"
    );
    assert!(
        e.contains("component[1].requires.lens: \"vision\" (type \"vision\") requires no \"lens\"; it requires: camera"),
        "{e}"
    );
    let e = refused(&component("vision", "vision", ""));
    assert!(e.contains("which no component provides"), "{e}");
}

#[test]
fn a_services_port_connects_by_its_dotted_name() {
    let text = component("cam0", "camera", "")
        + &component("f", "follow", "")
        + "[[connection]]\nfrom = \"cam0.camera.exposure\"\nto = \"f.in\"\n";
    let gw = build(&text).unwrap();
    let f = gw.runtime().component("f").unwrap();
    assert_eq!(f.port("in").unwrap().connections().len(), 1);
    gw.start().unwrap();
    testkit::wait_until("the exposure followed", || {
        f.port("out").unwrap().last_value().ok().flatten() == Some(serde_json::json!(0.25))
    });
    gw.shutdown();
}

#[test]
fn a_reload_that_rebuilds_the_provider_binds_what_requires_it_to_the_new_one() {
    // cam0's service port feeds f; a reload rebuilds cam0 alone.
    let rest = component("vision", "vision", "")
        + &component("f", "follow", "")
        + "[[connection]]\nfrom = \"cam0.camera.exposure\"\nto = \"f.in\"\n";
    let text = component("cam0", "camera", "") + &rest;
    let gw = build(&text).unwrap();
    gw.start().unwrap();
    let vision = gw.runtime().component("vision").unwrap();
    testkit::wait_until("the binding ready", || vision.required()[0].ready);
    let changed = component("cam0", "camera", "properties = { model = \"b\" }") + &rest;
    let report = gw.reload_text(&changed, "services.toml");
    assert!(report.errors.is_empty(), "{report:?}");
    // The requirer was not rebuilt; its binding follows the new provider.
    let same = gw.runtime().component("vision").unwrap();
    assert_eq!(same.required()[0].bound_to, ["cam0.camera"]);
    testkit::wait_until("the binding ready again", || same.required()[0].ready);
    let cam0 = gw.runtime().component("cam0").unwrap();
    assert_eq!(
        cam0.properties().get_value("model").unwrap(),
        serde_json::json!("b")
    );
    // The service port's connection was made again, from the new cam0.
    let f = gw.runtime().component("f").unwrap();
    assert_eq!(f.port("in").unwrap().connections().len(), 1);
    assert_eq!(cam0.port("camera.exposure").unwrap().connections().len(), 1);
    // A loss seen during the reload is told once, and its return once: the return at
    // the requirer's next step after the binding is ready again, so it is waited for.
    testkit::wait_until("the return told", || {
        let info = &same.required()[0];
        info.lost == info.back
    });
    let info = &same.required()[0];
    assert!(info.lost <= 1, "{info:?}");
    cam0.stop().unwrap();
    assert!(
        !same.required()[0].ready,
        "bound to the new provider, not the old one"
    );
    gw.shutdown();
}
