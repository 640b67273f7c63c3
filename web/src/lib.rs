//! hwgw seen from the tools people already run: a Prometheus endpoint (`[server.metrics]`:
//! `/metrics` in OpenMetrics text and `/health`), a web page with live values
//! (`[server.web]`) and a Foxglove WebSocket live stream (`[server.foxglove]`), each a
//! server of the deployment, registered by name in the gateway's `ServerTypes`.
//!
//! Both read the gateway through its control protocol in-process
//! ([`driver_api::ControlLink`]): `status` for what `hwgw status` shows — the snapshots
//! the real-time threads keep anyway, so a scrape costs them nothing — `get` for a
//! port's value and, where the deployment allows it, `set` with the very checks `hwgw
//! set` passes. They listen on 127.0.0.1 unless the deployment says otherwise, take a
//! bounded number of clients, bound every request ([`http`]), and serve nothing from the
//! disk: the page and its script are compiled in.

pub mod config;
pub mod exposition;
pub mod foxglove;
pub mod guard;
pub mod http;
pub mod metrics;
pub mod page;
mod sampler;
mod service;

pub use config::{MetricsConfig, WebConfig};
pub use foxglove::FoxgloveConfig;
