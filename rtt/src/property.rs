//! Properties (configuration) and attributes (run-time values) of a component.
//!
//! A [`Property<T>`] is a typed, documented value in a [`PropertyBag`]; bags nest, so a
//! property has a dotted path (`pid.kp`). Bags load from and save to TOML; a bad file gets
//! errors that name the key path and say what was expected, and nothing changes unless the
//! whole file is valid. Attributes are the same mechanism in a second bag that is not
//! loaded from configuration.
//!
//! Reading a property on a real-time path is lock-free ([`Property::load`]); setting one
//! allocates and belongs to configuration time.
//!
//! ```
//! use rtt::property::PropertyBag;
//!
//! let bag = PropertyBag::new("controller");
//! let period = bag.add("period_ms", 10u32, "control period")?;
//! let pid = bag.bag("pid", "gains")?;
//! let kp = pid.add("kp", 1.0f64, "proportional gain")?;
//!
//! bag.load_toml_str("period_ms = 5\n[pid]\nkp = 2.5\n")?;
//! assert_eq!((period.get(), kp.get()), (5, 2.5));
//!
//! let err = bag.load_toml_str("[pid]\nkp = \"fast\"\n").unwrap_err();
//! assert!(err.to_string().contains("pid.kp"));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::lock::lock;
use arc_swap::ArcSwap;
use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::sync::{Arc, Mutex};

/// What a property can hold: any clonable serde type.
pub trait PropertyValue: Clone + Send + Sync + Serialize + DeserializeOwned + 'static {}
impl<T: Clone + Send + Sync + Serialize + DeserializeOwned + 'static> PropertyValue for T {}

/// Why a property could not be found, set, loaded or added.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PropertyError {
    /// No such property or bag.
    #[error("no property {path:?}; there are: {}", list(.known))]
    NotFound {
        /// The path asked for.
        path: String,
        /// The paths that exist.
        known: Vec<String>,
    },
    /// A value of the wrong type or shape.
    #[error("{path}: expected {expected}: {detail}")]
    WrongType {
        /// The property's path.
        path: String,
        /// Its Rust type.
        expected: String,
        /// What was wrong.
        detail: String,
    },
    /// A value where a table of properties was expected, or the reverse.
    #[error("{path}: {problem}")]
    Shape {
        /// The path.
        path: String,
        /// What was wrong.
        problem: String,
    },
    /// A name added twice to one bag.
    #[error("property {name:?} already exists in this bag")]
    Duplicate {
        /// The name.
        name: String,
    },
    /// A TOML text that does not parse.
    #[error("invalid TOML: {0}")]
    Toml(String),
    /// Several errors from one load.
    #[error("{}", .0.iter().map(|e| e.to_string()).collect::<Vec<_>>().join("\n"))]
    Many(Vec<PropertyError>),
}

fn list(v: &[String]) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// One property or attribute, as listed.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct PropertyInfo {
    /// Dotted path.
    pub path: String,
    /// Type of the value, as the control protocol names it ([`crate::typename`]).
    pub type_name: String,
    /// What it is for.
    pub doc: String,
    /// Current value.
    pub value: Value,
}

struct Cell<T> {
    name: String,
    doc: String,
    value: ArcSwap<T>,
}

/// A typed, documented value. Cheap to clone; every clone sees the same value.
pub struct Property<T> {
    cell: Arc<Cell<T>>,
}

impl<T> Clone for Property<T> {
    fn clone(&self) -> Self {
        Property {
            cell: Arc::clone(&self.cell),
        }
    }
}

impl<T: PropertyValue> Property<T> {
    /// A copy of the value. Lock-free; allocation-free for `Copy` values (so a real-time
    /// update can read a gain with it).
    pub fn get(&self) -> T {
        (**self.cell.value.load()).clone()
    }

    /// The value, without copying or locking (for real-time paths).
    pub fn load(&self) -> arc_swap::Guard<Arc<T>> {
        self.cell.value.load()
    }

    /// Replaces the value (allocates: configuration time).
    pub fn set(&self, value: T) {
        self.cell.value.store(Arc::new(value));
    }

    /// The name.
    pub fn name(&self) -> &str {
        &self.cell.name
    }

    /// The documentation.
    pub fn doc(&self) -> &str {
        &self.cell.doc
    }
}

