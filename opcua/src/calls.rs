//! What a client changes: writes to outputs (and to components' input ports) and calls of
//! operations, each checked and answered with the matching OPC UA status code — a wrong
//! type BadTypeMismatch, out of range BadOutOfRange, a component not running
//! BadInvalidState, its device offline BadNoCommunication, a write the device did not
//! take BadDeviceFailure — nothing written when refused. Writes go through the gateway's
//! `set` (its output policy and checks, as `hwgw set`); who may write or call at all is
//! decided before, by the user's role (see `auth`).
//!
//! Values between OPC UA and the control protocol's JSON go by the type the port or
//! argument is listed with: numbers, booleans and strings as themselves, any other type
//! as its JSON text in a String.

use driver_api::ControlLink;
use driver_api::channels::{Channel, Kind};
use serde_json::{Value as Json, json};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use ua::types::{DataTypeId, DataValue, NumericRange, StatusCode, Variant};

/// The server's counts of writes and calls, and what it last refused.
#[derive(Default)]
pub(crate) struct Book {
    pub writes: AtomicU64,
    pub writes_refused: AtomicU64,
    pub calls: AtomicU64,
    pub calls_refused: AtomicU64,
    pub last_refusal: Mutex<String>,
    /// The server is stopping: nothing more is written or called.
    pub stopping: AtomicBool,
}

impl Book {
    /// Counts refusal `code` of `what`, keeps its text; returns the code.
    pub(crate) fn refuse(&self, calls: bool, code: StatusCode, what: String) -> StatusCode {
        let n = if calls {
            &self.calls_refused
        } else {
            &self.writes_refused
        };
        n.fetch_add(1, Ordering::Relaxed);
        tracing::debug!("OPC UA: {what}: {code}");
        *rtt::lock(&self.last_refusal) = format!("{what}: {code}");
        code
    }
}

/// The OPC UA data type of a control protocol type name (`f64`, `u32`, `string`…); any
/// other type travels as its JSON text.
pub(crate) fn data_type(type_name: &str) -> DataTypeId {
    match type_name {
        "f64" => DataTypeId::Double,
        "f32" => DataTypeId::Float,
        "bool" => DataTypeId::Boolean,
        "i8" => DataTypeId::SByte,
        "u8" => DataTypeId::Byte,
        "i16" => DataTypeId::Int16,
        "u16" => DataTypeId::UInt16,
        "i32" => DataTypeId::Int32,
        "u32" => DataTypeId::UInt32,
        "i64" => DataTypeId::Int64,
        "u64" => DataTypeId::UInt64,
        _ => DataTypeId::String,
    }
}

/// A JSON value of type `type_name` as a variant (`null` is empty).
pub(crate) fn to_variant(v: &Json, type_name: &str) -> Variant {
    let i = || v.as_i64();
    let u = || v.as_u64();
    let out = match (data_type(type_name), v) {
        (_, Json::Null) => Some(Variant::Empty),
        (DataTypeId::Double, _) => v.as_f64().map(Variant::Double),
        (DataTypeId::Float, _) => v.as_f64().map(|x| Variant::Float(x as f32)),
        (DataTypeId::Boolean, _) => v.as_bool().map(Variant::Boolean),
        (DataTypeId::SByte, _) => i().and_then(|x| i8::try_from(x).ok()).map(Variant::SByte),
        (DataTypeId::Byte, _) => u().and_then(|x| u8::try_from(x).ok()).map(Variant::Byte),
        (DataTypeId::Int16, _) => i().and_then(|x| i16::try_from(x).ok()).map(Variant::Int16),
        (DataTypeId::UInt16, _) => u().and_then(|x| u16::try_from(x).ok()).map(Variant::UInt16),
        (DataTypeId::Int32, _) => i().and_then(|x| i32::try_from(x).ok()).map(Variant::Int32),
        (DataTypeId::UInt32, _) => u().and_then(|x| u32::try_from(x).ok()).map(Variant::UInt32),
        (DataTypeId::Int64, _) => i().map(Variant::Int64),
        (DataTypeId::UInt64, _) => u().map(Variant::UInt64),
        (_, Json::String(s)) if type_name == "string" => Some(Variant::from(s.as_str())),
        _ => None,
    };
    out.unwrap_or_else(|| Variant::from(v.to_string().as_str()))
}

