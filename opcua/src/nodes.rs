//! hwgw's node manager: async-opcua's simple in-memory one (values set by the sampler,
//! writes, reads and calls through callbacks), with one change: a write to a variable
//! that is not writable at all (an input, or an output where the deployment allows no
//! writes) is refused BadNotWritable, as OPC UA says, where the simple manager answers
//! BadUserAccessDenied — kept for a user whose role may not write a writable one.

use async_trait::async_trait;
use ua::nodes::AccessLevel;
use ua::server::CreateMonitoredItem;
use ua::server::address_space::AddressSpace;
use ua::server::address_space::NodeType;
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
use ua::types::{AttributeId, DataValue, MonitoringMode, StatusCode, TimestampsToReturn};

/// The node manager.
pub(crate) type HwgwNodeManager = InMemoryNodeManager<Nodes>;

/// The simple node manager, with writes checked first.
pub(crate) struct Nodes(SimpleNodeManagerImpl);

impl Nodes {
    /// The simple manager, for its callbacks.
    pub(crate) fn simple(&self) -> &SimpleNodeManagerImpl {
        &self.0
    }
}

struct Builder(SimpleNodeManagerBuilder);

impl InMemoryNodeManagerImplBuilder for Builder {
    type Impl = Nodes;

    fn build(self, context: ServerContext, address_space: &mut AddressSpace) -> Nodes {
        Nodes(self.0.build(context, address_space))
    }
}

/// The builder of hwgw's node manager of namespace `uri`.
pub(crate) fn builder(uri: &str) -> impl NodeManagerBuilder {
    InMemoryNodeManagerBuilder::new(Builder(SimpleNodeManagerBuilder::new(
        NamespaceMetadata {
            namespace_uri: uri.into(),
            ..Default::default()
        },
        "hwgw",
    )))
}

#[async_trait]
impl InMemoryNodeManagerImpl for Nodes {
    async fn init(&self, address_space: &mut AddressSpace, context: ServerContext) {
        self.0.init(address_space, context).await
    }

    fn name(&self) -> &str {
        self.0.name()
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        self.0.namespaces()
    }

    async fn read_values(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        nodes: &[&ParsedReadValueId],
        max_age: f64,
        timestamps_to_return: TimestampsToReturn,
    ) -> Vec<DataValue> {
        self.0
            .read_values(context, address_space, nodes, max_age, timestamps_to_return)
            .await
    }

    async fn create_value_monitored_items(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        items: &mut [&mut &mut CreateMonitoredItem],
    ) {
        self.0
            .create_value_monitored_items(context, address_space, items)
            .await
    }

    async fn set_monitoring_mode(
        &self,
        context: &RequestContext,
        mode: MonitoringMode,
        items: &[&MonitoredItemRef],
    ) {
        self.0.set_monitoring_mode(context, mode, items).await
    }

    async fn modify_monitored_items(
        &self,
        context: &RequestContext,
        items: &[&MonitoredItemUpdateRef],
    ) {
        self.0.modify_monitored_items(context, items).await
    }

    async fn delete_monitored_items(&self, context: &RequestContext, items: &[&MonitoredItemRef]) {
        self.0.delete_monitored_items(context, items).await
    }

    async fn write(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        nodes_to_write: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        let writable: Vec<bool> = {
            let sp = address_space.read();
            nodes_to_write
                .iter()
                .map(|w| {
                    let v = w.value();
                    match sp.find(&v.node_id) {
                        Some(NodeType::Variable(var)) if v.attribute_id == AttributeId::Value => {
                            var.access_level().contains(AccessLevel::CURRENT_WRITE)
                        }
                        _ => true,
                    }
                })
                .collect()
        };
        let mut rest: Vec<&mut WriteNode> = Vec::with_capacity(nodes_to_write.len());
        for (w, ok) in nodes_to_write.iter_mut().zip(writable) {
            if ok {
                rest.push(&mut **w);
            } else {
                w.set_status(StatusCode::BadNotWritable);
            }
        }
        self.0.write(context, address_space, &mut rest).await
    }

    async fn call(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        methods_to_call: &mut [&mut &mut MethodCall],
    ) -> Result<(), StatusCode> {
        self.0.call(context, address_space, methods_to_call).await
    }
}
