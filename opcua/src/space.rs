//! The address space hwgw serves, in its own namespace under `Objects/hwgw`:
//!
//! - `<card>/<device>/<channel>`: a variable per channel (node id `component.port`, as
//!   `hwgw get` names it) of the channel's type; an analog one an AnalogItemType with its
//!   `EURange` and `EngineeringUnits`; an output writable where the deployment allows;
//!   each device's `Error` (its last error, empty when none);
//! - `Components/<component>`: every component, its ports as variables (a channel's port
//!   is the channel's variable; another port is read when it is read, node id
//!   `port:component.port`) and its operations as methods with typed arguments (node id
//!   `call:component.operation`);
//! - `Diagnostics`: the server's counters and the gateway's `hwgw status` as JSON.

use crate::calls::{self, Book, ChannelWrite};
use crate::nodes::HwgwNodeManager;
use crate::plan::{Device, Plan};
use crate::values::{self, channel_id, error_id};
use driver_api::ControlLink;
use driver_api::channels::{Kind, Source};
use std::sync::Arc;
use ua::nodes::{AccessLevel, MethodBuilder, ObjectBuilder, VariableBuilder};
use ua::server::address_space::AddressSpace;
use ua::types::{
    Argument, DataTypeId, DataValue, EUInformation, ExtensionObject, LocalizedText, NodeId,
    ObjectId, ObjectTypeId, QualifiedName, Range, ReferenceTypeId, StatusCode, UAString,
    VariableTypeId, Variant,
};

/// What building the address space needs.
pub(crate) struct Build<'a> {
    pub nm: &'a HwgwNodeManager,
    pub ns: u16,
    pub plan: &'a Plan,
    pub allow_writes: bool,
    pub allow_calls: bool,
    pub sample_ms: f64,
    pub registry: Arc<device_interface::Registry>,
    pub control: ControlLink,
    pub book: Arc<Book>,
    /// The server's counters, by name, for `Diagnostics`.
    pub counters: Arc<dyn Fn() -> Vec<(String, u64)> + Send + Sync>,
}

fn name(ns: u16, text: &str) -> QualifiedName {
    QualifiedName::new(ns, text)
}

