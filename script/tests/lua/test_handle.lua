-- test_handle.lua — run comes first in every automatic step, then the transitions in
-- order; handle runs only when none is taken (manual L3338–3343, L3401–3406, L3517–3548).
-- A transition without a target stays in the state: neither exit nor entry, no handle.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local function eq(a, b, what)
  if a ~= b then
    error(what .. ":\n expected " .. tostring(b) .. "\n      got " .. tostring(a), 2)
  end
end

local log = {}
local function say(s) return function() log[#log + 1] = s end end
local function take()
  local s = table.concat(log, ", ")
  log = {}
  return s
end

local m = statemachine {
  initial = "a", final = "z",
  vars = { go = false, tick = false, seen_by_guard = nil },
  states = {
    a = {
      entry = say("a.entry"), exit = say("a.exit"), handle = say("a.handle"),
      run = function(m) log[#log + 1] = "a.run"; m.vars.ran = true end,
      transitions = {
        -- the guard sees what run did in the same step: run comes first
        { guard = function(m) log[#log + 1] = "g1"; return m.vars.go and m.vars.ran end,
          to = "b" },
        { guard = function(m) log[#log + 1] = "g2"; return m.vars.tick end,
          program = function(m) log[#log + 1] = "tick"; m.vars.tick = false end },
      },
    },
    b = { entry = say("b.entry"), run = say("b.run"), handle = say("b.handle") },
    z = {},
  },
}

m:start()
eq(take(), "a.entry", "start: entry only, run comes with the first update")
m:update()
eq(take(), "a.run, g1, g2, a.handle", "no transition: run, guards in order, handle")
m:update()
eq(take(), "a.run, g1, g2, a.handle", "again")

m.vars.tick = true
m:update()
eq(take(), "a.run, g1, g2, tick", "a program-only transition: no exit/entry, no handle")
eq(m:get_state(), "a", "stays in a")

m.vars.go = true
m:update()
eq(take(), "a.run, g1, a.exit, b.entry", "transition taken: no handle, later guards not evaluated")
m:update()
eq(take(), "b.run, b.handle", "b has no transitions: run then handle")

-- Reactive step(): no transition possible -> handle, and run is not repeated.
local r = statemachine {
  initial = "a", final = "z",
  states = {
    a = { run = say("a.run"), handle = say("a.handle"),
          transitions = { { guard = function() return false end, to = "z" } } },
    z = {},
  },
}
r:activate()
eq(take(), "a.run", "activate: entry then run once (reactive)")
r:update()
eq(take(), "", "reactive update: nothing")
eq(r:step(), false, "step without a valid transition")
eq(take(), "a.handle", "step runs handle only")
