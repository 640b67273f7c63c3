//! Property files: a component's properties read from TOML files (the manual's
//! readProperties/writeProperties, seed 000 L1881–1920 on the deployment component's
//! property files): `properties_file = ["base.toml", "site.toml"]` on a `[[component]]`,
//! applied in order before its inline `properties`, every error located in the file that
//! has it; and the files `hwgw save-properties` writes — whole, atomically, a new file
//! unless asked to replace one.

use crate::problems::{KeyPath, Problem, Problems, Source};
use rtt::TaskContext;
use rtt::property::PropertyError;
use std::io::Read;
use std::path::Path;

/// The largest property file read: a mistaken path to something huge is an error, not
/// memory.
pub const MAX_BYTES: u64 = 1 << 20;

/// Reads a property file of at most [`MAX_BYTES`].
pub fn read(path: &Path) -> Result<String, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut text = String::new();
    file.take(MAX_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if text.len() as u64 > MAX_BYTES {
        return Err(format!(
            "{}: larger than {} KiB: not a property file",
            path.display(),
            MAX_BYTES / 1024
        ));
    }
    Ok(text)
}

/// Every error of a load, one by one.
fn each(e: PropertyError) -> Vec<PropertyError> {
    match e {
        PropertyError::Many(list) => list.into_iter().flat_map(each).collect(),
        e => vec![e],
    }
}

/// The property path an error is about, if any.
fn path_of(e: &PropertyError) -> Option<&str> {
    match e {
        PropertyError::NotFound { path, .. }
        | PropertyError::WrongType { path, .. }
        | PropertyError::Shape { path, .. } => Some(path),
        _ => None,
    }
}

/// Loads property file `path` into `task`'s properties, all or nothing; a problem at `at`
/// (the deployment's key naming the file) when it cannot be read, else each in the file at
/// its key. Whether it loaded.
pub(crate) fn load(task: &TaskContext, path: &Path, at: &KeyPath, problems: &mut Problems) -> bool {
    let text = match read(path) {
        Ok(t) => t,
        Err(e) => {
            problems.at(at, e);
            return false;
        }
    };
    let label = path.display().to_string();
    let source = Source::new(&label, &text);
    let table: toml::Table = match text.parse() {
        Ok(t) => t,
        Err(e) => {
            let e: toml::de::Error = e;
            let location = e.span().map(|s| source.locate_offset(s.start));
            problems.add(Problem::new(location, "", e.message()));
            return false;
        }
    };
    match task.properties().load_toml(&table) {
        Ok(()) => true,
        Err(e) => {
            for e in each(e) {
                let path = path_of(&e).unwrap_or("");
                let key = KeyPath::root().join(path);
                // A name that is no property: at the name; a wrong value: at the value.
                let at = if matches!(e, PropertyError::NotFound { .. }) {
                    source.locate_key(&key)
                } else {
                    source.locate(&key)
                };
                problems.add(Problem::new(at, path, &e.to_string()));
            }
            false
        }
    }
}
