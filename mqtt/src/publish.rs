//! What a session publishes: the births (NBIRTH, a DBIRTH per online device) and the JSON
//! topics' first values, then each period what changed — DDATA by alias, a JSON message
//! per changed channel, DDEATH and DBIRTH as devices go and return — and what became of
//! the commands. A Sparkplug message counts in `seq` only once queued; a message not
//! queued (the queue full) is counted as dropped and its metrics are not marked sent, so
//! their newest values go in a later message.

use crate::commands::Origin;
use crate::link::Outbox;
use crate::model::{self, Value};
use crate::session::Node;
use crate::sparkplug;
use device_interface::Status;
use serde_json::json;
use std::sync::atomic::Ordering;
use std::time::Instant;

impl Node {
    /// Queues a Sparkplug message made with `self.seq`: the next `seq` once it is queued.
    /// A birth goes whatever the byte budget (`birth`).
    fn send(&mut self, out: &mut Outbox, topic: String, payload: Vec<u8>, birth: bool) -> bool {
        let ok = if birth {
            out.publish_now(topic, false, false, payload)
        } else {
            out.publish(topic, false, false, payload)
        };
        if ok {
            self.seq = self.seq.wrapping_add(1);
        } else {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
        }
        ok
    }

    /// At connection: the births when the host is online, and every JSON topic's value.
    pub(crate) fn first_values(&mut self, out: &mut Outbox, host_online: bool) {
        if host_online {
            self.births(out);
        }
        let at = (Instant::now(), sparkplug::now_ms());
        for gi in 0..self.groups.len() {
            let statuses = self.groups[gi].statuses(&self.registry);
            for mi in 0..self.groups[gi].metrics.len() {
                let m = &self.groups[gi].metrics[mi];
                let v = m.source.read().ok();
                let status = statuses[m.device];
                self.publish_json(out, (gi, mi), (v, v), status, at);
            }
        }
    }

    /// NBIRTH, then a DBIRTH for each online device, with the values now. When the NBIRTH
    /// cannot be queued, nothing is born and a rebirth is tried the next period.
    pub(crate) fn births(&mut self, out: &mut Outbox) {
        let Some(topics) = self.topics.clone() else {
            return;
        };
        self.born = false;
        for g in &mut self.groups {
            g.born = false;
        }
        self.seq = 0;
        let refused = self.book.refused.load(Ordering::Relaxed);
        let last = rtt::lock(&self.book.last_refusal).clone();
        let nbirth = sparkplug::nbirth(self.bd_seq, refused, &last);
        if !self.send(out, topics.node("NBIRTH"), nbirth, true) {
            self.rebirth_asked = true;
            return;
        }
        self.born = true;
        self.announced = true;
        self.counters.births.fetch_add(1, Ordering::Relaxed);
        for gi in 0..self.groups.len() {
            let statuses = self.groups[gi].statuses(&self.registry);
            if model::online(&statuses) {
                self.dbirth(out, gi);
            }
        }
    }

    /// A DBIRTH of group `gi` with its values now; whether it was queued.
    fn dbirth(&mut self, out: &mut Outbox, gi: usize) -> bool {
        let Some(topics) = self.topics.clone() else {
            return false;
        };
        let now = Instant::now();
        let g = &self.groups[gi];
        let values: Vec<Option<Value>> = g.metrics.iter().map(|m| m.source.read().ok()).collect();
        let payload = sparkplug::dbirth(self.seq, g, &values, self.settings.allow_writes);
        if !self.send(out, topics.device("DBIRTH", &g.id), payload, true) {
            return false;
        }
        let g = &mut self.groups[gi];
        g.born = true;
        for (m, v) in g.metrics.iter_mut().zip(values) {
            m.sent = v.map(|v| (v, now));
        }
        true
    }

    /// A rebirth: what changed first (for the JSON topics), then the births.
    pub(crate) fn rebirth(&mut self, out: &mut Outbox) {
        self.publish_changes(out);
        self.births(out);
    }

