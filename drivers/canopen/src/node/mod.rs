//! One managed node's life, as a state machine without I/O: NMT reset at start, boot-up
//! seen, configured by SDO (the writes, then each value read back), started, watched by
//! its heartbeat (offline when it stops; configured again at the next boot-up), its
//! emergencies counted with their codes. Frames to send go into the caller's queue; time
//! is the caller's monotonic clock in ns.

use crate::map::NodeMap;
use crate::pdo::Write;
use crate::sdo::{Download, SdoError, Step, Upload, abort, code};
use serde::Serialize;
use std::collections::VecDeque;
use std::time::Duration;

/// NMT command specifiers (CiA 301 §7.2.8.3.1).
pub mod nmt {
    /// Start remote node (to operational).
    pub const START: u8 = 0x01;
    /// Stop remote node.
    pub const STOP: u8 = 0x02;
    /// Enter pre-operational.
    pub const PRE_OPERATIONAL: u8 = 0x80;
    /// Reset node.
    pub const RESET_NODE: u8 = 0x81;
    /// Reset communication.
    pub const RESET_COMMUNICATION: u8 = 0x82;
}

/// A frame to send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tx {
    /// COB-ID.
    pub id: u16,
    /// Length.
    pub len: u8,
    /// Payload.
    pub data: [u8; 8],
}

impl Tx {
    /// An NMT command for `node`.
    pub fn nmt(command: u8, node: u8) -> Tx {
        Tx {
            id: 0,
            len: 2,
            data: [command, node, 0, 0, 0, 0, 0, 0],
        }
    }

    /// An SDO request to `node`.
    pub fn sdo(node: u8, data: [u8; 8]) -> Tx {
        Tx {
            id: 0x600 + u16::from(node),
            len: 8,
            data,
        }
    }
}

/// Where a node is, as hwgw sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NodeState {
    /// Reset at start; no boot-up or heartbeat seen yet.
    Waiting,
    /// Being configured by SDO.
    Configuring,
    /// Configured and started: its PDOs are the card's channels.
    Operational,
    /// Its heartbeat stopped.
    Offline,
    /// Its configuration failed (the error says where); tried again at its next boot-up.
    Failed,
}

/// One emergency.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Emergency {
    /// The error code (0x0000: error reset).
    pub code: u16,
    /// The error register (0x1001).
    pub register: u8,
    /// The manufacturer-specific bytes.
    pub data: [u8; 5],
}

/// How many of a node's last emergencies are kept.
pub const EMERGENCIES_KEPT: usize = 8;

/// A node's status and counters.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NodeStatus {
    /// Node id.
    pub id: u8,
    /// Where it is.
    pub state: NodeState,
    /// Its NMT state from its last heartbeat (0 boot-up, 4 stopped, 5 operational, 127
    /// pre-operational).
    pub nmt: Option<u8>,
    /// Why its configuration failed, or what went wrong last.
    pub error: Option<String>,
    /// Boot-ups seen.
    pub boot_ups: u64,
    /// Times it was configured and started.
    pub configured: u64,
    /// Times its heartbeat stopped.
    pub heartbeats_lost: u64,
    /// SDO transfers aborted (by the node, or by hwgw on a bad response or timeout).
    pub sdo_aborts: u64,
    /// SDO responses nobody asked for.
    pub sdo_unexpected: u64,
    /// Emergencies received.
    pub emergencies: u64,
    /// The last ones, newest last.
    pub last_emergencies: VecDeque<Emergency>,
    /// Heartbeat or emergency frames of the wrong length.
    pub bad_frames: u64,
}

enum Transfer {
    Write(Download),
    Verify(Upload, Vec<u8>),
    ReadOutput(Upload),
}

