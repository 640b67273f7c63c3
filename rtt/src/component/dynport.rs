//! The type-erased port layer: every port of a component reachable by name, read and
//! written as JSON values, connected without knowing its type at compile time.

use crate::error::IntrospectError;
use crate::info::{Direction, NamedValue, PortData, PortInfo};
use crate::port::journal::{Journal, Tap, tap_shared};
use crate::port::word::from_word;
use crate::port::{
    ConnPolicy, ConnectError, ConnectionInfo, FlowStatus, InputPort, InputShared, OutputPort,
    OutputShared, connect_shared, connect_with,
};
use serde::Serialize;
use serde_json::Value;
use std::any::Any;
use std::sync::{Arc, OnceLock};

/// Reads a port's data as dynamically typed values (made by [`DynPort::reader`] and
/// [`DynPort::stamped_reader`]).
pub trait DynReader: Send {
    /// The next sample, as [`InputPort::read`] gives it, serialised.
    fn read(&mut self) -> (FlowStatus, Option<Value>);

    /// The next sample and, when new and the connection is stamped, the time it was
    /// written (ns on the monotonic clock; 0 from an unstamped connection).
    fn read_at(&mut self) -> (FlowStatus, Option<Value>, u64) {
        let (status, value) = self.read();
        (status, value, 0)
    }

    /// Samples lost so far on this reader's connection because its buffer was full.
    fn dropped(&self) -> u64 {
        0
    }
}

/// Turns a journal entry's word back into its port's value, serialised (made with a
/// [`DynPort::tap`]).
pub type WordValue = Box<dyn Fn(u64) -> Option<Value> + Send>;

/// Writes dynamically typed values into an input port (made by [`DynPort::writer`]).
pub trait DynWriter: Send {
    /// Converts `value` to the port's type and writes it.
    fn write(&mut self, value: Value) -> Result<(), IntrospectError>;
}

/// A port of any type and direction, reachable by name.
pub trait DynPort: Send + Sync {
    /// Name, doc, direction, type.
    fn info(&self) -> PortInfo;
    /// Live connections and their counters.
    fn connections(&self) -> Vec<ConnectionInfo>;
    /// The port's current value: an output port's last written value; an input port's
    /// read-back of what it drives when it has one (a device output), else the last new
    /// sample its component read. `None` before there is one.
    fn last_value(&self) -> Result<Option<Value>, IntrospectError>;
    /// A new connection from this output port to a reader of serialised values.
    fn reader(&self, policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError>;
    /// A new stamped buffer connection (see [`crate::port::connect_stamped`]) from this
    /// output port to a reader of serialised values with the time each was written. A port
    /// that cannot stamp refuses.
    fn stamped_reader(&self, _policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        let info = self.info();
        Err(IntrospectError::Refused {
            what: format!("port {:?}", info.name),
            detail: "it gives no stamped connection".into(),
        })
    }
    /// A tap of this output port into `journal` as number `tap` (see
    /// [`crate::port::journal`]), with what turns its entries' words back into values. A
    /// port that cannot be tapped (an input, or samples of more than one word) refuses.
    fn tap(
        &self,
        _journal: &Arc<Journal>,
        _tap: u32,
        _reader: &str,
    ) -> Result<(Tap, WordValue), IntrospectError> {
        let info = self.info();
        Err(IntrospectError::Refused {
            what: format!("port {:?}", info.name),
            detail: "it cannot be tapped into a journal".into(),
        })
    }
    /// A new connection from a writer of serialised values to this input port.
    fn writer(&self, policy: ConnPolicy) -> Result<Box<dyn DynWriter>, IntrospectError>;
    /// For an input port that drives something (a device output): `value` written there
    /// now, past the port, with the answer of what it drives — refused, not delivered, or
    /// done. `None` for every other port (a value for it goes through a
    /// [`writer`](Self::writer)).
    fn drive(&self, _value: Value) -> Option<Result<(), IntrospectError>> {
        None
    }
    /// True for an input port that drives something ([`drive`](Self::drive) answers).
    fn drives(&self) -> bool {
        false
    }
    /// Connects this output port to `input`.
    fn connect_to(
        &self,
        input: &dyn DynPort,
        policy: ConnPolicy,
    ) -> Result<ConnectionInfo, IntrospectError>;
    /// Closes connection `id`, or all with `None`; returns how many.
    fn disconnect(&self, id: Option<u64>) -> usize;
    /// For typed downcasts.
    fn as_any(&self) -> &dyn Any;
    /// Gives the port's values names (once; false if it had them already).
    fn name_values(&self, values: Vec<NamedValue>) -> bool;
}

/// The value `value` names among `values` (a string that is one of the names), else
/// `value` itself.
fn unname(values: &[NamedValue], value: Value) -> Value {
    match &value {
        Value::String(s) => values
            .iter()
            .find(|v| v.name == *s)
            .map_or(value, |v| v.value.clone()),
        _ => value,
    }
}

/// What a port of type `T` with named values `values` takes.
fn expected<T>(values: &[NamedValue]) -> String {
    let t = crate::typename::of::<T>();
    if values.is_empty() {
        return t;
    }
    let names: Vec<&str> = values.iter().map(|v| v.name.as_str()).collect();
    format!("{t} or one of {}", names.join(", "))
}

/// An output port as the dynamic layer holds it.
pub(crate) struct OutEntry<T: Send> {
    pub(crate) shared: Arc<OutputShared<T>>,
    pub(crate) doc: String,
    pub(crate) values: OnceLock<Vec<NamedValue>>,
}

/// A port's value as JSON. A number that is not finite becomes the string `"NaN"`,
/// `"inf"` or `"-inf"`: JSON has no such numbers, and `null` means "no data yet".
pub fn to_json<T: Serialize + 'static>(v: &T) -> Option<Value> {
    let any = v as &dyn Any;
    let f = any
        .downcast_ref::<f64>()
        .copied()
        .or_else(|| any.downcast_ref::<f32>().map(|f| f64::from(*f)));
    match f {
        Some(f) if !f.is_finite() => Some(Value::String(f.to_string())),
        _ => serde_json::to_value(v).ok(),
    }
}

