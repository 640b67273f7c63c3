//! A triggered capture, as halscope makes one: `comp.port > 3.0` is the trigger; the
//! capture is every item from `pre` before to `post` after the time of the first sample at
//! which the condition became true (a sample where it held after one where it did not).
//! As a scope's, the trigger is armed once `pre` of history has come: an edge sooner
//! after the first item is not taken.
//!
//! Items arrive in batches, each in time order (see [`crate::Capture`]), batches later
//! than each other but a batch's first items earlier than the last batch's last. So the
//! window keeps a ring of what came before the trigger, longer than `pre` by
//! [`SLACK_NS`], and decides each item by its own time: the capture holds exactly the items
//! whose times fall within `[t - pre, t + post]`. The ring is bounded; what it had to let
//! go of within `pre` is counted, and the time from which the capture is surely whole is
//! kept ([`Window::complete_from`]).

use crate::item::Item;
use serde_json::Value;
use std::collections::VecDeque;
use std::str::FromStr;

/// A comparison.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op {
    /// `>`
    Above,
    /// `>=`
    AtLeast,
    /// `<`
    Below,
    /// `<=`
    AtMost,
    /// `==`
    Equal,
    /// `!=`
    NotEqual,
}

/// `component.port OP number`.
#[derive(Debug, Clone, PartialEq)]
pub struct Trigger {
    /// The port, `component.port`.
    pub port: String,
    /// The comparison.
    pub op: Op,
    /// The level compared with.
    pub level: f64,
}

/// Why a trigger expression was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "trigger {text:?}: {why} (expected \"component.port OP number\", OP one of > >= < <= == !=)"
)]
pub struct TriggerError {
    text: String,
    why: String,
}

const OPS: [(&str, Op); 6] = [
    (">=", Op::AtLeast),
    ("<=", Op::AtMost),
    ("==", Op::Equal),
    ("!=", Op::NotEqual),
    (">", Op::Above),
    ("<", Op::Below),
];

impl FromStr for Trigger {
    type Err = TriggerError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let fail = |why: &str| TriggerError {
            text: text.chars().take(200).collect(),
            why: why.to_string(),
        };
        let (at, sym, op) = OPS
            .iter()
            .filter_map(|(sym, op)| text.find(sym).map(|i| (i, *sym, *op)))
            .min_by_key(|(i, sym, _)| (*i, std::cmp::Reverse(sym.len())))
            .ok_or_else(|| fail("no comparison"))?;
        let port = text[..at].trim();
        let level = text[at + sym.len()..].trim();
        if port
            .split_once('.')
            .is_none_or(|(c, p)| c.is_empty() || p.is_empty())
        {
            return Err(fail("the left side is not \"component.port\""));
        }
        let level: f64 = level
            .parse()
            .map_err(|_| fail(&format!("{level:?} is not a number")))?;
        if !level.is_finite() {
            return Err(fail("the level must be a finite number"));
        }
        Ok(Trigger {
            port: port.to_string(),
            op,
            level,
        })
    }
}

/// A sample's value as a number: a number, a boolean as 0 or 1, or a float's string form
/// (`"NaN"`, `"inf"`); `None` for anything else.
pub fn number(v: &Value) -> Option<f64> {
    match v {
        Value::Number(n) => n.as_f64(),
        Value::Bool(b) => Some(f64::from(u8::from(*b))),
        Value::String(s) => s.parse().ok(),
        _ => None,
    }
}

impl Trigger {
    /// Whether the condition holds for `value` (`None`: not a number).
    pub fn holds(&self, value: &Value) -> Option<bool> {
        let x = number(value)?;
        Some(match self.op {
            Op::Above => x > self.level,
            Op::AtLeast => x >= self.level,
            Op::Below => x < self.level,
            Op::AtMost => x <= self.level,
            Op::Equal => x == self.level,
            Op::NotEqual => x != self.level,
        })
    }
}