/// A variant as the JSON value of type `type_name`, or BadTypeMismatch.
pub(crate) fn to_json(v: &Variant, type_name: &str) -> Result<Json, StatusCode> {
    let integer = |v: &Variant| -> Option<Json> {
        Some(match v {
            Variant::SByte(x) => json!(x),
            Variant::Byte(x) => json!(x),
            Variant::Int16(x) => json!(x),
            Variant::UInt16(x) => json!(x),
            Variant::Int32(x) => json!(x),
            Variant::UInt32(x) => json!(x),
            Variant::Int64(x) => json!(x),
            Variant::UInt64(x) => json!(x),
            _ => return None,
        })
    };
    let out = match (data_type(type_name), v) {
        (DataTypeId::Double | DataTypeId::Float, Variant::Double(x)) => {
            serde_json::Number::from_f64(*x).map(Json::Number)
        }
        (DataTypeId::Double | DataTypeId::Float, Variant::Float(x)) => {
            serde_json::Number::from_f64(f64::from(*x)).map(Json::Number)
        }
        (DataTypeId::Double | DataTypeId::Float, v) => integer(v),
        (DataTypeId::Boolean, Variant::Boolean(b)) => Some(json!(b)),
        (DataTypeId::String, Variant::String(s)) => {
            let s = s.as_ref();
            if type_name == "string" {
                Some(json!(s))
            } else {
                serde_json::from_str(s).ok()
            }
        }
        (DataTypeId::Boolean | DataTypeId::String, _) => None,
        (_, v) => integer(v),
    };
    out.ok_or(StatusCode::BadTypeMismatch)
}

/// The gateway's `set` of `component.port` to `value`; its refusal as a status code.
fn set(control: &ControlLink, component: &str, port: &str, value: Json) -> Result<(), StatusCode> {
    let request = json!({"cmd": "set", "component": component, "port": port, "value": value});
    control.request(request).map(drop).map_err(|e| {
        tracing::debug!("OPC UA write of {component}.{port}: {e}");
        match e.kind.as_str() {
            "not_found" => StatusCode::BadNodeIdUnknown,
            "stopping" | "unavailable" => StatusCode::BadShutdown,
            _ => StatusCode::BadDeviceFailure,
        }
    })
}

/// What a channel write needs.
#[derive(Clone)]
pub(crate) struct ChannelWrite {
    pub channel: Channel,
    pub task: Option<rtt::TaskContext>,
    pub device: (device_interface::Interface, String),
    pub registry: Arc<device_interface::Registry>,
    pub control: ControlLink,
    pub book: Arc<Book>,
}

impl ChannelWrite {
    /// Writes `value` to the channel, checked; the status code of the outcome.
    pub(crate) fn write(&self, value: &DataValue, range: &NumericRange) -> StatusCode {
        let what = format!("write of {}", self.channel.address());
        match self.checked(value, range) {
            Err(code) => self.book.refuse(false, code, what),
            Ok(json) => {
                match set(
                    &self.control,
                    &self.channel.component,
                    &self.channel.port,
                    json,
                ) {
                    Ok(()) => {
                        self.book.writes.fetch_add(1, Ordering::Relaxed);
                        StatusCode::Good
                    }
                    Err(code) => self.book.refuse(false, code, what),
                }
            }
        }
    }

    fn checked(&self, value: &DataValue, range: &NumericRange) -> Result<Json, StatusCode> {
        if self.book.stopping.load(Ordering::Acquire) {
            return Err(StatusCode::BadShutdown);
        }
        if !matches!(range, NumericRange::None) {
            return Err(StatusCode::BadIndexRangeInvalid);
        }
        let v = value.value.as_ref().ok_or(StatusCode::BadTypeMismatch)?;
        let json = match (self.channel.source.kind(), v) {
            (Kind::AnalogOut, Variant::Double(x)) => self.analog(*x)?,
            (Kind::AnalogOut, Variant::Float(x)) => self.analog(f64::from(*x))?,
            (Kind::DigitalOut, Variant::Boolean(b)) => json!(b),
            (Kind::Input, _) => return Err(StatusCode::BadNotWritable),
            _ => return Err(StatusCode::BadTypeMismatch),
        };
        if !self
            .task
            .as_ref()
            .is_some_and(|t| t.state() == rtt::TaskState::Running)
        {
            return Err(StatusCode::BadInvalidState);
        }
        let (interface, name) = &self.device;
        if self
            .registry
            .health(*interface, name)
            .is_none_or(|h| h.status == device_interface::Status::Offline)
        {
            return Err(StatusCode::BadNoCommunication);
        }
        Ok(json)
    }

    fn analog(&self, x: f64) -> Result<Json, StatusCode> {
        let inside = self
            .channel
            .range
            .is_some_and(|r| r.lowest <= x && x <= r.highest);
        match serde_json::Number::from_f64(x) {
            Some(n) if inside => Ok(Json::Number(n)),
            _ => Err(StatusCode::BadOutOfRange),
        }
    }
}

