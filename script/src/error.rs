//! What goes wrong with a script, named with its file (and line, where Lua knows it).

use thiserror::Error;

/// A script error.
#[derive(Debug, Error)]
pub enum ScriptError {
    /// The file could not be read.
    #[error("script {path}: {source}")]
    Read {
        /// The path as resolved.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// Lua refused or raised: a syntax error, an error at top level or in a hook (the
    /// message carries the script's file:line).
    #[error("{0}")]
    Lua(String),
    /// A port the script declared that cannot be.
    #[error("port {port:?}: {detail}")]
    Port {
        /// The port's name.
        port: String,
        /// Why.
        detail: String,
    },
    /// A property with a value that does not work.
    #[error("property {name}: {detail}")]
    Property {
        /// The property.
        name: &'static str,
        /// Why.
        detail: String,
    },
}

impl ScriptError {
    /// A Lua error as one readable message: the script's own message (with its
    /// file:line), and for an error inside a callback the cause, without mlua's wrapping.
    pub fn lua(e: &mlua::Error) -> ScriptError {
        ScriptError::Lua(message(e))
    }
}

/// The message of a Lua error, without the traceback mlua appends.
pub fn message(e: &mlua::Error) -> String {
    match e {
        mlua::Error::RuntimeError(m) | mlua::Error::SyntaxError { message: m, .. } => {
            // Lua's message, without the traceback mlua appends.
            m.split("\nstack traceback:")
                .next()
                .unwrap_or(m)
                .to_string()
        }
        mlua::Error::MemoryError(m) => format!("out of memory (memory_kb): {m}"),
        mlua::Error::CallbackError { cause, traceback } => {
            // The line the script was at is the traceback's first frame in a script file.
            let at = traceback
                .lines()
                .map(str::trim)
                .find(|l| l.ends_with(".lua") || l.contains(".lua:"))
                .and_then(|l| l.split(": in ").next())
                .map(|l| format!("{l}: "))
                .unwrap_or_default();
            format!("{at}{}", message(cause))
        }
        mlua::Error::WithContext { context, cause } => format!("{context}: {}", message(cause)),
        other => other.to_string(),
    }
}