/// How much longer than `pre` the ring keeps items, and how long past `t + post` the
/// window waits for stragglers: items come in batches at most this far apart.
pub const SLACK_NS: u64 = 500_000_000;

/// The most items the ring holds (about 64 MiB of numeric samples): a `pre` longer than
/// the ring holds at the recorded rate loses its oldest items, counted as `ring_overflow`.
pub const MAX_RING: usize = 1 << 20;

/// A capture window around a trigger.
#[derive(Debug)]
pub struct Window {
    trigger: Trigger,
    /// The trigger port's index among the recorded ports.
    port: u32,
    pre_ns: u64,
    post_ns: u64,
    ring: VecDeque<Item>,
    ring_limit: usize,
    last_held: Option<bool>,
    at: Option<u64>,
    newest: u64,
    /// The recorder's clock: how far time has surely gone, items or not.
    clock: u64,
    /// Items the ring let go of within `pre` of the newest (it was full).
    pub ring_overflow: u64,
    /// The first item's time: the trigger is armed `pre` after it.
    first: Option<u64>,
    /// The newest time of an item the ring let go of (0: none).
    let_go: u64,
    /// Trigger-port samples that were not numbers.
    pub not_numbers: u64,
}

impl Window {
    /// A window of `pre_ns` before and `post_ns` after `trigger`, whose port is recorded as
    /// port number `port`; the ring holds at most `ring_limit` items (clamped to
    /// [`MAX_RING`]).
    pub fn new(trigger: Trigger, port: u32, pre_ns: u64, post_ns: u64, ring_limit: usize) -> Self {
        Window {
            trigger,
            port,
            pre_ns,
            post_ns,
            ring: VecDeque::new(),
            ring_limit: ring_limit.clamp(1, MAX_RING),
            last_held: None,
            at: None,
            newest: 0,
            clock: 0,
            ring_overflow: 0,
            first: None,
            let_go: 0,
            not_numbers: 0,
        }
    }

    /// When the trigger came (runtime clock ns), once it has.
    pub fn triggered_at(&self) -> Option<u64> {
        self.at
    }

    /// The window `[t - pre, t + post]`, once triggered.
    pub fn bounds(&self) -> Option<(u64, u64)> {
        self.at.map(|t| {
            (
                t.saturating_sub(self.pre_ns),
                t.saturating_add(self.post_ns),
            )
        })
    }

    /// Time has gone on to `now_ns` (the recorder's clock), whether items came or not: a
    /// window ends though the ports fall silent.
    pub fn advance(&mut self, now_ns: u64) {
        self.clock = self.clock.max(now_ns);
    }

    /// From when the capture surely holds every item of the window: its start, or later
    /// when the ring had to let go of items within it.
    pub fn complete_from(&self) -> Option<u64> {
        self.bounds().map(|(start, _)| {
            if self.let_go >= start {
                self.let_go + 1
            } else {
                start
            }
        })
    }

    /// True once every item of the window has surely come.
    pub fn done(&self) -> bool {
        self.bounds()
            .is_some_and(|(_, end)| self.newest.max(self.clock) > end.saturating_add(SLACK_NS))
    }