/// Reads back what an input port drives (a device output's current value).
pub(crate) type ReadBack<T> = Box<dyn Fn() -> Option<T> + Send + Sync>;

/// Checks a value written into an input port through the dynamic layer before it is
/// written (a device output's range): `Err` says why it is refused.
pub(crate) type Check<T> = Arc<dyn Fn(&T) -> Result<(), String> + Send + Sync>;

/// An input port as the dynamic layer holds it.
pub(crate) struct InEntry<T: Send> {
    pub(crate) shared: Arc<InputShared<T>>,
    pub(crate) doc: String,
    pub(crate) values: OnceLock<Vec<NamedValue>>,
    pub(crate) sample: T,
    pub(crate) event: bool,
    pub(crate) read_back: Option<ReadBack<T>>,
    pub(crate) check: Option<Check<T>>,
    /// Writes a value set from outside straight to what the port drives (see
    /// [`DynPort::drive`]).
    pub(crate) apply: Option<Check<T>>,
}

fn direction_error(port: &str, actual: Direction, what: &'static str) -> IntrospectError {
    let needed = match actual {
        Direction::Input => Direction::Output,
        Direction::Output => Direction::Input,
    };
    IntrospectError::Direction {
        port: port.to_string(),
        actual,
        needed,
        what,
    }
}

struct ValueReader<T: Clone + Send + 'static> {
    port: InputPort<T>,
    sample: T,
    /// Losses counted so far (a connection whose writer went away is no longer listed).
    dropped: std::cell::Cell<u64>,
}

// A dynamic reader lives off the real-time threads (a watch, a recording, a reporter): its
// connections are kept until their writers let go, so a real-time writer never frees one.
impl<T: Clone + Send + 'static> Drop for ValueReader<T> {
    fn drop(&mut self) {
        self.port.bury_connections();
    }
}

impl<T: PortData> DynReader for ValueReader<T> {
    fn read(&mut self) -> (FlowStatus, Option<Value>) {
        let (status, value, _) = self.read_at();
        (status, value)
    }

    fn read_at(&mut self) -> (FlowStatus, Option<Value>, u64) {
        let mut at = 0;
        match self.port.read_at(&mut self.sample, &mut at) {
            FlowStatus::NoData => (FlowStatus::NoData, None, 0),
            s => (s, to_json(&self.sample), at),
        }
    }

    fn dropped(&self) -> u64 {
        let now: u64 = self.port.connections().iter().map(|c| c.dropped).sum();
        let n = now.max(self.dropped.get());
        self.dropped.set(n);
        n
    }
}

struct ValueWriter<T: Send> {
    port: OutputPort<T>,
    what: String,
    check: Option<Check<T>>,
    values: Vec<NamedValue>,
}

impl<T: PortData> DynWriter for ValueWriter<T> {
    fn write(&mut self, value: Value) -> Result<(), IntrospectError> {
        let value = unname(&self.values, value);
        let v: T = serde_json::from_value(value).map_err(|e| IntrospectError::BadValue {
            what: self.what.clone(),
            expected: expected::<T>(&self.values),
            detail: e.to_string(),
        })?;
        if let Some(check) = &self.check {
            check(&v).map_err(|detail| IntrospectError::Refused {
                what: self.what.clone(),
                detail,
            })?;
        }
        self.port.write(&v);
        Ok(())
    }
}

impl<T: PortData> OutEntry<T> {
    fn value_reader(
        &self,
        policy: ConnPolicy,
        stamped: bool,
    ) -> Result<Box<dyn DynReader>, IntrospectError> {
        let sample = match self.shared.last_written() {
            Some(v) => v,
            None => self.shared.sample_clone(),
        };
        let port = InputPort::with_sample(&format!("{}.reader", self.shared.name), sample.clone());
        connect_with(&self.shared, port.shared(), policy, stamped)?;
        Ok(Box::new(ValueReader {
            port,
            sample,
            dropped: std::cell::Cell::new(0),
        }))
    }
}

