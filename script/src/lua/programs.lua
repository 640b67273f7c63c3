-- programs.lua — hwgw's script component: programs, after Orocos RTT 1.x program scripts.
--
-- Loaded by the script component (first, before fsm.lua and the user's script) into a
-- sandboxed Lua 5.4 state that has only the base, table, string, math, coroutine and utf8
-- libraries. Running this chunk defines these globals:
--
--   program(name, fn)    registers a program; `fn` becomes a coroutine when started
--   yield()              inside a program: wait one step
--   wait(handle)         inside a program: wait for an operation handle, return its result
--   wait_until(fn)       inside a program: wait until fn() is true
--   sleep(seconds)       inside a program: wait until the host's now() has advanced
--   programs             start/pause/step/stop/inspect programs by name; programs._step()
--                        is the host's once-per-step entry point
--
-- Semantics follow the RTT 1.x manual (/work/shared/seeds/000_237df74429c13ddb.txt):
-- L2159–2263 (a loaded program is started, paused, stepped and stopped by name, and
-- inspected with isRunning, inError, isPaused: L2173–2210) and L3017–3321 (statements
-- run one after the other until one has to wait, which postpones the program to the next
-- execution period, L3019–3030; a run-time error puts the program in the error state and
-- stops it, L3042–3046; the 'nothing' command waits exactly one step, L3289–3295, here
-- yield(); start/pause/step/stop from another script, L3297–3321). A program is a Lua
-- function run as a coroutine: everything between two waits runs within one step.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local registry = {} -- name -> program object
local order = {}    -- program objects in registration order (the order _step runs them)
local current = nil -- the coroutine being resumed by resume() right now
local failures = {} -- {name=, error=} since the last programs._step() returned

local Program = {}
Program.__index = Program

-- Lists the names of the known programs for error messages: "a, b" or "none".
local function known_names()
  local names = {}
  for name in pairs(registry) do names[#names + 1] = name end
  table.sort(names)
  if #names == 0 then return "none" end
  return table.concat(names, ", ")
end

-- Finds a program by name; `level` is the error level of the caller's caller.
local function lookup(name, level)
  local p = registry[name]
  if p == nil then
    error(string.format("no program %q; this script has: %s", tostring(name), known_names()),
      level + 1)
  end
  return p
end

-- Drops a program's coroutine. A suspended one is closed so that its pending
-- to-be-closed variables are closed; the one running now (a program stopping itself)
-- cannot be closed and is simply forgotten: its yield ends it.
local function drop(p)
  local co = p.co
  p.co = nil
  if co ~= nil and coroutine.status(co) == "suspended" then coroutine.close(co) end
end

-- Resumes p's coroutine once. On return: finished -> "stopped"; raised -> "error" with the
-- message kept (Lua puts "file:line:" in front of a string raised with error(msg)), and the
-- failure is queued for the host's next programs._step(). Returns the error or nil.
local function resume(p)
  local co = p.co
  local outer = current
  current = co
  local ok, err = coroutine.resume(co)
  current = outer
  if p.co ~= co then return nil end -- stopped (or stopped and restarted) while it ran
  if not ok then
    drop(p)
    p.state = "error"
    p.error = tostring(err)
    failures[#failures + 1] = { name = p.name, error = p.error }
    return p.error
  end
  if coroutine.status(co) == "dead" then
    drop(p)
    p.state = "stopped"
  end
  return nil
end

-- Checks that the caller runs inside a program's coroutine (not in a state machine hook,
-- not in the main chunk, not in a coroutine of its own; a program that stopped itself
-- still runs until its next wait). `what` names the function.
local function in_program(what)
  if current == nil or coroutine.running() ~= current then
    error(what .. " can only be used inside a program (state machine hooks and the main "
      .. "chunk must not wait; poll instead)", 3)
  end
end

-- Waits one step (the manual's 'nothing' command, L3289–3295).
function yield()
  in_program("yield()")
  coroutine.yield()
end

-- Waits for an operation handle: polls handle:collect_if_done() now and then once per step.
-- It returns nothing/nil while pending, `true, result...` when done or `false, errmsg` when
-- the operation failed; wait returns the results or raises errmsg at the caller's line.
function wait(handle)
  in_program("wait()")
  local ht = type(handle)
  local okm, collect = pcall(function() return handle.collect_if_done end)
  if (ht ~= "table" and ht ~= "userdata") or not okm or collect == nil then
    error("wait() needs an operation handle (a value with a collect_if_done method), got "
      .. ht, 2)
  end
  while true do
    local r = table.pack(collect(handle))
    if r[1] == true then
      return table.unpack(r, 2, r.n)
    elseif r[1] == false then
      error(r[2], 2)
    end
    coroutine.yield()
  end
end

-- Waits until fn() returns a true value; checks it now, then once per step.
function wait_until(fn)
  in_program("wait_until()")
  if type(fn) ~= "function" then
    error("wait_until() needs a function, got " .. type(fn), 2)
  end
  while not fn() do coroutine.yield() end
end

-- Waits until the host's clock, the global now() in seconds, has advanced by `seconds`.
-- Returns at once when seconds <= 0; otherwise checks once per step.
function sleep(seconds)
  in_program("sleep()")
  if type(seconds) ~= "number" then
    error("sleep() needs a number of seconds, got " .. type(seconds), 2)
  end
  if type(now) ~= "function" then
    error("sleep() needs the host's now() function, which is not defined", 2)
  end
  local deadline = now() + seconds
  while now() < deadline do coroutine.yield() end
end

-- Registers a program. It does not run until programs.start(name).
function program(name, fn)
  if type(name) ~= "string" or name == "" then
    error("program() needs a name (a non-empty string) first, got " .. type(name), 2)
  end
  if type(fn) ~= "function" then
    error(string.format("program %q needs a function, got %s", name, type(fn)), 2)
  end
  if registry[name] ~= nil then
    error(string.format("program %q is already defined", name), 2)
  end
  local p = setmetatable({ name = name, fn = fn, state = "stopped", co = nil, error = nil },
    Program)
  registry[name] = p
  order[#order + 1] = p
  return p
end

programs = {}

-- stopped or error: a fresh coroutine, running; paused: running again; running: nothing.
-- A program started during a step is first resumed at the next programs._step().
function programs.start(name)
  local p = lookup(name, 2)
  if p.state == "stopped" or p.state == "error" then
    drop(p)
    p.co = coroutine.create(p.fn)
    p.error = nil
  end
  p.state = "running"
end

-- running -> paused (paused: nothing). Pausing a stopped or failed program is an error.
function programs.pause(name)
  local p = lookup(name, 2)
  if p.state ~= "running" and p.state ~= "paused" then
    error(string.format("program %q is %s, not running", name, p.state), 2)
  end
  p.state = "paused"
end

-- When paused: resumes the program exactly once (one piece between two waits) and leaves it
-- paused, unless it finished ("stopped") or raised ("error"). Returns the state after the
-- step and, on error, the message (which the next programs._step() also reports).
function programs.step(name)
  local p = lookup(name, 2)
  if p.state ~= "paused" then
    error(string.format("program %q is %s, not paused", name, p.state), 2)
  end
  if coroutine.status(p.co) ~= "suspended" then
    error(string.format("program %q is running now (a program cannot step itself)", name), 2)
  end
  local err = resume(p)
  return p.state, err
end

-- Any state -> stopped; the coroutine is dropped and the error, if any, forgotten.
function programs.stop(name)
  local p = lookup(name, 2)
  drop(p)
  p.state = "stopped"
  p.error = nil
end

function programs.is_running(name) return lookup(name, 2).state == "running" end
function programs.is_paused(name) return lookup(name, 2).state == "paused" end
function programs.in_error(name) return lookup(name, 2).state == "error" end
function programs.error_of(name) return lookup(name, 2).error end
function programs.state(name) return lookup(name, 2).state end

-- The names of all programs, sorted.
function programs.list()
  local names = {}
  for name in pairs(registry) do names[#names + 1] = name end
  table.sort(names)
  return names
end

-- The host's entry point, once per step: resumes every program that was running when the
-- step began once, in registration order. A program started, restarted or stopped by
-- another program during this step is not resumed in it (the coroutine must be the one
-- seen when the step began); one paused during it is skipped. Never raises for a
-- program's error: returns the list of {name=, error=} of the programs that failed since
-- the previous call (in this step, or through programs.step() in between), else {}.
-- The answer when no program failed: shared, so that a step with nothing to report
-- allocates nothing (the step of a real-time script should not feed the collector).
local NO_FAILURES = setmetatable({}, { __newindex = function() error("read-only", 2) end })

function programs._step()
  local due = nil
  for _, p in ipairs(order) do
    if p.state == "running" then
      due = due or {}
      due[#due + 1] = { p = p, co = p.co }
    end
  end
  for _, d in ipairs(due or NO_FAILURES) do
    local p = d.p
    if p.state == "running" and p.co == d.co and coroutine.status(d.co) == "suspended" then
      resume(p)
    end
  end
  if #failures == 0 then return NO_FAILURES end
  local out = failures
  failures = {}
  return out
end

-- The same operations as methods of the object program() returns: p:start(), p:get_state() …
-- (tail calls, so that their errors point at the caller's line as well).
for _, op in ipairs({ "start", "pause", "step", "stop", "is_running", "is_paused",
  "in_error", "error_of" }) do
  local f = programs[op]
  Program[op] = function(p) return f(p.name) end
end
function Program:get_state() return self.state end