/// One node's manager.
pub struct NodeRun {
    map: NodeMap,
    sdo_timeout: u64,
    status: NodeStatus,
    /// Configuration step: `setup` then `verify`.
    step: usize,
    transfer: Option<(Transfer, u16, u8)>,
    deadline: u64,
    last_heartbeat: Option<u64>,
    /// Until when a heartbeat without a boot-up does not start a configuration: the
    /// reset sent at start makes the node boot (ns).
    booting_until: u64,
    /// When it was started (ns): a heartbeat sent before the START took effect still
    /// says pre-operational.
    started_at: u64,
    /// A boot-up came while an SDO transfer was under way: its response (or its timeout)
    /// is waited for and dropped, then the configuration starts again (a late response
    /// must not be taken for the new transfer's).
    restart: bool,
    /// Set when the status changed (the caller publishes it and clears this).
    pub changed: bool,
    /// The values of its RPDOs' objects as read at its configuration (index, sub, data):
    /// the caller takes them before it publishes the node operational.
    pub outputs_read: Vec<(u16, u8, Vec<u8>)>,
}

fn ns(d: Duration) -> u64 {
    d.as_nanos().min(u128::from(u64::MAX)) as u64
}

impl NodeRun {
    /// A node's manager, waiting.
    pub fn new(map: NodeMap, sdo_timeout: Duration) -> NodeRun {
        NodeRun {
            status: NodeStatus {
                id: map.id,
                state: NodeState::Waiting,
                nmt: None,
                error: None,
                boot_ups: 0,
                configured: 0,
                heartbeats_lost: 0,
                sdo_aborts: 0,
                sdo_unexpected: 0,
                emergencies: 0,
                last_emergencies: VecDeque::with_capacity(EMERGENCIES_KEPT),
                bad_frames: 0,
            },
            map,
            sdo_timeout: ns(sdo_timeout).max(1),
            step: 0,
            transfer: None,
            deadline: 0,
            last_heartbeat: None,
            booting_until: 0,
            started_at: 0,
            restart: false,
            changed: true,
            outputs_read: Vec::new(),
        }
    }

    /// Its id.
    pub fn id(&self) -> u8 {
        self.map.id
    }

    /// Its status.
    pub fn status(&self) -> &NodeStatus {
        &self.status
    }

    /// Whether its PDOs are live: configured, started, heartbeat alive.
    pub fn is_operational(&self) -> bool {
        self.status.state == NodeState::Operational
    }

    fn set_state(&mut self, state: NodeState) {
        if self.status.state != state {
            self.status.state = state;
            self.changed = true;
        }
    }

    /// At start (`now`): reset its communication, so that it boots up and is configured;
    /// a heartbeat heard before its boot-up, for one SDO timeout, is its old life's.
    pub fn start(&mut self, now: u64, out: &mut Vec<Tx>) {
        out.push(Tx::nmt(nmt::RESET_COMMUNICATION, self.map.id));
        self.booting_until = now + self.sdo_timeout;
    }

    /// Its heartbeat or boot-up frame.
    pub fn on_heartbeat(&mut self, data: &[u8], now: u64, out: &mut Vec<Tx>) {
        if data.len() != 1 {
            self.status.bad_frames += 1;
            self.changed = true;
            return;
        }
        let state = data[0] & 0x7F;
        self.last_heartbeat = Some(now);
        if self.status.nmt != Some(state) {
            self.status.nmt = Some(state);
            self.changed = true;
        }
        if state == 0 {
            self.status.boot_ups += 1;
            self.booting_until = 0;
            if self.transfer.is_some() {
                self.restart = true;
                self.set_state(NodeState::Configuring);
            } else {
                self.configure(now, out);
            }
            return;
        }
        if self.status.state == NodeState::Operational
            && state != 5
            && now >= self.started_at + self.sdo_timeout
        {
            // It left operational on its own (its error behaviour, another master): its
            // PDOs are not live; configured and started again.
            let why = format!("it left operational (NMT state {state}); configured again");
            tracing::warn!(node = self.map.id, "{why}");
            self.status.error = Some(why);
            out.push(Tx::nmt(nmt::PRE_OPERATIONAL, self.map.id));
            self.configure(now, out);
            return;
        }
        if matches!(self.status.state, NodeState::Waiting | NodeState::Offline)
            && now >= self.booting_until
        {
            // Alive, its boot-up missed: configured from pre-operational.
            out.push(Tx::nmt(nmt::PRE_OPERATIONAL, self.map.id));
            self.configure(now, out);
        }
    }

    fn configure(&mut self, now: u64, out: &mut Vec<Tx>) {
        self.restart = false;
        self.transfer = None;
        self.step = 0;
        self.outputs_read.clear();
        self.set_state(NodeState::Configuring);
        self.next(now, out);
    }

