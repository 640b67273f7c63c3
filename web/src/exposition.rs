//! `hwgw status` as OpenMetrics text (prometheus-client): every counter and state the
//! status report carries, as metric families with labels — never a metric name per
//! device — and, when the deployment asks for them, chosen ports' values.
//!
//! The families, each labelled by what the deployment names (label values escaped by
//! the encoder; interfaces and states as `hwgw status --json` writes them):
//!
//! | family | labels | what |
//! |---|---|---|
//! | `hwgw_healthy` | — | 1 when the gateway's health is ok (what feeds systemd's watchdog) |
//! | `hwgw_device_up` | `device`, `interface` | 1 while the device is online |
//! | `hwgw_device_sample_age_seconds` | `device`, `interface` | age of its last good sample |
//! | `hwgw_card_info` | `card`, `driver`, `bus` | 1 for every card |
//! | `hwgw_card_status` | `card`, `driver`, `field` | the driver's numeric counters and bus state (CAN error counters, Modbus requests, exceptions, timeouts, I2C NAKs, GPIO events lost …) |
//! | `hwgw_card_status_text` | `card`, `driver`, `field`, `value` | its text states (the CAN controller state) |
//! | `hwgw_card_outputs_written_total`, `hwgw_card_watchdog_trips_total` | `card` | the output policy's counters |
//! | `hwgw_server_status`, `hwgw_server_status_text` | `server`, `field` (, `value`) | as the cards', of every server (Modbus server, Zenoh node with its peers and import ages, these HTTP servers) |
//! | `hwgw_component_state` | `component`, `state` | 1 for the state it is in |
//! | `hwgw_component_healthy`, `hwgw_component_realtime`, `hwgw_component_warning` | `component` | 0 or 1 |
//! | `hwgw_component_steps_total`, `…_overruns_total`, `…_unhealthy_spells_total`, `…_unhealthy_seconds_total`, `…_runtime_errors_total`, `…_exceptions_total`, `…_failed_hooks_total`, `…_warnings_total`, `…_services_lost_total` | `component` | counters |
//! | `hwgw_component_step_seconds`, `hwgw_component_lateness_seconds` | `component` | histograms of step time and wake-up lateness |
//! | `hwgw_control_*` | — | the control socket's clients and requests |
//! | `hwgw_port_value` | `component`, `port` (, `index`) | opt-in: the ports a `[server.metrics]` lists |
//!
//! The histograms' buckets are powers of two nanoseconds, 2¹⁴ ns (16 µs) to 2²⁷ ns
//! (134 ms), as the activities count them (a step of exactly 2ᵏ ns counts in the bucket
//! above it).

use prometheus_client::encoding::{EncodeMetric, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::{MetricType, TypedMetric};
use prometheus_client::registry::Registry;
use protocol::{ComponentStatus, StatusReport};
use serde_json::Value;
use std::sync::Mutex;
use std::sync::atomic::AtomicU64;

/// Labels as pairs.
type Labels = Vec<(String, String)>;
type Gauges = Family<Labels, Gauge<f64, AtomicU64>>;
type Counters = Family<Labels, Counter<u64>>;
type Histograms = Family<Labels, Buckets>;

/// The lowest and highest bucket bound, as powers of two ns.
const LOW: usize = 14;
const HIGH: usize = 27;

/// A histogram as a snapshot gives it.
#[derive(Debug, Default)]
struct Snapshot {
    /// The sum of the values, s.
    sum: f64,
    /// How many values.
    count: u64,
    /// (upper bound, count in the bucket), `+Inf` last.
    buckets: Vec<(f64, u64)>,
}

/// A histogram whose buckets come from a snapshot.
#[derive(Debug, Default)]
struct Buckets(Mutex<Snapshot>);

impl TypedMetric for Buckets {
    const TYPE: MetricType = MetricType::Histogram;
}

impl EncodeMetric for Buckets {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        let s = self.0.lock().unwrap_or_else(|p| p.into_inner());
        encoder.encode_histogram::<NoLabelSet>(s.sum, s.count, &s.buckets, None)
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Histogram
    }
}