trait DynProperty: Send + Sync {
    fn doc(&self) -> &str;
    fn type_name(&self) -> String;
    fn get_value(&self) -> Value;
    fn check(&self, v: &Value) -> Result<(), String>;
    fn set_value(&self, v: Value) -> Result<(), String>;
}

impl<T: PropertyValue> DynProperty for Cell<T> {
    fn doc(&self) -> &str {
        &self.doc
    }

    fn type_name(&self) -> String {
        crate::typename::of::<T>()
    }

    fn get_value(&self) -> Value {
        serde_json::to_value(&**self.value.load()).unwrap_or(Value::Null)
    }

    fn check(&self, v: &Value) -> Result<(), String> {
        T::deserialize(v).map(|_| ()).map_err(|e| e.to_string())
    }

    fn set_value(&self, v: Value) -> Result<(), String> {
        let t = T::deserialize(v).map_err(|e| e.to_string())?;
        self.value.store(Arc::new(t));
        Ok(())
    }
}

/// A value fixed when it was added: read like a property, never written.
struct Constant {
    doc: String,
    type_name: String,
    value: Value,
}

impl DynProperty for Constant {
    fn doc(&self) -> &str {
        &self.doc
    }

    fn type_name(&self) -> String {
        self.type_name.clone()
    }

    fn get_value(&self) -> Value {
        self.value.clone()
    }

    fn check(&self, _: &Value) -> Result<(), String> {
        Err("a constant: it cannot be set".into())
    }

    fn set_value(&self, v: Value) -> Result<(), String> {
        self.check(&v)
    }
}

enum Entry {
    Value(Arc<dyn DynProperty>),
    Bag(Arc<PropertyBag>),
}

/// A documented set of properties and nested bags.
pub struct PropertyBag {
    doc: String,
    entries: Mutex<Vec<(String, Entry)>>,
}

impl PropertyBag {
    /// An empty bag.
    pub fn new(doc: &str) -> Self {
        PropertyBag {
            doc: doc.to_string(),
            entries: Mutex::new(Vec::new()),
        }
    }

    /// The bag's documentation.
    pub fn doc(&self) -> &str {
        &self.doc
    }

    /// Adds property `name` with a default value.
    pub fn add<T: PropertyValue>(
        &self,
        name: &str,
        default: T,
        doc: &str,
    ) -> Result<Property<T>, PropertyError> {
        let cell = Arc::new(Cell {
            name: name.to_string(),
            doc: doc.to_string(),
            value: ArcSwap::from_pointee(default),
        });
        self.insert(name, Entry::Value(cell.clone()))?;
        Ok(Property { cell })
    }

    /// Adds constant `name` (RTT's `addConstant`): listed and read by name like the rest,
    /// refused when written.
    pub fn constant<T: PropertyValue>(
        &self,
        name: &str,
        value: T,
        doc: &str,
    ) -> Result<(), PropertyError> {
        let constant = Arc::new(Constant {
            doc: doc.to_string(),
            type_name: crate::typename::of::<T>(),
            value: serde_json::to_value(&value).unwrap_or(Value::Null),
        });
        self.insert(name, Entry::Value(constant))
    }

    /// Adds a nested bag `name`.
    pub fn bag(&self, name: &str, doc: &str) -> Result<Arc<PropertyBag>, PropertyError> {
        let bag = Arc::new(PropertyBag::new(doc));
        self.insert(name, Entry::Bag(bag.clone()))?;
        Ok(bag)
    }

    fn insert(&self, name: &str, entry: Entry) -> Result<(), PropertyError> {
        let mut entries = lock(&self.entries);
        if name.is_empty() || name.contains('.') || entries.iter().any(|(n, _)| n == name) {
            return Err(PropertyError::Duplicate {
                name: name.to_string(),
            });
        }
        entries.push((name.to_string(), entry));
        Ok(())
    }

    fn find(&self, path: &str) -> Result<Arc<dyn DynProperty>, PropertyError> {
        let not_found = || PropertyError::NotFound {
            path: path.to_string(),
            known: self.list().into_iter().map(|i| i.path).collect(),
        };
        let mut bag_holder: Option<Arc<PropertyBag>> = None;
        let mut parts = path.split('.').peekable();
        while let Some(part) = parts.next() {
            let bag: &PropertyBag = bag_holder.as_deref().unwrap_or(self);
            // Decide under the lock, build any error after it (listing locks again).
            let next = {
                let entries = lock(&bag.entries);
                match entries.iter().find(|(n, _)| n == part).map(|(_, e)| e) {
                    Some(Entry::Value(p)) if parts.peek().is_none() => return Ok(p.clone()),
                    Some(Entry::Bag(b)) if parts.peek().is_some() => Some(b.clone()),
                    _ => None,
                }
            };
            bag_holder = Some(next.ok_or_else(not_found)?);
        }
        Err(not_found())
    }