/// A write to input port `port` of `task`, of type `type_name`.
pub(crate) fn port_write(
    control: &ControlLink,
    book: &Book,
    (task, port, type_name): (&rtt::TaskContext, &str, &str),
    value: &DataValue,
) -> StatusCode {
    let component = task.name();
    let what = format!("write of {component}.{port}");
    if book.stopping.load(Ordering::Acquire) {
        return book.refuse(false, StatusCode::BadShutdown, what);
    }
    let json = match value.value.as_ref().map(|v| to_json(v, type_name)) {
        Some(Ok(j)) => j,
        Some(Err(code)) => return book.refuse(false, code, what),
        None => return book.refuse(false, StatusCode::BadTypeMismatch, what),
    };
    if task.state() != rtt::TaskState::Running {
        return book.refuse(false, StatusCode::BadInvalidState, what);
    }
    match set(control, component, port, json) {
        Ok(()) => {
            book.writes.fetch_add(1, Ordering::Relaxed);
            StatusCode::Good
        }
        Err(code) => book.refuse(false, code, what),
    }
}

/// Calls `operation` of `task` with `args` converted by the operation's argument types;
/// its result converted by its result type (none when it answers nothing).
pub(crate) fn call(
    task: &rtt::TaskContext,
    book: &Book,
    info: &rtt::operation::OperationInfo,
    args: &[Variant],
) -> Result<Vec<Variant>, StatusCode> {
    let what = format!("call of {}.{}", task.name(), info.name);
    if book.stopping.load(Ordering::Acquire) {
        return Err(book.refuse(true, StatusCode::BadShutdown, what));
    }
    if args.len() != info.args.len() {
        let code = if args.len() < info.args.len() {
            StatusCode::BadArgumentsMissing
        } else {
            StatusCode::BadTooManyArguments
        };
        return Err(book.refuse(true, code, what));
    }
    let json: Result<Vec<Json>, StatusCode> = args
        .iter()
        .zip(&info.args)
        .map(|(v, a)| to_json(v, &a.type_name).map_err(|_| StatusCode::BadInvalidArgument))
        .collect();
    let json = json.map_err(|code| book.refuse(true, code, what.clone()))?;
    use rtt::component::CallOrIntrospect;
    use rtt::operation::CallError;
    match task.call_value(&info.name, json) {
        Ok(result) => {
            // A `Result` answers `{"Ok": v}` or `{"Err": e}`: its type name is `v`'s.
            let result = match result {
                Json::Object(mut o) if o.len() == 1 && o.contains_key("Ok") => {
                    o.remove("Ok").unwrap_or(Json::Null)
                }
                Json::Object(o) if o.len() == 1 && o.contains_key("Err") => {
                    let why = o.get("Err").map(Json::to_string).unwrap_or_default();
                    let code = StatusCode::BadUnexpectedError;
                    return Err(book.refuse(true, code, format!("{what}: {why}")));
                }
                other => other,
            };
            book.calls.fetch_add(1, Ordering::Relaxed);
            Ok(if info.result.is_empty() {
                Vec::new()
            } else {
                vec![to_variant(&result, &info.result)]
            })
        }
        Err(e) => {
            let code = match &e {
                CallOrIntrospect::Introspect(_) => StatusCode::BadMethodInvalid,
                CallOrIntrospect::Call(CallError::WrongArguments { .. }) => {
                    StatusCode::BadInvalidArgument
                }
                CallOrIntrospect::Call(
                    CallError::NotRunning { .. } | CallError::NotReady { .. },
                ) => StatusCode::BadInvalidState,
                CallOrIntrospect::Call(
                    CallError::Cancelled { .. } | CallError::Vanished { .. },
                ) => StatusCode::BadShutdown,
                CallOrIntrospect::Call(_) => StatusCode::BadUnexpectedError,
            };
            Err(book.refuse(true, code, format!("{what}: {e}")))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions() {
        assert_eq!(to_json(&Variant::Double(0.1), "f64"), Ok(json!(0.1)));
        assert_eq!(to_json(&Variant::Int64(3), "f64"), Ok(json!(3)));
        assert_eq!(to_json(&Variant::UInt32(7), "u32"), Ok(json!(7)));
        assert_eq!(
            to_json(&Variant::Double(1.5), "u32"),
            Err(StatusCode::BadTypeMismatch)
        );
        assert_eq!(to_json(&Variant::Boolean(true), "bool"), Ok(json!(true)));
        assert_eq!(
            to_json(&Variant::from("x"), "bool"),
            Err(StatusCode::BadTypeMismatch)
        );
        assert_eq!(to_json(&Variant::from("hi"), "string"), Ok(json!("hi")));
        assert_eq!(to_json(&Variant::from("[1,2]"), "[u32]"), Ok(json!([1, 2])));
        assert_eq!(to_variant(&json!(0.1), "f64"), Variant::Double(0.1));
        assert_eq!(to_variant(&json!(7), "u32"), Variant::UInt32(7));
        assert_eq!(to_variant(&json!("a"), "string"), Variant::from("a"));
        assert_eq!(to_variant(&json!([1]), "[u32]"), Variant::from("[1]"));
        assert_eq!(to_variant(&json!(300), "u8"), Variant::from("300"));
    }
}