impl Buckets {
    /// Sets it from `histogram` (bucket `i`: `2^i..2^(i+1)` ns) and the sum in ns.
    fn set(&self, histogram: &[u64], total_ns: u64) {
        let at = |i: usize| histogram.get(i).copied().unwrap_or(0);
        let mut buckets = vec![(bound(LOW), (0..LOW).map(at).sum())];
        buckets.extend((LOW + 1..=HIGH).map(|k| (bound(k), at(k - 1))));
        let beyond = histogram.iter().skip(HIGH).sum();
        buckets.push((f64::INFINITY, beyond));
        let count = histogram.iter().sum();
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = Snapshot {
            sum: total_ns as f64 * 1e-9,
            count,
            buckets,
        };
    }
}

/// 2^k ns in seconds.
fn bound(k: usize) -> f64 {
    (1u64 << k) as f64 * 1e-9
}

/// `v` as `hwgw status --json` names it (`analog_in`, `stopped`).
fn json_name(v: &impl serde::Serialize) -> String {
    match serde_json::to_value(v) {
        Ok(Value::String(s)) => s,
        Ok(other) => other.to_string(),
        Err(e) => e.to_string(),
    }
}

fn labels(pairs: &[(&str, &str)]) -> Labels {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

/// A port's value read for the metrics: (component, port, its `get` answer).
pub type PortValue = (String, String, Value);

/// A gauge family `name` registered in `r`.
fn gauge(r: &mut Registry, name: &str, help: &str) -> Gauges {
    let f = Gauges::default();
    r.register(name, help, f.clone());
    f
}

/// The metrics of `status` (and of `ports`, the values read of the listed ports) as
/// OpenMetrics text.
pub fn encode(status: &StatusReport, ports: &[PortValue]) -> String {
    let mut r = Registry::default();
    let healthy = Gauge::<f64, AtomicU64>::default();
    healthy.set(f64::from(u8::from(status.health == "ok")));
    r.register(
        "hwgw_healthy",
        "1 when the gateway is healthy (what feeds systemd's watchdog)",
        healthy,
    );
    devices(&mut r, status, &gauge);
    cards(&mut r, status, &gauge);
    components(&mut r, &status.components, &gauge);
    control(&mut r, &status.control);
    if !ports.is_empty() {
        let values = gauge(&mut r, "hwgw_port_value", "A listed port's last value");
        for (component, port, value) in ports {
            port_value(&values, component, port, value);
        }
    }
    let mut out = String::new();
    // Writing into a String does not fail.
    let _ = prometheus_client::encoding::text::encode(&mut out, &r);
    out
}

fn devices(
    r: &mut Registry,
    s: &StatusReport,
    gauge: &impl Fn(&mut Registry, &str, &str) -> Gauges,
) {
    let up = gauge(r, "hwgw_device_up", "1 while the device is online");
    let age = gauge(
        r,
        "hwgw_device_sample_age_seconds",
        "Age of the device's last good sample",
    );
    for d in &s.devices {
        let interface = json_name(&d.interface);
        let l = labels(&[("device", &d.name), ("interface", &interface)]);
        let online = d.status == device_interface::Status::Online;
        up.get_or_create(&l).set(f64::from(u8::from(online)));
        if let Some(a) = d.age_s {
            age.get_or_create(&l).set(a);
        }
    }
}

fn cards(r: &mut Registry, s: &StatusReport, gauge: &impl Fn(&mut Registry, &str, &str) -> Gauges) {
    let info = gauge(r, "hwgw_card_info", "Every card, with its driver and bus");
    let values = gauge(
        r,
        "hwgw_card_status",
        "A card's numeric counter or bus state",
    );
    let texts = gauge(r, "hwgw_card_status_text", "A card's state in words");
    let written = Counters::default();
    r.register(
        "hwgw_card_outputs_written",
        "Outputs hwgw wrote",
        written.clone(),
    );
    let trips = Counters::default();
    r.register(
        "hwgw_card_watchdog_trips",
        "Outputs the watchdog drove to their safe values",
        trips.clone(),
    );
    for c in &s.cards {
        let base = [("card", c.name.as_str()), ("driver", c.driver.as_str())];
        info.get_or_create(&labels(&[base[0], base[1], ("bus", &c.status.bus)]))
            .set(1.0);
        fields(&values, &texts, &base, &c.status.counters);
        let l = labels(&[("card", &c.name)]);
        written.get_or_create(&l).inc_by(c.outputs.written);
        trips.get_or_create(&l).inc_by(c.outputs.watchdog_trips);
    }
    let values = gauge(
        r,
        "hwgw_server_status",
        "A server's numeric counter or state",
    );
    let texts = gauge(r, "hwgw_server_status_text", "A server's state in words");
    for sv in &s.servers {
        fields(
            &values,
            &texts,
            &[("server", &sv.name)],
            &sv.status.counters,
        );
    }
}

/// Every field of `counters` (nested objects flattened with dots): numbers and booleans
/// to `values`, text to `texts` (value 1, the text a label).
fn fields(
    values: &Gauges,
    texts: &Gauges,
    base: &[(&str, &str)],
    counters: &serde_json::Map<String, Value>,
) {
    let mut stack: Vec<(String, &Value)> = counters.iter().map(|(k, v)| (k.clone(), v)).collect();
    while let Some((field, v)) = stack.pop() {
        let mut l = labels(base);
        match v {
            Value::Number(n) => {
                l.push(("field".into(), field));
                values.get_or_create(&l).set(n.as_f64().unwrap_or(f64::NAN));
            }
            Value::Bool(b) => {
                l.push(("field".into(), field));
                values.get_or_create(&l).set(f64::from(u8::from(*b)));
            }
            Value::String(t) => {
                l.push(("field".into(), field));
                l.push(("value".into(), t.clone()));
                texts.get_or_create(&l).set(1.0);
            }
            Value::Object(m) => stack.extend(m.iter().map(|(k, v)| (format!("{field}.{k}"), v))),
            Value::Array(_) | Value::Null => {}
        }
    }
}

fn components(
    r: &mut Registry,
    list: &[ComponentStatus],
    gauge: &impl Fn(&mut Registry, &str, &str) -> Gauges,
) {
    let state = gauge(
        r,
        "hwgw_component_state",
        "1 for the state the component is in",
    );
    let healthy = gauge(
        r,
        "hwgw_component_healthy",
        "0 while its activity overruns more than it may",
    );
    let realtime = gauge(
        r,
        "hwgw_component_realtime",
        "1 when its thread got real-time scheduling",
    );
    let warning = gauge(
        r,
        "hwgw_component_warning",
        "1 while its warning flag is up",
    );
    let counter = |r: &mut Registry, name: &str, help: &str| {
        let f = Counters::default();
        r.register(name, help, f.clone());
        f
    };
    let steps = counter(r, "hwgw_component_steps", "Steps run");
    let overruns = counter(
        r,
        "hwgw_component_overruns",
        "Wake-ups after the next was due",
    );
    let spells = counter(
        r,
        "hwgw_component_unhealthy_spells",
        "Times its activity turned unhealthy (more overruns in a row than it may)",
    );
    let unhealthy_time = Family::<Labels, Counter<f64, AtomicU64>>::default();
    r.register(
        "hwgw_component_unhealthy_seconds",
        "Time its activity spent unhealthy (what the systemd watchdog judges)",
        unhealthy_time.clone(),
    );
    let runtime_errors = counter(
        r,
        "hwgw_component_runtime_errors",
        "Times it went to RunTimeError",
    );
    let exceptions = counter(r, "hwgw_component_exceptions", "Times it went to Exception");
    let failed_hooks = counter(
        r,
        "hwgw_component_failed_hooks",
        "Hooks that failed or panicked",
    );
    let warnings = counter(
        r,
        "hwgw_component_warnings",
        "Times its warning flag was raised",
    );
    let lost = counter(
        r,
        "hwgw_component_services_lost",
        "Times a required service or device stopped being ready",
    );
    let step_time = Histograms::default();
    r.register(
        "hwgw_component_step_seconds",
        "Step duration",
        step_time.clone(),
    );
    let lateness = Histograms::default();
    r.register(
        "hwgw_component_lateness_seconds",
        "Wake-up lateness of its periodic activity",
        lateness.clone(),
    );
    for c in list {
        let l = labels(&[("component", &c.name)]);
        let mut with_state = l.clone();
        with_state.push(("state".into(), json_name(&c.state)));
        state.get_or_create(&with_state).set(1.0);
        let flag = |f: &Gauges, b: bool| f.get_or_create(&l).set(f64::from(u8::from(b)));
        flag(&healthy, c.healthy);
        flag(&realtime, c.realtime);
        flag(&warning, c.counters.warning);
        steps.get_or_create(&l).inc_by(c.steps);
        overruns.get_or_create(&l).inc_by(c.overruns);
        spells.get_or_create(&l).inc_by(c.unhealthy_spells);
        unhealthy_time
            .get_or_create(&l)
            .inc_by(c.unhealthy_ns as f64 * 1e-9);
        runtime_errors
            .get_or_create(&l)
            .inc_by(c.counters.runtime_errors);
        exceptions.get_or_create(&l).inc_by(c.counters.exceptions);
        failed_hooks
            .get_or_create(&l)
            .inc_by(c.counters.failed_hooks);
        warnings.get_or_create(&l).inc_by(c.counters.warnings);
        lost.get_or_create(&l).inc_by(c.counters.services_lost);
        step_time
            .get_or_create(&l)
            .set(&c.step_histogram, c.step_total_ns);
        lateness
            .get_or_create(&l)
            .set(&c.lateness_histogram, c.lateness_total_ns);
    }
}

fn control(r: &mut Registry, c: &protocol::ControlReport) {
    let connected = Gauge::<i64>::default();
    connected.set(i64::try_from(c.connected).unwrap_or(i64::MAX));
    r.register(
        "hwgw_control_clients_connected",
        "Control socket clients connected now",
        connected,
    );
    for (name, help, v) in [
        (
            "hwgw_control_clients",
            "Control socket clients accepted",
            c.clients,
        ),
        (
            "hwgw_control_refused",
            "Control clients turned away for the limit",
            c.refused,
        ),
        (
            "hwgw_control_idle_closed",
            "Control clients closed for silence",
            c.idle_closed,
        ),
        (
            "hwgw_control_requests",
            "Control requests answered",
            c.requests,
        ),
        (
            "hwgw_control_errors",
            "Control requests answered with an error",
            c.errors,
        ),
        (
            "hwgw_control_accept_failures",
            "Control clients not taken for want of resources",
            c.accept_failures,
        ),
    ] {
        let counter = Counter::<u64>::default();
        counter.inc_by(v);
        r.register(name, help, counter);
    }
}

/// OpenMetrics text (as [`encode`] writes it) in Prometheus' text format 0.0.4, for a
/// client that does not ask for OpenMetrics: a counter's family is named with its
/// `_total` (as its samples are), and there is no `# EOF` or `# UNIT`.
pub fn to_prometheus_text(openmetrics: &str) -> String {
    let counters: std::collections::HashSet<&str> = openmetrics
        .lines()
        .filter_map(|l| l.strip_prefix("# TYPE "))
        .filter_map(|l| l.strip_suffix(" counter"))
        .collect();
    let mut out = String::with_capacity(openmetrics.len());
    for line in openmetrics.lines() {
        if line == "# EOF" || line.starts_with("# UNIT ") {
            continue;
        }
        let meta = ["# HELP ", "# TYPE "]
            .into_iter()
            .find_map(|p| line.strip_prefix(p).map(|rest| (p, rest)));
        match meta {
            Some((p, rest)) => {
                let (name, tail) = rest.split_once(' ').unwrap_or((rest, ""));
                let total = if counters.contains(name) {
                    "_total"
                } else {
                    ""
                };
                out.push_str(&format!("{p}{name}{total} {tail}\n"));
            }
            None => {
                out.push_str(line);
                out.push('\n');
            }
        }
    }
    out
}

/// `value` of `component.port` as gauges: a number or a boolean, or an array of them
/// (one series an index); anything else is left out.
fn port_value(values: &Gauges, component: &str, port: &str, value: &Value) {
    let number = |v: &Value| match v {
        Value::Number(n) => n.as_f64(),
        Value::Bool(b) => Some(f64::from(u8::from(*b))),
        _ => None,
    };
    let base = [("component", component), ("port", port)];
    match value {
        Value::Array(items) => {
            for (i, item) in items.iter().enumerate() {
                if let Some(x) = number(item) {
                    let index = i.to_string();
                    values
                        .get_or_create(&labels(&[base[0], base[1], ("index", &index)]))
                        .set(x);
                }
            }
        }
        v => {
            if let Some(x) = number(v) {
                values.get_or_create(&labels(&base)).set(x);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prometheus_text_names_counter_families_with_their_total() {
        let om = "# HELP a_steps Steps.\n# TYPE a_steps counter\na_steps_total 3\n\
                  # HELP g A gauge.\n# TYPE g gauge\ng 1.0\n# EOF\n";
        assert_eq!(
            to_prometheus_text(om),
            "# HELP a_steps_total Steps.\n# TYPE a_steps_total counter\na_steps_total 3\n\
             # HELP g A gauge.\n# TYPE g gauge\ng 1.0\n"
        );
    }

    /// The time a component spent unhealthy reaches the metrics to the nanosecond status
    /// gives, and its spells as counted.
    #[test]
    fn a_components_unhealthy_time_is_its_seconds_to_the_nanosecond() {
        let c: ComponentStatus = serde_json::from_value(serde_json::json!({
            "name": "loop", "state": "running", "steps": 10, "overruns": 4, "healthy": true,
            "unhealthy_spells": 2, "unhealthy_ns": 1_234_567_891u64, "realtime": false,
            "lateness_p99_us": 0.0, "step_mean_us": 0.0,
            "counters": {"runtime_errors": 0, "exceptions": 0, "failed_hooks": 0, "last_error": null}
        }))
        .unwrap();
        let mut r = Registry::default();
        components(&mut r, &[c], &gauge);
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &r).unwrap();
        assert!(
            text.contains(
                "hwgw_component_unhealthy_seconds_total{component=\"loop\"} 1.234567891\n"
            ),
            "{text}"
        );
        assert!(
            text.contains("hwgw_component_unhealthy_spells_total{component=\"loop\"} 2\n"),
            "{text}"
        );
    }

    #[test]
    fn buckets_accumulate_below_the_lowest_and_beyond_the_highest() {
        let b = Buckets::default();
        let mut h = vec![0u64; 40];
        h[3] = 2; // 8..16 ns: under the lowest bound
        h[LOW] = 5; // 2^14..2^15: le 2^15
        h[30] = 1; // beyond 2^27 ns
        b.set(&h, 1_000_000_000);
        let s = b.0.lock().unwrap();
        let (sum, count, buckets) = (s.sum, s.count, &s.buckets);
        assert_eq!(sum, 1.0);
        assert_eq!(count, 8);
        assert_eq!(buckets[0], (bound(LOW), 2));
        assert_eq!(buckets[1], (bound(LOW + 1), 5));
        assert_eq!(buckets.last(), Some(&(f64::INFINITY, 1)));
        assert_eq!(buckets.iter().map(|b| b.1).sum::<u64>(), 8);
    }
}
