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
const LEFT_OUT: &str = r##"
local function refuse(what)
  return function() error(what .. " is not available in a script (the sandbox: no processes, no files outside data_dir, no native modules)", 2) end
end
dofile = refuse("dofile")
loadfile = refuse("loadfile")
require = refuse("require")
string.dump = refuse("string.dump")
do
  local text_load = load
  -- Text chunks only: binary chunks can break the interpreter. The environment is passed
  -- on only when given (a fourth argument, even nil, would be the chunk's _ENV).
  load = function(chunk, name, mode, ...)
    if mode ~= nil and mode ~= "t" then error("load: only text chunks (mode \"t\") in a script", 2) end
    if select("#", ...) > 0 then return text_load(chunk, name, "t", ...) end
    return text_load(chunk, name, "t")
  end
end
do
  -- A call stopped for its time stays stopped: pcall, xpcall and coroutine.resume give
  -- the error back to their caller's caller once the time is past, so no loop of
  -- protected calls outlives the deadline.
  local overran = __hwgw_overran
  local function pass(ok, ...)
    if overran() then error("stopped: it ran past its time", 0) end
    return ok, ...
  end
  local raw_pcall, raw_xpcall, raw_resume = pcall, xpcall, coroutine.resume
  pcall = function(...) return pass(raw_pcall(...)) end
  xpcall = function(...) return pass(raw_xpcall(...)) end
  coroutine.resume = function(...) return pass(raw_resume(...)) end
  -- C functions the hook cannot stop: string.rep of nothing many times, and patterns
  -- whose backtracking grows as (subject length)^(quantifiers).
  local raw_rep = string.rep
  string.rep = function(s, n, sep)
    local len = #tostring(s) + #tostring(sep or "")
    if type(n) == "number" and n > 0 and (len == 0 or n > (1 << 40) // len) then
      if len == 0 then return "" end
      error("string.rep: " .. tostring(n) .. " copies do not fit a script's memory", 2)
    end
    return raw_rep(s, n, sep)
  end
  local raw_gsub, raw_gmatch = string.gsub, string.gmatch
  local function costly(subject, pattern, plain)
    if plain or type(pattern) ~= "string" or type(subject) ~= "string" then return end
    local q = 0
    for _ in raw_gmatch((raw_gsub(pattern, "%%.", "")), "[%*%-%+%?]") do q = q + 1 end
    if q >= 2 and q * math.log(math.max(#subject, 2), 10) > 8 then
      error(string.format("pattern with %d quantifiers over %d characters: too costly for a script", q, #subject), 3)
    end
  end
  for _, f in ipairs({ "find", "match", "gmatch", "gsub" }) do
    local raw = string[f]
    string[f] = function(s, p, a, plain)
      costly(s, p, f == "find" and plain)
      return raw(s, p, a, plain)
    end
  end
  -- No finalizers: they would run outside any step's time (in the collector, at close).
  local raw_setmetatable = setmetatable
  setmetatable = function(t, mt)
    if type(mt) == "table" and rawget(mt, "__gc") ~= nil then
      error("setmetatable: __gc is not available in a script (finalizers run outside its time)", 2)
    end
    return raw_setmetatable(t, mt)
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
__hwgw_time, __hwgw_clock, __hwgw_overran = nil, nil, nil
"##;

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
        let deadline = Arc::new(AtomicU64::new(0));
        let overran = Arc::new(AtomicBool::new(false));
        let o = overran.clone();
        g.set(
            "__hwgw_overran",
            lua.create_function(move |_, ()| Ok(o.load(Ordering::Relaxed)))?,
        )?;
        lua.load(LEFT_OUT).set_name("=hwgw/sandbox").exec()?;
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

    /// What tells how long the call under way may still take.
    pub fn deadline(&self) -> Deadline {
        Deadline {
            due: self.deadline.clone(),
            epoch: self.epoch,
        }
    }

    /// Whether the last armed call was stopped by its deadline.
    pub fn overran(&self) -> bool {
        self.overran.load(Ordering::Relaxed)
    }
}

/// How long the call into the script under way may still take.
#[derive(Clone)]
pub struct Deadline {
    due: Arc<AtomicU64>,
    epoch: Instant,
}

impl Deadline {
    /// The time left, `None` when the call has no deadline.
    pub fn remaining(&self) -> Option<Duration> {
        match self.due.load(Ordering::Relaxed) {
            0 => None,
            due => Some(Duration::from_nanos(
                due.saturating_sub(self.epoch.elapsed().as_nanos() as u64),
            )),
        }
    }
}