impl<T: PortData> DynPort for OutEntry<T> {
    fn info(&self) -> PortInfo {
        PortInfo {
            name: self.shared.name.to_string(),
            doc: self.doc.clone(),
            direction: Direction::Output,
            type_name: crate::typename::of::<T>(),
            event: false,
            values: self.values.get().cloned().unwrap_or_default(),
        }
    }

    fn connections(&self) -> Vec<ConnectionInfo> {
        self.shared.connections()
    }

    fn last_value(&self) -> Result<Option<Value>, IntrospectError> {
        Ok(self.shared.last_written().and_then(|v| to_json(&v)))
    }

    fn reader(&self, policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        self.value_reader(policy, false)
    }

    fn stamped_reader(&self, policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        self.value_reader(policy, true)
    }

    fn tap(
        &self,
        journal: &Arc<Journal>,
        tap: u32,
        reader: &str,
    ) -> Result<(Tap, WordValue), IntrospectError> {
        let t = tap_shared(&self.shared, journal, tap, reader)?;
        let sample = self.shared.sample_clone();
        Ok((
            t,
            Box::new(move |w| {
                let mut v = sample.clone();
                from_word(w, &mut v);
                to_json(&v)
            }),
        ))
    }

    fn writer(&self, _policy: ConnPolicy) -> Result<Box<dyn DynWriter>, IntrospectError> {
        Err(direction_error(
            &self.shared.name,
            Direction::Output,
            "writing",
        ))
    }

    fn connect_to(
        &self,
        input: &dyn DynPort,
        policy: ConnPolicy,
    ) -> Result<ConnectionInfo, IntrospectError> {
        match input.as_any().downcast_ref::<InEntry<T>>() {
            Some(inp) => Ok(connect_shared(&self.shared, &inp.shared, policy)?),
            None => {
                let info = input.info();
                if info.direction == Direction::Output {
                    return Err(ConnectError::Direction {
                        from: self.shared.name.to_string(),
                        to: info.name,
                    }
                    .into());
                }
                Err(ConnectError::TypeMismatch {
                    output: self.shared.name.to_string(),
                    output_type: crate::typename::of::<T>(),
                    input: info.name,
                    input_type: info.type_name,
                }
                .into())
            }
        }
    }

    fn disconnect(&self, id: Option<u64>) -> usize {
        self.shared.disconnect(id)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }

    fn name_values(&self, values: Vec<NamedValue>) -> bool {
        self.values.set(values).is_ok()
    }
}

impl<T: PortData> DynPort for InEntry<T> {
    fn info(&self) -> PortInfo {
        PortInfo {
            name: self.shared.name.to_string(),
            doc: self.doc.clone(),
            direction: Direction::Input,
            type_name: crate::typename::of::<T>(),
            event: self.event,
            values: self.values.get().cloned().unwrap_or_default(),
        }
    }

    fn connections(&self) -> Vec<ConnectionInfo> {
        self.shared.connections()
    }

    fn last_value(&self) -> Result<Option<Value>, IntrospectError> {
        let v = match &self.read_back {
            Some(f) => f(),
            None => self.shared.last_read(),
        };
        Ok(v.and_then(|v| to_json(&v)))
    }

    fn reader(&self, _policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        Err(direction_error(
            &self.shared.name,
            Direction::Input,
            "watching",
        ))
    }

    fn stamped_reader(&self, policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        self.reader(policy)
    }

    fn writer(&self, policy: ConnPolicy) -> Result<Box<dyn DynWriter>, IntrospectError> {
        let port =
            OutputPort::with_sample(&format!("{}.writer", self.shared.name), self.sample.clone());
        connect_shared(port.shared(), &self.shared, policy)?;
        Ok(Box::new(ValueWriter {
            port,
            what: format!("port {:?}", self.shared.name),
            check: self.check.clone(),
            values: self.values.get().cloned().unwrap_or_default(),
        }))
    }

    fn drives(&self) -> bool {
        self.apply.is_some()
    }

    fn drive(&self, value: Value) -> Option<Result<(), IntrospectError>> {
        let apply = self.apply.as_ref()?;
        let what = format!("port {:?}", self.shared.name);
        let values = self.values.get().map(Vec::as_slice).unwrap_or_default();
        let v: T = match serde_json::from_value(unname(values, value)) {
            Ok(v) => v,
            Err(e) => {
                return Some(Err(IntrospectError::BadValue {
                    what,
                    expected: expected::<T>(values),
                    detail: e.to_string(),
                }));
            }
        };
        let checked = match &self.check {
            Some(check) => check(&v),
            None => Ok(()),
        };
        Some(
            checked
                .and_then(|()| apply(&v))
                .map_err(|detail| IntrospectError::Refused { what, detail }),
        )
    }

    fn connect_to(
        &self,
        input: &dyn DynPort,
        _policy: ConnPolicy,
    ) -> Result<ConnectionInfo, IntrospectError> {
        Err(ConnectError::Direction {
            from: self.shared.name.to_string(),
            to: input.info().name,
        }
        .into())
    }

    fn disconnect(&self, id: Option<u64>) -> usize {
        self.shared.disconnect(id)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }

    fn name_values(&self, values: Vec<NamedValue>) -> bool {
        self.values.set(values).is_ok()
    }
}