    /// What changed since it was last published, and devices gone or back. Sparkplug
    /// and the JSON topics each keep what they last published: a value one of them could
    /// not queue (or a DBIRTH took) is not lost for the other.
    pub(crate) fn publish_changes(&mut self, out: &mut Outbox) {
        let at = (Instant::now(), sparkplug::now_ms());
        let periods = (self.settings.min_period, self.settings.max_period);
        for gi in 0..self.groups.len() {
            let statuses = self.groups[gi].statuses(&self.registry);
            let values: Vec<Option<Value>> = self.groups[gi]
                .metrics
                .iter()
                .map(|m| m.source.read().ok())
                .collect();
            if self.born {
                self.sparkplug_changes(out, gi, &values, model::online(&statuses), at);
            }
            if self.settings.json.is_none() {
                continue;
            }
            for (mi, newest) in values.into_iter().enumerate() {
                let m = &self.groups[gi].metrics[mi];
                let state = &self.json[gi][mi];
                let due = newest.filter(|v| model::due(state.sent, m.deadband, *v, at.0, periods));
                let status = statuses[m.device];
                self.publish_json(out, (gi, mi), (due, newest), status, at);
            }
        }
    }

    /// Group `gi`'s Sparkplug messages of this period: its DDEATH or DBIRTH when it went
    /// or came back, else a DDATA of what is due among `values`, read at `at` (instant,
    /// UNIX ms).
    fn sparkplug_changes(
        &mut self,
        out: &mut Outbox,
        gi: usize,
        values: &[Option<Value>],
        online: bool,
        (now, t): (Instant, u64),
    ) {
        let Some(topics) = self.topics.clone() else {
            return;
        };
        let g = &self.groups[gi];
        if g.born && !online {
            let payload = sparkplug::ddeath(self.seq);
            if self.send(out, topics.device("DDEATH", &g.id), payload, true) {
                self.groups[gi].born = false;
            }
            return;
        }
        if !g.born {
            if online {
                self.dbirth(out, gi);
            }
            return;
        }
        let (min, max) = (self.settings.min_period, self.settings.max_period);
        let changes: Vec<(usize, Value)> = g
            .metrics
            .iter()
            .zip(values)
            .enumerate()
            .filter_map(|(i, (m, v))| {
                let v = (*v)?;
                m.due(v, now, min, max).then_some((i, v))
            })
            .collect();
        if changes.is_empty() {
            return;
        }
        let list: Vec<_> = changes
            .iter()
            .map(|(i, v)| (&g.metrics[*i], *v, t))
            .collect();
        let payload = sparkplug::ddata(self.seq, &list);
        // Not queued: these values go with a later message.
        if self.send(out, topics.device("DDATA", &g.id), payload, false) {
            for (i, v) in changes {
                self.groups[gi].metrics[i].sent = Some((v, now));
            }
        }
    }

    /// A JSON topic's state when its value is due (`due`), its device's status changed,
    /// or a value of it is still to be published (then the `newest`); a message not queued
    /// is counted and tried again with the newest value the next period.
    fn publish_json(
        &mut self,
        out: &mut Outbox,
        (gi, mi): (usize, usize),
        (due, newest): (Option<Value>, Option<Value>),
        status: Status,
        (now, t): (Instant, u64),
    ) {
        let Some(prefix) = &self.settings.json else {
            return;
        };
        let m = &self.groups[gi].metrics[mi];
        let state = &mut self.json[gi][mi];
        if due.is_none() && state.status == Some(status) && !state.pending {
            return;
        }
        let value = due.or(newest).or(state.sent.map(|s| s.0));
        let text = value.map_or(serde_json::Value::Null, Value::json);
        let body = json!({"value": text, "status": status.to_string(), "t": t});
        let topic = format!("{prefix}/{}/{}", m.component, m.port);
        if out.publish(topic, false, true, body.to_string().into_bytes()) {
            state.status = Some(status);
            state.pending = false;
            if let Some(v) = value {
                state.sent = Some((v, now));
            }
        } else {
            state.pending = true;
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// What became of the commands since the last period.
    pub(crate) fn publish_outcomes(&mut self, out: &mut Outbox) {
        let outcomes: Vec<_> = rtt::lock(&self.book.outcomes).drain(..).collect();
        let mut refused = false;
        for o in outcomes {
            match &o.origin {
                Origin::Sparkplug(_) => refused |= o.result.is_err(),
                Origin::Json(topic) => {
                    let body = match &o.result {
                        Ok(()) => json!({"ok": true}),
                        Err(why) => json!({"ok": false, "error": why.to_string()}),
                    };
                    let topic = format!("{topic}/result");
                    if !out.publish(topic, true, false, body.to_string().into_bytes()) {
                        self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
        if let (true, true, Some(topics)) = (refused, self.born, self.topics.clone()) {
            let n = self.book.refused.load(Ordering::Relaxed);
            let last = rtt::lock(&self.book.last_refusal).clone();
            let payload = sparkplug::ndata_refusal(self.seq, n, &last);
            self.send(out, topics.node("NDATA"), payload, false);
        }
    }
}
