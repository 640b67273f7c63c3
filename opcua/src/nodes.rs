//! hwgw's node manager: async-opcua's simple in-memory one (values set by the sampler,
//! reads through callbacks, monitored items), with writes and calls of its own:
//!
//! - a write is checked under the address space's lock (a variable not writable at all —
//!   an input, or an output where the deployment allows no writes — BadNotWritable, as
//!   OPC UA says, where the simple manager answers BadUserAccessDenied, kept for a user
//!   whose role may not write a writable one; the type; the user's access), each refusal
//!   counted; then carried out with the lock let go, on tokio's blocking pool: a `set`
//!   waits for the device to take the value (seconds on a slow bus), and meanwhile every
//!   other request and the sampler go on;
//! - a call likewise runs on the blocking pool (an operation run by its component's
//!   thread waits for its next step).
//!
//! The writes of one request are carried out in their order, one after the other.

use crate::calls::Book;
use async_trait::async_trait;
use std::collections::HashMap;
use std::sync::Arc;
use ua::nodes::AccessLevel;
use ua::server::CreateMonitoredItem;
use ua::server::address_space::AddressSpace;
use ua::server::address_space::{NodeType, validate_node_write};
use ua::server::diagnostics::NamespaceMetadata;
use ua::server::node_manager::memory::{
    InMemoryNodeManager, InMemoryNodeManagerBuilder, InMemoryNodeManagerImpl,
    InMemoryNodeManagerImplBuilder, SimpleNodeManagerBuilder, SimpleNodeManagerImpl,
};
use ua::server::node_manager::{
    MethodCall, MonitoredItemRef, MonitoredItemUpdateRef, NodeManagerBuilder, ParsedReadValueId,
    RequestContext, ServerContext, WriteNode,
};
use ua::sync::RwLock;
use ua::types::{
    AttributeId, DataValue, MonitoringMode, NodeId, NumericRange, StatusCode, TimestampsToReturn,
    Variant,
};

/// Carries out a write of a value (and its index range): its outcome.
pub(crate) type Writer = Arc<dyn Fn(&DataValue, &NumericRange) -> StatusCode + Send + Sync>;

/// Carries out a call with its arguments: its outputs, or why not.
pub(crate) type Method = Arc<dyn Fn(&[Variant]) -> Result<Vec<Variant>, StatusCode> + Send + Sync>;

/// The node manager.
pub(crate) type HwgwNodeManager = InMemoryNodeManager<Nodes>;

/// The simple node manager, with writes and calls of its own.
pub(crate) struct Nodes {
    simple: SimpleNodeManagerImpl,
    writers: RwLock<HashMap<NodeId, Writer>>,
    methods: RwLock<HashMap<NodeId, Method>>,
    book: Arc<Book>,
}

impl Nodes {
    /// The simple manager, for its read callbacks.
    pub(crate) fn simple(&self) -> &SimpleNodeManagerImpl {
        &self.simple
    }

    /// Writes of variable `id`'s value are carried out by `w`.
    pub(crate) fn add_writer(&self, id: NodeId, w: Writer) {
        self.writers.write().insert(id, w);
    }

    /// Calls of method `id` are carried out by `m`.
    pub(crate) fn add_method(&self, id: NodeId, m: Method) {
        self.methods.write().insert(id, m);
    }
}

struct Builder(SimpleNodeManagerBuilder, Arc<Book>);

impl InMemoryNodeManagerImplBuilder for Builder {
    type Impl = Nodes;

    fn build(self, context: ServerContext, address_space: &mut AddressSpace) -> Nodes {
        Nodes {
            simple: self.0.build(context, address_space),
            writers: RwLock::default(),
            methods: RwLock::default(),
            book: self.1,
        }
    }
}

/// The builder of hwgw's node manager of namespace `uri`, its refusals counted in `book`.
pub(crate) fn builder(uri: &str, book: Arc<Book>) -> impl NodeManagerBuilder {
    InMemoryNodeManagerBuilder::new(Builder(
        SimpleNodeManagerBuilder::new(
            NamespaceMetadata {
                namespace_uri: uri.into(),
                ..Default::default()
            },
            "hwgw",
        ),
        book,
    ))
}

