//! Loading a script into a fresh sandbox: the libraries hwgw ships (programs, state
//! machines, their glue), then the script's file with its ports declared, its hooks
//! found. A script that fails to load leaves nothing behind but the ports it declared
//! (ports stay for the component's life).

use crate::error::{ScriptError, message};
use crate::host::{Host, Requests};
use crate::ports::PortMap;
use crate::sandbox::{STRICT, Sandbox};
use mlua::{Function, Lua};
use rtt::component::SelfRef;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// The libraries, in load order: (chunk name, text).
pub const LIBRARIES: [(&str, &str); 3] = [
    ("=hwgw/programs.lua", include_str!("lua/programs.lua")),
    ("=hwgw/fsm.lua", include_str!("lua/fsm.lua")),
    ("=hwgw/prelude.lua", include_str!("lua/prelude.lua")),
];

/// The most a script's top level may run (an endless loop there is stopped).
pub const LOAD_BUDGET: Duration = Duration::from_secs(2);

/// The least memory a script may be given (its libraries take about 100 KiB).
pub const MIN_MEMORY: usize = 256 << 10;

/// The largest script file read.
pub const MAX_FILE: u64 = 4 << 20;

/// The hooks a script may define, as the names it defines them under.
pub const HOOKS: [&str; 6] = [
    "configure",
    "start",
    "update",
    "stop",
    "cleanup",
    "error_update",
];

/// A loaded script.
pub struct Loaded {
    /// Its state.
    pub sandbox: Sandbox,
    /// The hooks it defines, in [`HOOKS`] order.
    pub hooks: [Option<Function>; 6],
    /// The per-step entry point (programs, machine).
    pub step: Function,
    /// Set when a call asked something of the error model (the host's `ask`).
    pub asked: Arc<std::sync::atomic::AtomicBool>,
    /// The time a call may take, as the properties said at load (a script cannot lift
    /// it by setting them).
    pub budget: Option<Duration>,
    /// Its memory limit, bytes.
    pub memory: usize,
}

/// What a load needs.
pub struct Setup<'a> {
    /// The component's name.
    pub name: &'a str,
    /// The script's path as the deployment gives it (its chunk name: errors say it).
    pub file: &'a str,
    /// The folder a relative `file` and `data_dir` are found in.
    pub base_dir: &'a Path,
    /// The folder `io.open` reaches, if any.
    pub data_dir: Option<PathBuf>,
    /// Values passed in, as `vars`.
    pub vars: &'a serde_json::Value,
    /// Lua memory, bytes.
    pub memory: usize,
    /// The component, for ports and peers.
    pub me: SelfRef,
    /// Its ports.
    pub ports: PortMap,
    /// The registry.
    pub registry: Arc<device_interface::Registry>,
    /// The time a call into the script may take (`max_step_us`; none: no limit and no
    /// instruction hook once loaded).
    pub budget: Option<Duration>,
}

/// `file` resolved against `base`.
pub fn resolve(base: &Path, file: &str) -> PathBuf {
    let p = Path::new(file);
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        base.join(p)
    }
}

fn read(path: &Path) -> Result<String, ScriptError> {
    use std::io::Read;
    let err = |source| ScriptError::Read {
        path: path.display().to_string(),
        source,
    };
    let f =
        crate::files::open_regular(std::fs::OpenOptions::new().read(true), path, 0).map_err(err)?;
    let mut text = String::new();
    f.take(MAX_FILE + 1)
        .read_to_string(&mut text)
        .map_err(err)?;
    if text.len() as u64 > MAX_FILE {
        return Err(err(std::io::Error::other(format!(
            "larger than {MAX_FILE} bytes"
        ))));
    }
    Ok(text)
}

/// Loads the script: a syntax error, an error at its top level (an undefined name
/// called there among them) or a port it cannot have is an error with the script's
/// file:line.
pub fn load(s: Setup<'_>) -> Result<Loaded, ScriptError> {
    if s.file.is_empty() {
        return Err(ScriptError::Property {
            name: "file",
            detail: "empty: name the Lua script to run".into(),
        });
    }
    if s.memory < MIN_MEMORY {
        return Err(ScriptError::Property {
            name: "memory_kb",
            detail: format!(
                "{} KiB is less than the {} KiB a script's libraries need",
                s.memory / 1024,
                MIN_MEMORY / 1024
            ),
        });
    }
    let path = resolve(s.base_dir, s.file);
    let text = read(&path)?;
    let sandbox = Sandbox::new(s.memory).map_err(|e| ScriptError::lua(&e))?;
    let lua = &sandbox.lua;
    let asked = Arc::new(std::sync::atomic::AtomicBool::new(false));
    lua.set_app_data(Host {
        name: s.name.to_string(),
        me: s.me,
        ports: s.ports,
        declaring: true,
        requests: Requests::default(),
        asked: asked.clone(),
        deadline: sandbox.deadline(),
        registry: s.registry,
        data_dir: s.data_dir,
    });
    let lua_err = |e: mlua::Error| ScriptError::lua(&e);
    crate::api::install(lua, s.vars).map_err(lua_err)?;
    for (name, lib) in LIBRARIES {
        lua.load(lib).set_name(name).exec().map_err(lua_err)?;
    }
    lua.load(STRICT)
        .set_name("=hwgw/strict")
        .exec()
        .map_err(lua_err)?;
    sandbox.arm(Some(LOAD_BUDGET));
    let ran = lua.load(&text).set_name(format!("@{}", s.file)).exec();
    sandbox.disarm();
    if let Some(mut h) = lua.app_data_mut::<Host>() {
        h.declaring = false;
    }
    ran.map_err(|e| {
        if sandbox.overran() {
            ScriptError::Lua(format!(
                "{}: its top level ran past {} s and was stopped",
                s.file,
                LOAD_BUDGET.as_secs()
            ))
        } else {
            ScriptError::Lua(message(&e))
        }
    })?;
    let hooks = hooks(lua, s.file)?;
    let step: Function = lua.globals().raw_get("__hwgw_step").map_err(lua_err)?;
    // From here on the collector runs between steps, in steps the component sizes.
    lua.gc_stop();
    if s.budget.is_none() {
        // No instruction hook: every instruction runs without the hook's check (see
        // the benchmark), and nothing stops an endless loop.
        lua.remove_hook();
    }
    Ok(Loaded {
        sandbox,
        hooks,
        step,
        asked,
        budget: s.budget,
        memory: s.memory,
    })
}

fn hooks(lua: &Lua, file: &str) -> Result<[Option<Function>; 6], ScriptError> {
    let g = lua.globals();
    let mut out: [Option<Function>; 6] = Default::default();
    for (slot, name) in out.iter_mut().zip(HOOKS) {
        match g
            .raw_get::<mlua::Value>(name)
            .map_err(|e| ScriptError::lua(&e))?
        {
            mlua::Value::Nil => {}
            mlua::Value::Function(f) => *slot = Some(f),
            other => {
                return Err(ScriptError::Lua(format!(
                    "{file}: {name} is a {}; a hook is a function",
                    other.type_name()
                )));
            }
        }
    }
    Ok(out)
}