    /// The value at `path`, dynamically typed.
    pub fn get_value(&self, path: &str) -> Result<Value, PropertyError> {
        Ok(self.find(path)?.get_value())
    }

    /// Sets the value at `path` from a dynamically typed value.
    pub fn set_value(&self, path: &str, value: Value) -> Result<(), PropertyError> {
        let p = self.find(path)?;
        p.set_value(value)
            .map_err(|detail| PropertyError::WrongType {
                path: path.to_string(),
                expected: p.type_name(),
                detail,
            })
    }

    /// Every property, depth first, with its path, type, doc and value.
    pub fn list(&self) -> Vec<PropertyInfo> {
        let mut out = Vec::new();
        self.walk("", &mut |path, p| {
            out.push(PropertyInfo {
                path: path.to_string(),
                type_name: p.type_name(),
                doc: p.doc().to_string(),
                value: p.get_value(),
            })
        });
        out
    }

    fn walk(&self, prefix: &str, f: &mut dyn FnMut(&str, &Arc<dyn DynProperty>)) {
        let entries: Vec<(String, Entry)> = lock(&self.entries)
            .iter()
            .map(|(n, e)| {
                let e = match e {
                    Entry::Value(p) => Entry::Value(p.clone()),
                    Entry::Bag(b) => Entry::Bag(b.clone()),
                };
                (n.clone(), e)
            })
            .collect();
        for (name, e) in entries {
            let path = if prefix.is_empty() {
                name
            } else {
                format!("{prefix}.{name}")
            };
            match e {
                Entry::Value(p) => f(&path, &p),
                Entry::Bag(b) => b.walk(&path, f),
            }
        }
    }

    /// Loads values from a TOML table. Unknown keys and wrong types are errors naming their
    /// key path; all are reported, and nothing changes unless every value is valid.
    pub fn load_toml(&self, table: &toml::Table) -> Result<(), PropertyError> {
        let mut plan = Vec::new();
        let mut errors = Vec::new();
        self.plan_load("", table, &mut plan, &mut errors);
        match errors.len() {
            0 => {
                for (p, v) in plan {
                    // Checked in plan_load, so this cannot fail now.
                    let _ = p.set_value(v);
                }
                Ok(())
            }
            1 => Err(errors.remove(0)),
            _ => Err(PropertyError::Many(errors)),
        }
    }