impl Build<'_> {
    /// Adds every node and its callbacks.
    pub(crate) fn run(&self) {
        let ns = self.ns;
        let root = NodeId::new(ns, "hwgw");
        {
            let mut sp = self.nm.address_space().write();
            ObjectBuilder::new(&root, name(ns, "hwgw"), "hwgw")
                .description("The IO of this hwgw gateway")
                .organized_by(ObjectId::ObjectsFolder)
                .has_type_definition(ObjectTypeId::FolderType)
                .insert(&mut *sp);
            let mut cards: Vec<&str> = Vec::new();
            for d in &self.plan.devices {
                let card = NodeId::new(ns, format!("card:{}", d.card));
                if !cards.contains(&d.card.as_str()) {
                    cards.push(&d.card);
                    ObjectBuilder::new(&card, name(ns, &d.card), d.card.as_str())
                        .description(format!("Card {}", d.card))
                        .organized_by(&root)
                        .has_type_definition(ObjectTypeId::FolderType)
                        .insert(&mut *sp);
                }
                self.device(&mut sp, &card, d);
            }
        }
        self.components(&root);
        self.diagnostics(&root);
    }

    fn device(&self, sp: &mut AddressSpace, card: &NodeId, d: &Device) {
        let ns = self.ns;
        let id = NodeId::new(ns, d.component.clone());
        ObjectBuilder::new(&id, name(ns, &d.label), d.label.as_str())
            .description(format!("{} ({})", d.component, d.interface))
            .organized_by(card)
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .insert(sp);
        VariableBuilder::new(&error_id(ns, &d.component), name(ns, "Error"), "Error")
            .description("The device's last error; empty when it has none")
            .data_type(DataTypeId::String)
            .value("")
            .access_level(AccessLevel::CURRENT_READ)
            .user_access_level(AccessLevel::CURRENT_READ)
            .component_of(&id)
            .has_type_definition(VariableTypeId::BaseDataVariableType)
            .insert(sp);
        for c in &d.channels {
            let vid = channel_id(ns, &c.component, &c.port);
            let output = c.source.kind() != Kind::Input;
            let writable = output && self.allow_writes;
            let level = if writable {
                AccessLevel::CURRENT_READ | AccessLevel::CURRENT_WRITE
            } else {
                AccessLevel::CURRENT_READ
            };
            let analog = matches!(c.source, Source::Ai(..) | Source::Ao(..));
            let type_def = if analog {
                VariableTypeId::AnalogItemType
            } else {
                VariableTypeId::BaseDataVariableType
            };
            VariableBuilder::new(&vid, name(ns, &c.port), c.port.as_str())
                .description(c.address())
                .data_type(values::data_type(&c.source))
                .value(Variant::Empty)
                .access_level(level)
                .user_access_level(level)
                .minimum_sampling_interval(self.sample_ms)
                .component_of(&id)
                .has_type_definition(type_def)
                .insert(sp);
            if let Some(r) = c.range.filter(|_| analog) {
                self.range_properties(sp, &vid, r);
            }
            if writable {
                let w = ChannelWrite {
                    channel: c.clone(),
                    task: d.task.clone(),
                    device: (d.interface, d.name.clone()),
                    registry: self.registry.clone(),
                    control: self.control.clone(),
                    book: self.book.clone(),
                };
                self.nm
                    .inner()
                    .add_writer(vid, Arc::new(move |v, range| w.write(v, range)));
            }
        }
    }

    /// `EURange` and `EngineeringUnits` of an analog variable.
    fn range_properties(
        &self,
        sp: &mut AddressSpace,
        var: &NodeId,
        r: device_interface::AnalogRange,
    ) {
        let range = Range {
            low: r.lowest,
            high: r.highest,
        };
        let unit = EUInformation {
            namespace_uri: UAString::from("http://www.opcfoundation.org/UA/units/un/cefact"),
            unit_id: -1,
            display_name: LocalizedText::new("", r.unit.as_str()),
            description: LocalizedText::new("", r.unit.as_str()),
        };
        let props: [(&str, DataTypeId, Variant); 2] = [
            (
                "EURange",
                DataTypeId::Range,
                Variant::from(ExtensionObject::from_message(range)),
            ),
            (
                "EngineeringUnits",
                DataTypeId::EUInformation,
                Variant::from(ExtensionObject::from_message(unit)),
            ),
        ];
        for (prop, dt, value) in props {
            let pid = NodeId::new(self.ns, format!("{}/{prop}", var.identifier));
            VariableBuilder::new(&pid, QualifiedName::new(0, prop), prop)
                .data_type(dt)
                .value(value)
                .access_level(AccessLevel::CURRENT_READ)
                .user_access_level(AccessLevel::CURRENT_READ)
                .property_of(var)
                .has_type_definition(VariableTypeId::PropertyType)
                .insert(sp);
        }
    }

    fn components(&self, root: &NodeId) {
        let ns = self.ns;
        let folder = NodeId::new(ns, "Components");
        let mut sp = self.nm.address_space().write();
        ObjectBuilder::new(&folder, name(ns, "Components"), "Components")
            .description("The components of the deployment: ports and operations")
            .organized_by(root)
            .has_type_definition(ObjectTypeId::FolderType)
            .insert(&mut *sp);
        for t in &self.plan.components {
            let cname = t.name().to_string();
            let id = NodeId::new(ns, format!("component:{cname}"));
            ObjectBuilder::new(&id, name(ns, &cname), cname.as_str())
                .organized_by(&folder)
                .has_type_definition(ObjectTypeId::BaseObjectType)
                .insert(&mut *sp);
            for p in t.ports() {
                if self.plan.is_channel(&cname, &p.name) {
                    sp.insert_reference(
                        &id,
                        &channel_id(ns, &cname, &p.name),
                        ReferenceTypeId::Organizes,
                    );
                    continue;
                }
                self.port(&mut sp, &id, t, &p);
            }
            // An output's IO component's operations write it past a write's checks: they
            // are methods only where writes are allowed too.
            if !self.plan.drives_outputs.contains(&cname) || self.allow_writes {
                for op in t.operations() {
                    self.method(&mut sp, &id, t, op);
                }
            }
        }
    }

    fn port(
        &self,
        sp: &mut AddressSpace,
        parent: &NodeId,
        t: &rtt::TaskContext,
        p: &rtt::info::PortInfo,
    ) {
        let cname = t.name().to_string();
        let pid = NodeId::new(self.ns, format!("port:{cname}.{}", p.name));
        let writable = self.allow_writes && p.direction == rtt::info::Direction::Input;
        let level = if writable {
            AccessLevel::CURRENT_READ | AccessLevel::CURRENT_WRITE
        } else {
            AccessLevel::CURRENT_READ
        };
        VariableBuilder::new(&pid, name(self.ns, &p.name), p.name.as_str())
            .description(format!("{} ({}, {})", p.doc, p.direction, p.type_name))
            .data_type(calls::data_type(&p.type_name))
            .value(Variant::Empty)
            .access_level(level)
            .user_access_level(level)
            .component_of(parent)
            .has_type_definition(VariableTypeId::BaseDataVariableType)
            .insert(sp);
        let (task, port, ty) = (t.clone(), p.name.clone(), p.type_name.clone());
        self.nm
            .inner()
            .simple()
            .add_read_callback(pid.clone(), move |_, _, _| {
                let v = task
                    .port(&port)
                    .map_err(|_| StatusCode::BadNodeIdUnknown)?
                    .last_value()
                    .map_err(|_| StatusCode::BadNoData)?;
                Ok(match v {
                    Some(v) => DataValue::new_now(calls::to_variant(&v, &ty)),
                    None => DataValue::new_now_status(
                        Variant::Empty,
                        StatusCode::BadWaitingForInitialData,
                    ),
                })
            });
        if writable {
            let (control, book, task) = (self.control.clone(), self.book.clone(), t.clone());
            let (port, ty) = (p.name.clone(), p.type_name.clone());
            self.nm.inner().add_writer(
                pid,
                Arc::new(move |v, range| {
                    if !matches!(range, ua::types::NumericRange::None) {
                        return StatusCode::BadIndexRangeInvalid;
                    }
                    calls::port_write(&control, &book, (&task, &port, &ty), v)
                }),
            );
        }
    }

    fn method(
        &self,
        sp: &mut AddressSpace,
        parent: &NodeId,
        t: &rtt::TaskContext,
        op: rtt::operation::OperationInfo,
    ) {
        let ns = self.ns;
        let key = format!("{}.{}", t.name(), op.name);
        let mid = NodeId::new(ns, format!("call:{key}"));
        let arg = |n: &str, ty: &str, doc: &str| Argument {
            name: UAString::from(n),
            data_type: calls::data_type(ty).into(),
            value_rank: -1,
            array_dimensions: None,
            description: LocalizedText::new(
                "",
                &if doc.is_empty() {
                    ty.to_string()
                } else {
                    format!("{doc} ({ty})")
                },
            ),
        };
        let inputs: Vec<Argument> = op
            .args
            .iter()
            .map(|a| arg(&a.name, &a.type_name, &a.doc))
            .collect();
        let outputs: Vec<Argument> = if op.result.is_empty() {
            Vec::new()
        } else {
            vec![arg("result", &op.result, "the result")]
        };
        MethodBuilder::new(&mid, name(ns, &op.name), op.name.as_str())
            .description(op.doc.as_str())
            .component_of(parent)
            .executable(self.allow_calls)
            .user_executable(self.allow_calls)
            .input_args(sp, &NodeId::new(ns, format!("call:{key}/in")), &inputs)
            .output_args(sp, &NodeId::new(ns, format!("call:{key}/out")), &outputs)
            .insert(sp);
        if self.allow_calls {
            let (task, book) = (t.clone(), self.book.clone());
            self.nm.inner().add_method(
                mid,
                Arc::new(move |args| calls::call(&task, &book, &op, args)),
            );
        }
    }

    fn diagnostics(&self, root: &NodeId) {
        let ns = self.ns;
        let id = NodeId::new(ns, "Diagnostics");
        let mut sp = self.nm.address_space().write();
        ObjectBuilder::new(&id, name(ns, "Diagnostics"), "Diagnostics")
            .description("This server's counters, and the gateway's status")
            .organized_by(root)
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .insert(&mut *sp);
        let variable = |sp: &mut AddressSpace, key: &str, dt: DataTypeId, doc: &str| {
            let vid = NodeId::new(ns, format!("diagnostics:{key}"));
            VariableBuilder::new(&vid, name(ns, key), key)
                .description(doc)
                .data_type(dt)
                .value(Variant::Empty)
                .access_level(AccessLevel::CURRENT_READ)
                .user_access_level(AccessLevel::CURRENT_READ)
                .component_of(&id)
                .has_type_definition(VariableTypeId::BaseDataVariableType)
                .insert(sp);
            vid
        };
        let control = self.control.clone();
        let status = variable(
            &mut sp,
            "Status",
            DataTypeId::String,
            "The gateway's status as `hwgw status` gives it, JSON",
        );
        self.nm
            .inner()
            .simple()
            .add_read_callback(status, move |_, _, _| {
                let s = control
                    .request(serde_json::json!({"cmd": "status"}))
                    .map_err(|_| StatusCode::BadResourceUnavailable)?;
                Ok(DataValue::new_now(Variant::from(s.to_string().as_str())))
            });
        for (key, _) in (self.counters)() {
            let vid = variable(
                &mut sp,
                &key,
                DataTypeId::UInt64,
                "A counter of this server",
            );
            let counters = self.counters.clone();
            self.nm
                .inner()
                .simple()
                .add_read_callback(vid, move |_, _, _| {
                    let v = counters()
                        .into_iter()
                        .find(|(k, _)| *k == key)
                        .map_or(0, |(_, v)| v);
                    Ok(DataValue::new_now(Variant::UInt64(v)))
                });
        }
    }
}