    /// Takes one item: what is to be written now goes to `out`.
    pub fn offer(&mut self, item: Item, out: &mut Vec<Item>) {
        let t = item.time_ns();
        self.newest = self.newest.max(t);
        if let Some((start, end)) = self.bounds() {
            if (start..=end).contains(&t) {
                out.push(item);
            }
            return;
        }
        let first = *self.first.get_or_insert(t);
        if let Item::Sample { port, value, at_ns } = &item
            && *port == self.port
        {
            match self.trigger.holds(value) {
                Some(held) => {
                    let armed = *at_ns >= first.saturating_add(self.pre_ns);
                    if held && self.last_held == Some(false) && armed {
                        self.at = Some(*at_ns);
                    }
                    self.last_held = Some(held);
                }
                None => self.not_numbers += 1,
            }
        }
        if self.ring.len() == self.ring_limit
            && let Some(old) = self.ring.pop_front()
        {
            self.let_go = self.let_go.max(old.time_ns());
            if old.time_ns() >= self.newest.saturating_sub(self.pre_ns) {
                self.ring_overflow += 1;
            }
        }
        self.ring.push_back(item);
        match self.bounds() {
            Some((start, end)) => {
                out.extend(
                    self.ring
                        .drain(..)
                        .filter(|i| (start..=end).contains(&i.time_ns())),
                );
                out.sort_by_key(Item::time_ns);
            }
            None => {
                let keep = self
                    .newest
                    .saturating_sub(self.pre_ns.saturating_add(SLACK_NS));
                while self.ring.front().is_some_and(|i| i.time_ns() < keep) {
                    if let Some(old) = self.ring.pop_front() {
                        self.let_go = self.let_go.max(old.time_ns());
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn expressions_parse_or_say_why_not() {
        let t: Trigger = "sim0.ai.ch1 >= -2.5".parse().expect("valid");
        assert_eq!(
            (t.port.as_str(), t.op, t.level),
            ("sim0.ai.ch1", Op::AtLeast, -2.5)
        );
        let t: Trigger = "a.b<3".parse().expect("valid");
        assert_eq!(t.op, Op::Below);
        for bad in ["a.b ~ 3", "ab > 3", "a.b > x", "a.b > inf", " > 3"] {
            let e = bad.parse::<Trigger>().expect_err(bad).to_string();
            assert!(e.contains("expected \"component.port OP number\""), "{e}");
        }
    }

    fn sample(port: u32, at_ns: u64, v: f64) -> Item {
        Item::Sample {
            port,
            at_ns,
            value: json!(v),
        }
    }

    #[test]
    fn the_window_holds_exactly_pre_before_and_post_after_the_rising_edge() {
        let trig: Trigger = "c.p > 5".parse().expect("valid");
        let ms = 1_000_000;
        let mut w = Window::new(trig, 0, 100 * ms, 50 * ms, 1 << 20);
        let mut out = Vec::new();
        // Port 0 ramps one unit each 10 ms from 0 at t = 1 s; port 1 every 1 ms, its
        // batches arriving after port 0's.
        for batch in 0..40u64 {
            for k in 0..10 {
                let t = 1_000 * ms + (batch * 10 + k) * ms;
                if k == 0 {
                    w.offer(sample(0, t, (batch as f64) / 2.0), &mut out);
                }
            }
            for k in 0..10 {
                let t = 1_000 * ms + (batch * 10 + k) * ms;
                w.offer(sample(1, t, 0.0), &mut out);
            }
        }
        // 5.5 first exceeds 5 at batch 11: t = 1.11 s.
        assert_eq!(w.triggered_at(), Some(1_110 * ms));
        let (start, end) = w.bounds().expect("triggered");
        assert_eq!((start, end), (1_010 * ms, 1_160 * ms));
        assert!(out.iter().all(|i| (start..=end).contains(&i.time_ns())));
        let ones = out
            .iter()
            .filter(|i| matches!(i, Item::Sample { port: 1, .. }))
            .count();
        assert_eq!(ones, 151, "1 ms samples from 1.010 s to 1.160 s inclusive");
        assert!(!w.done(), "0.4 s seen: stragglers may still come");
    }

    #[test]
    fn a_condition_true_from_the_start_is_not_an_edge() {
        let trig: Trigger = "c.p > 5".parse().expect("valid");
        let mut w = Window::new(trig, 0, 10, 10, 8);
        let mut out = Vec::new();
        for t in 0..20 {
            w.offer(sample(0, t, 9.0), &mut out);
        }
        assert_eq!(w.triggered_at(), None);
        assert!(out.is_empty());
        assert_eq!(w.ring_overflow, 12, "a ring of 8 kept the newest");
    }
}