    /// Starts the next configuration step, or starts the node when there is none: the
    /// writes, the read-backs, then the reads of its outputs.
    fn next(&mut self, now: u64, out: &mut Vec<Tx>) {
        let setup = self.map.setup.len();
        let verify = setup + self.map.verify.len();
        let (transfer, first, (index, sub)) = if let Some(w) = self.map.setup.get(self.step) {
            let (d, first) = Download::start(w.index, w.sub, &w.data);
            (Transfer::Write(d), first, (w.index, w.sub))
        } else if let Some(w) = self.map.verify.get(self.step - setup) {
            let (u, first) = Upload::start(w.index, w.sub);
            (Transfer::Verify(u, w.data.clone()), first, (w.index, w.sub))
        } else if let Some(&(index, sub)) = self.map.outputs.get(self.step - verify) {
            let (u, first) = Upload::start(index, sub);
            (Transfer::ReadOutput(u), first, (index, sub))
        } else {
            out.push(Tx::nmt(nmt::START, self.map.id));
            self.started_at = now;
            // The heartbeat consumer counts from the start: while it was configured (its
            // producer time written first) its answers, not its heartbeat, said it lived.
            self.last_heartbeat = Some(now);
            self.status.configured += 1;
            self.status.error = None;
            self.set_state(NodeState::Operational);
            self.changed = true;
            return;
        };
        self.transfer = Some((transfer, index, sub));
        self.deadline = now + self.sdo_timeout;
        out.push(Tx::sdo(self.map.id, first));
    }

    /// An SDO response from it.
    pub fn on_sdo(&mut self, data: &[u8], now: u64, out: &mut Vec<Tx>) {
        if self.restart && self.transfer.is_some() {
            // The answer to a request of before the boot-up: dropped.
            self.configure(now, out);
            return;
        }
        let Some((transfer, index, sub)) = &mut self.transfer else {
            self.status.sdo_unexpected += 1;
            self.changed = true;
            return;
        };
        let (index, sub) = (*index, *sub);
        let step = match transfer {
            Transfer::Write(d) => d.on_response(data),
            Transfer::Verify(u, _) | Transfer::ReadOutput(u) => u.on_response(data),
        };
        match step {
            Ok(Step::Send(frame)) => {
                self.deadline = now + self.sdo_timeout;
                out.push(Tx::sdo(self.map.id, frame));
            }
            Ok(Step::Done(read)) => {
                // An expedited upload that does not give its size has 4 bytes: the
                // object's are the first, the rest zero.
                let mut read = read;
                let size = match &self.transfer {
                    Some((Transfer::Verify(_, wrote), ..)) => Some(wrote.len()),
                    _ => self.object_size(index, sub),
                };
                if let Some(size) = size
                    && read.len() > size
                    && read[size..].iter().all(|&b| b == 0)
                {
                    read.truncate(size);
                }
                if let Some((Transfer::Verify(_, wrote), ..)) = &self.transfer
                    && read != *wrote
                {
                    let msg = format!(
                        "read back {index:#06x} sub {sub} ({}): {} after writing {}",
                        self.object_name(index, sub),
                        hex(&read),
                        hex(wrote)
                    );
                    self.fail(msg);
                    return;
                }
                if let Some((Transfer::ReadOutput(_), ..)) = &self.transfer {
                    self.outputs_read.push((index, sub, read));
                }
                self.step += 1;
                self.transfer = None;
                self.next(now, out);
            }
            Err(e) => {
                if let Some(frame) = e.abort_frame() {
                    out.push(Tx::sdo(self.map.id, frame));
                }
                self.status.sdo_aborts += 1;
                let what = self.describe(index, sub, &e);
                self.fail(what);
            }
        }
    }

    /// The size of object `index`:`sub` in bytes, from its EDS data type.
    fn object_size(&self, index: u16, sub: u8) -> Option<usize> {
        let v = self.map.od.variable(index, sub)?;
        crate::pdo::type_bits(v.data_type).map(|b| usize::from(b).div_ceil(8))
    }

