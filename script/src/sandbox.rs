//! The Lua state a script runs in, and what bounds it: only the base, table, string,
//! math, coroutine and utf8 libraries (no `os`, `io`, `package`, `debug`, no native
//! modules, no binary chunks); what is left out says so when a script reaches for it; a
//! memory limit (`memory_kb`: exceeding it is a Lua error, never an abort); an
//! instruction-count hook that stops a call running past its deadline (`max_step_us`);
//! undefined globals as errors (a misspelt name fails where it is used, with its line);
//! the garbage collector stopped while Lua runs and stepped between steps by the component.

use mlua::{HookTriggers, Lua, LuaOptions, StdLib, VmState};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// Instructions between two looks at the clock: ~10 µs of Lua at most between looks.
const HOOK_EVERY: u32 = 1000;

/// A fresh, bounded Lua state.
pub struct Sandbox {
    /// The state.
    pub lua: Lua,
    deadline: Arc<AtomicU64>,
    overran: Arc<AtomicBool>,
    epoch: Instant,
}

/// The names a script may miss: each raises an error that says why it is not there.
const LEFT_OUT: &str = r#"
local function refuse(what)
  return function() error(what .. " is not available in a script (the sandbox: no processes, no files outside data_dir, no native modules)", 2) end
end
dofile = refuse("dofile")
loadfile = refuse("loadfile")
require = refuse("require")
string.dump = refuse("string.dump")
do
  local text_load = load
  -- Text chunks only: binary chunks can break the interpreter.
  load = function(chunk, name, mode, env)
    if mode ~= nil and mode ~= "t" then error("load: only text chunks (mode \"t\") in a script", 2) end
    return text_load(chunk, name, "t", env)
  end
end
do
  local gc = collectgarbage
  -- The component runs the collector between steps; a script may only look.
  collectgarbage = function(opt)
    if opt == "count" then return gc("count") end
    error("collectgarbage(" .. tostring(opt) .. "): the collector is the component's (gc_step_kb); only \"count\" is allowed", 2)
  end
end
local function strict(name, t)
  return setmetatable(t, { __index = function(_, k)
    error(name .. "." .. tostring(k) .. " is not available in a script (the sandbox)", 2)
  end })
end
os = strict("os", { time = __hwgw_time, clock = __hwgw_clock })
io = strict("io", {})
package = strict("package", {})
debug = strict("debug", { traceback = function(m) return m end })
__hwgw_time, __hwgw_clock = nil, nil
"#;

/// Undefined globals as errors; run after everything the script may use is defined.
pub const STRICT: &str = r#"
setmetatable(_G, {
  __index = function(_, k)
    error("undefined name '" .. tostring(k) .. "'", 2)
  end,
})
"#;

impl Sandbox {
    /// A state with at most `memory_bytes` of Lua memory.
    pub fn new(memory_bytes: usize) -> mlua::Result<Sandbox> {
        let libs = StdLib::TABLE | StdLib::STRING | StdLib::MATH | StdLib::COROUTINE | StdLib::UTF8;
        let lua = Lua::new_with(libs, LuaOptions::default())?;
        let epoch = Instant::now();
        let g = lua.globals();
        g.set(
            "__hwgw_time",
            lua.create_function(|_, ()| {
                Ok(std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_secs() as i64)
                    .unwrap_or(0))
            })?,
        )?;
        g.set(
            "__hwgw_clock",
            lua.create_function(move |_, ()| Ok(epoch.elapsed().as_secs_f64()))?,
        )?;
        lua.load(LEFT_OUT).set_name("=hwgw/sandbox").exec()?;
        let deadline = Arc::new(AtomicU64::new(0));
        let overran = Arc::new(AtomicBool::new(false));
        let (d, o) = (deadline.clone(), overran.clone());
        // Coroutines made from Lua inherit the hook of the thread that made them.
        lua.set_hook(
            HookTriggers::new().every_nth_instruction(HOOK_EVERY),
            move |_, debug| {
                let due = d.load(Ordering::Relaxed);
                if due != 0 && epoch.elapsed().as_nanos() as u64 > due {
                    o.store(true, Ordering::Relaxed);
                    let src = debug.source();
                    let file = src.short_src.as_deref().unwrap_or("?").to_string();
                    let line = debug.current_line().unwrap_or(0);
                    return Err(mlua::Error::runtime(format!(
                        "{file}:{line}: stopped there: it ran past its time"
                    )));
                }
                Ok(VmState::Continue)
            },
        )?;
        lua.set_memory_limit(memory_bytes)?;
        // Incremental mode, stopped while Lua runs: the component steps it between steps.
        lua.gc_inc(200, 200, 13);
        Ok(Sandbox {
            lua,
            deadline,
            overran,
            epoch,
        })
    }

    /// Lua running from now on is stopped after `budget` (none: no limit).
    pub fn arm(&self, budget: Option<Duration>) {
        self.overran.store(false, Ordering::Relaxed);
        let due = budget.map_or(0, |b| (self.epoch.elapsed() + b).as_nanos() as u64);
        self.deadline
            .store(due.max(u64::from(budget.is_some())), Ordering::Relaxed);
    }

    /// No deadline.
    pub fn disarm(&self) {
        self.deadline.store(0, Ordering::Relaxed);
    }

    /// Whether the last armed call was stopped by its deadline.
    pub fn overran(&self) -> bool {
        self.overran.load(Ordering::Relaxed)
    }
}