    /// Parses `text` as TOML and loads it as [`load_toml`](Self::load_toml) does.
    pub fn load_toml_str(&self, text: &str) -> Result<(), PropertyError> {
        let table: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| PropertyError::Toml(e.to_string()))?;
        self.load_toml(&table)
    }

    fn plan_load(
        &self,
        prefix: &str,
        table: &toml::Table,
        plan: &mut Vec<(Arc<dyn DynProperty>, Value)>,
        errors: &mut Vec<PropertyError>,
    ) {
        for (key, value) in table {
            let path = if prefix.is_empty() {
                key.clone()
            } else {
                format!("{prefix}.{key}")
            };
            let entry = lock(&self.entries)
                .iter()
                .find(|(n, _)| n == key)
                .map(|(_, e)| match e {
                    Entry::Value(p) => Entry::Value(p.clone()),
                    Entry::Bag(b) => Entry::Bag(b.clone()),
                });
            match (entry, value) {
                (None, _) => errors.push(PropertyError::NotFound {
                    path,
                    known: lock(&self.entries).iter().map(|(n, _)| n.clone()).collect(),
                }),
                (Some(Entry::Bag(b)), toml::Value::Table(t)) => b.plan_load(&path, t, plan, errors),
                (Some(Entry::Bag(_)), other) => errors.push(PropertyError::Shape {
                    path,
                    problem: format!("expected a table of properties, found {}", other.type_str()),
                }),
                (Some(Entry::Value(p)), v) => {
                    let json = serde_json::to_value(v).unwrap_or(Value::Null);
                    match p.check(&json) {
                        Ok(()) => plan.push((p, json)),
                        Err(detail) => errors.push(PropertyError::WrongType {
                            path,
                            expected: p.type_name(),
                            detail,
                        }),
                    }
                }
            }
        }
    }

    /// The bag as a TOML table (values that TOML cannot hold, such as `None`, are left out).
    pub fn to_toml(&self) -> toml::Table {
        let mut root = toml::Table::new();
        self.walk("", &mut |path, p| {
            let Ok(v) = toml::Value::try_from(p.get_value()) else {
                return;
            };
            let mut parts: Vec<&str> = path.split('.').collect();
            let Some(last) = parts.pop() else { return };
            let mut t = &mut root;
            for part in parts {
                let entry = t
                    .entry(part.to_string())
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                let toml::Value::Table(inner) = entry else {
                    return;
                };
                t = inner;
            }
            t.insert(last.to_string(), v);
        });
        root
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Limits {
        low: f64,
        high: f64,
    }

    fn bag() -> (PropertyBag, Property<u32>, Property<f64>, Property<Limits>) {
        let bag = PropertyBag::new("test");
        let n = bag.add("count", 3u32, "how many").unwrap();
        let pid = bag.bag("pid", "gains").unwrap();
        let kp = pid.add("kp", 1.0, "p gain").unwrap();
        let lim = pid
            .add(
                "limits",
                Limits {
                    low: -1.0,
                    high: 1.0,
                },
                "clamp",
            )
            .unwrap();
        (bag, n, kp, lim)
    }

    #[test]
    fn load_and_save_round_trip() {
        let (b, n, kp, lim) = bag();
        b.load_toml_str("count = 7\n[pid]\nkp = 0.5\nlimits = { low = -2.0, high = 2.0 }\n")
            .unwrap();
        assert_eq!((n.get(), kp.get()), (7, 0.5));
        assert_eq!(
            lim.get(),
            Limits {
                low: -2.0,
                high: 2.0
            }
        );
        let saved = toml::to_string(&b.to_toml()).unwrap();
        let (b2, n2, kp2, lim2) = bag();
        b2.load_toml_str(&saved).unwrap();
        assert_eq!((n2.get(), kp2.get(), lim2.get()), (7, 0.5, lim.get()));
    }

    #[test]
    fn errors_name_key_paths_and_change_nothing() {
        let (b, n, kp, _) = bag();
        let err = b
            .load_toml_str(
                "count = 9\nspeed = 1\n[pid]\nkp = \"x\"\nki = 2\nlimits = { low = 0.0 }\n",
            )
            .unwrap_err();
        let text = err.to_string();
        for want in [
            "no property \"speed\"",
            "pid.kp: expected f64: invalid type: string \"x\", expected f64",
            "no property \"pid.ki\"; there are: kp, limits",
            "pid.limits: expected",
            "missing field `high`",
        ] {
            assert!(text.contains(want), "missing {want:?} in:\n{text}");
        }
        assert_eq!(
            (n.get(), kp.get()),
            (3, 1.0),
            "an invalid file changes nothing"
        );
        let err = b.load_toml_str("pid = 3").unwrap_err();
        assert_eq!(
            err.to_string(),
            "pid: expected a table of properties, found integer"
        );
    }

    #[test]
    fn dynamic_get_set_and_list() {
        let (b, _, kp, _) = bag();
        b.set_value("pid.kp", serde_json::json!(4.0)).unwrap();
        assert_eq!(kp.get(), 4.0);
        assert_eq!(b.get_value("pid.kp").unwrap(), serde_json::json!(4.0));
        let e = b
            .set_value("pid.kp", serde_json::json!("fast"))
            .unwrap_err();
        assert!(matches!(e, PropertyError::WrongType { .. }), "{e}");
        let e = b.get_value("pid.kd").unwrap_err();
        assert_eq!(
            e.to_string(),
            "no property \"pid.kd\"; there are: count, pid.kp, pid.limits"
        );
        assert!(b.get_value("pid").is_err(), "a bag is not a value");
        let paths: Vec<String> = b.list().into_iter().map(|i| i.path).collect();
        assert_eq!(paths, vec!["count", "pid.kp", "pid.limits"]);
        assert!(b.add("count", 1u8, "again").is_err());
    }
}