    fn object_name(&self, index: u16, sub: u8) -> String {
        match self.map.od.variable(index, sub) {
            Some(v) => v.name.clone(),
            None => "not in its EDS".into(),
        }
    }

    fn describe(&self, index: u16, sub: u8, e: &SdoError) -> String {
        let doing = if self.step < self.map.setup.len() {
            "writing"
        } else if self.step < self.map.setup.len() + self.map.verify.len() {
            "reading back"
        } else {
            "reading output"
        };
        format!(
            "configuring: {doing} {index:#06x} sub {sub} ({}): {e}",
            self.object_name(index, sub)
        )
    }

    fn fail(&mut self, why: String) {
        tracing::warn!(node = self.map.id, "{why}");
        self.transfer = None;
        self.status.error = Some(why);
        self.set_state(NodeState::Failed);
        self.changed = true;
    }

    /// An emergency from it.
    pub fn on_emcy(&mut self, data: &[u8]) {
        self.changed = true;
        if data.len() != 8 {
            self.status.bad_frames += 1;
            return;
        }
        self.status.emergencies += 1;
        if self.status.last_emergencies.len() == EMERGENCIES_KEPT {
            self.status.last_emergencies.pop_front();
        }
        self.status.last_emergencies.push_back(Emergency {
            code: u16::from_le_bytes([data[0], data[1]]),
            register: data[2],
            data: [data[3], data[4], data[5], data[6], data[7]],
        });
    }

    /// Checks its SDO and heartbeat timeouts at `now`.
    pub fn tick(&mut self, now: u64, out: &mut Vec<Tx>) {
        if self.restart && now >= self.deadline {
            self.configure(now, out);
        }
        if let Some((_, index, sub)) = &self.transfer
            && now >= self.deadline
        {
            let (index, sub) = (*index, *sub);
            out.push(Tx::sdo(self.map.id, abort(index, sub, code::TIMEOUT)));
            self.status.sdo_aborts += 1;
            let e = SdoError::Protocol {
                index,
                sub,
                why: format!("no response in {} ms", self.sdo_timeout / 1_000_000),
                code: code::TIMEOUT,
            };
            let what = self.describe(index, sub, &e);
            self.fail(what);
        }
        if let Some(at) = self.heartbeat_deadline()
            && now >= at
        {
            tracing::warn!(node = self.map.id, "heartbeat lost");
            self.status.heartbeats_lost += 1;
            self.status.nmt = None;
            self.transfer = None;
            self.last_heartbeat = None;
            self.set_state(NodeState::Offline);
        }
    }

    /// When its heartbeat is lost if none comes, if it is watched now: not while it is
    /// offline, nor while it is configured — its producer time is written then, and a
    /// slow node's SDO answers say it lives (their own timeout says when it does not); a
    /// lost heartbeat would drop the transfer under way, whose late answer the next
    /// configuration would take for its own.
    fn heartbeat_deadline(&self) -> Option<u64> {
        if matches!(
            self.status.state,
            NodeState::Offline | NodeState::Configuring
        ) {
            return None;
        }
        Some(
            self.last_heartbeat?
                .saturating_add(ns(self.map.heartbeat_timeout?)),
        )
    }

    /// When [`tick`](Self::tick) has something to check next (ns), if ever.
    pub fn next_deadline(&self) -> Option<u64> {
        let sdo = self.transfer.as_ref().map(|_| self.deadline);
        sdo.into_iter().chain(self.heartbeat_deadline()).min()
    }

    /// The NMT command that leaves it as `at_stop` says, if any.
    pub fn stop(&self, at_stop: crate::section::AtStop, out: &mut Vec<Tx>) {
        use crate::section::AtStop;
        let command = match at_stop {
            AtStop::Operational => return,
            AtStop::PreOperational => nmt::PRE_OPERATIONAL,
            AtStop::Stopped => nmt::STOP,
        };
        out.push(Tx::nmt(command, self.map.id));
    }

    /// The configuration writes (for tests and docs).
    pub fn setup(&self) -> &[Write] {
        &self.map.setup
    }
}

fn hex(b: &[u8]) -> String {
    if b.is_empty() {
        return "nothing".into();
    }
    b.iter()
        .map(|x| format!("{x:02x}"))
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests;