/// Runs `f` on tokio's blocking pool; BadInternalError when it panicked.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, StatusCode> + Send + 'static,
) -> Result<T, StatusCode> {
    tokio::task::spawn_blocking(f)
        .await
        .unwrap_or(Err(StatusCode::BadInternalError))
}

#[async_trait]
impl InMemoryNodeManagerImpl for Nodes {
    async fn init(&self, address_space: &mut AddressSpace, context: ServerContext) {
        self.simple.init(address_space, context).await
    }

    fn name(&self) -> &str {
        self.simple.name()
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        self.simple.namespaces()
    }

    async fn read_values(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        nodes: &[&ParsedReadValueId],
        max_age: f64,
        timestamps_to_return: TimestampsToReturn,
    ) -> Vec<DataValue> {
        self.simple
            .read_values(context, address_space, nodes, max_age, timestamps_to_return)
            .await
    }

    async fn create_value_monitored_items(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        items: &mut [&mut &mut CreateMonitoredItem],
    ) {
        self.simple
            .create_value_monitored_items(context, address_space, items)
            .await
    }

    async fn set_monitoring_mode(
        &self,
        context: &RequestContext,
        mode: MonitoringMode,
        items: &[&MonitoredItemRef],
    ) {
        self.simple.set_monitoring_mode(context, mode, items).await
    }

    async fn modify_monitored_items(
        &self,
        context: &RequestContext,
        items: &[&MonitoredItemUpdateRef],
    ) {
        self.simple.modify_monitored_items(context, items).await
    }

    async fn delete_monitored_items(&self, context: &RequestContext, items: &[&MonitoredItemRef]) {
        self.simple.delete_monitored_items(context, items).await
    }

    async fn write(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        nodes_to_write: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        let mut jobs = Vec::new();
        {
            let sp = address_space.read();
            let type_tree = context.type_tree.read();
            let writers = self.writers.read();
            for (i, w) in nodes_to_write.iter_mut().enumerate() {
                let v = w.value();
                let checked = match sp.find(&v.node_id) {
                    None => Err(StatusCode::BadNodeIdUnknown),
                    Some(NodeType::Variable(var))
                        if v.attribute_id == AttributeId::Value
                            && !var.access_level().contains(AccessLevel::CURRENT_WRITE) =>
                    {
                        Err(StatusCode::BadNotWritable)
                    }
                    Some(node) => validate_node_write(node, context, v, &*type_tree),
                };
                let writer = checked.and_then(|()| match v.attribute_id {
                    AttributeId::Value => writers
                        .get(&v.node_id)
                        .cloned()
                        .ok_or(StatusCode::BadNotWritable),
                    _ => Err(StatusCode::BadNotWritable),
                });
                match writer {
                    Ok(f) => jobs.push((i, f, v.value.clone(), v.index_range.clone())),
                    Err(code) => {
                        let what = format!("write of {}", v.node_id);
                        w.set_status(self.book.refuse(false, code, what));
                    }
                }
            }
        }
        for (i, f, value, range) in jobs {
            let code = blocking(move || Ok(f(&value, &range)))
                .await
                .unwrap_or_else(|e| e);
            nodes_to_write[i].set_status(code);
        }
        Ok(())
    }

    async fn call(
        &self,
        _context: &RequestContext,
        _address_space: &RwLock<AddressSpace>,
        methods_to_call: &mut [&mut &mut MethodCall],
    ) -> Result<(), StatusCode> {
        for m in methods_to_call.iter_mut() {
            let method = self.methods.read().get(m.method_id()).cloned();
            let Some(f) = method else {
                m.set_status(StatusCode::BadMethodInvalid);
                continue;
            };
            let args = m.arguments().to_vec();
            match blocking(move || f(&args)).await {
                Ok(outputs) => {
                    m.set_outputs(outputs);
                    m.set_status(StatusCode::Good);
                }
                Err(code) => m.set_status(code),
            }
        }
        Ok(())
    }
}
