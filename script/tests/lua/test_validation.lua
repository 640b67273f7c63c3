-- test_validation.lua — statemachine() checks its definition when it is created and
-- raises at the caller's line with a message naming the mistake.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local function eq(a, b, what)
  if a ~= b then
    error(what .. ":\n expected " .. tostring(b) .. "\n      got " .. tostring(a), 2)
  end
end

-- A valid definition to derive broken ones from.
local function good()
  return {
    name = "sup", initial = "idle", final = "stopped",
    states = {
      idle = { entry = function() end, transitions = { { to = "running" } } },
      running = {},
      stopped = {},
    },
  }
end

-- Expects statemachine(def) to fail with every one of `needles` in the message, and the
-- message to point at the line that called statemachine.
local function fails(def, what, ...)
  local ok, err = pcall(function() local m = statemachine(def); return m end)
  eq(ok, false, what .. " must be refused")
  err = tostring(err)
  if not err:find("test_validation.lua:%d+:") then
    error(what .. ": the message does not point at the caller: " .. err, 2)
  end
  for _, needle in ipairs({ ... }) do
    if not err:find(needle, 1, true) then
      error(what .. ": expected «" .. needle .. "» in: " .. err, 2)
    end
  end
end

assert(statemachine(good()), "the good definition is accepted")

fails(nil, "no table", "statemachine() needs a definition table, got nil")
local d = good(); d.inital = "idle"
fails(d, "unknown top-level key", 'statemachine "sup": unknown key "inital"',
  "allowed: final, initial, name, states, submachines, vars")
d = good(); d.states = {}
fails(d, "no states", "needs states =")
d = good(); d.initial = nil
fails(d, "no initial", 'needs initial = "<state name>"')
d = good(); d.initial = "idel"
fails(d, "unknown initial", 'initial: unknown state "idel"; states are: idle, running, stopped')
d = good(); d.final = "stop"
fails(d, "unknown final", 'final: unknown state "stop"; states are: idle, running, stopped')
d = good(); d.states.idle.transitions[1].to = "runing"
fails(d, "unknown to",
  'state "idle", transition 1: to: unknown state "runing"; states are: idle, running, stopped')
d = good()
d.states.idle.transitions[2] = { guard = function() return true end, failure_to = "nowhere",
  to = "idle" }
fails(d, "unknown failure_to", 'state "idle", transition 2: failure_to: unknown state "nowhere"')
d = good(); d.states.idle.transitions[1] = { guard = function() return true end }
fails(d, "neither to nor program",
  'state "idle", transition 1: needs a target state (to = ...) or a transition program')
d = good(); d.states.idle.entyr = function() end
fails(d, "typo in a state", 'state "idle": unknown key "entyr"',
  "allowed: entry, exit, handle, precondition, run, transitions")
d = good(); d.states.idle.transitions[1].gaurd = function() return true end
fails(d, "typo in a transition", 'state "idle", transition 1: unknown key "gaurd"',
  "allowed: event, failure, failure_to, guard, program, to")
d = good(); d.states.running.run = "go"
fails(d, "non-function hook", 'state "running": run must be a function, got string')
d = good(); d.states.running.precondition = true
fails(d, "non-function precondition", "precondition must be a function, got boolean")
d = good(); d.states.idle.transitions[1].guard = true
fails(d, "non-function guard", 'transition 1: guard must be a function, got boolean')
d = good(); d.states.idle.transitions[1].program = {}
fails(d, "non-function program", "program must be a function, got table")
d = good(); d.states.idle.transitions[1].failure = 1
fails(d, "non-function failure", "failure must be a function, got number")
d = good(); d.states.idle.transitions[1].event = 3
fails(d, "bad event", "event must be a name (string) or a port")
d = good(); d.states.idle.transitions[1].event = {}
fails(d, "a table without read is no port", "event must be a name (string) or a port")
d = good(); d.states.idle.transitions = { { to = "running" }, named = { to = "idle" } }
fails(d, "transitions not a list", 'transitions must be a list')
d = good(); d.states.idle.transitions = function() end
fails(d, "transitions not a table", "transitions must be a table, got function")
d = good(); d.states.running = "x"
fails(d, "state not a table", 'state "running" must be a table, got string')
d = good(); d.vars = 3
fails(d, "vars not a table", "vars must be a table")
d = good(); d.submachines = { child = {} }
fails(d, "submachine not a machine", 'submachine "child" must be made by statemachine{...}')
d = good(); d.name = 5
fails(d, "name not a string", "name must be a string")

-- A port event (anything with a read method) and vars are accepted.
d = good()
d.vars = { count = 0 }
d.states.idle.transitions[2] = { event = { read = function() return nil, "none" end },
  to = "stopped" }
local m = statemachine(d)
eq(m.vars, d.vars, "m.vars is the given table")
eq(m.name, "sup", "name")
local unnamed = statemachine({ initial = "a", final = "a", states = { a = {} } })
eq(unnamed.name, "machine", "default name")

-- The error from a misplaced program() and friends points at the caller too.
local ok, err = pcall(function() program(3) end)
eq(ok, false, "program without a name")
assert(err:find("test_validation.lua:%d+: program%(%) needs a name"), err)
ok, err = pcall(function() program("p") end)
eq(ok, false, "program without a function")
assert(err:find('test_validation.lua:%d+: program "p" needs a function, got nil'), err)
