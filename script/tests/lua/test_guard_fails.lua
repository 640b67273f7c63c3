-- test_guard_fails.lua — a false guard takes no transition and runs the failure program;
-- failure_to then selects its state (manual L3532–3537, L3585–3600); a precondition that
-- does not hold blocks a transition as if its guard were false (L3550–3568).
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

-- A false guard with a failure program only: no transition, the next one is tried.
local m = statemachine {
  initial = "a", final = "z",
  vars = { ok = false },
  states = {
    a = {
      exit = say("a.exit"), handle = say("a.handle"),
      transitions = {
        { guard = function(m) return m.vars.ok end, to = "b", program = say("to b"),
          failure = say("failure 1") },
        { guard = function() return false end, to = "b", failure = say("failure 2"),
          failure_to = "c" },
        { to = "b", program = say("never") },
      },
    },
    b = { entry = say("b.entry") },
    c = { entry = say("c.entry"), handle = say("c.handle") },
    z = {},
  },
}
m:start()
take()
m:update()
eq(take(), "failure 1, failure 2, a.exit, c.entry", "failure programs, then failure_to taken")
eq(m:get_state(), "c", "in c via failure_to")
m:update()
eq(take(), "c.handle", "c: no transitions")

-- Guard true: the failure program does not run.
local n = statemachine {
  initial = "a", final = "z",
  states = {
    a = { exit = say("a.exit"),
          transitions = { { to = "b", program = say("program"), failure = say("failure") } } },
    b = { entry = say("b.entry") },
    z = {},
  },
}
n:start()
n:update()
eq(take(), "program, a.exit, b.entry", "guard true: program, exit, entry")

-- Preconditions.
local allow_b = false
local p = statemachine {
  initial = "a", final = "z",
  states = {
    a = {
      handle = say("a.handle"),
      transitions = {
        { to = "b", failure = say("b blocked") },
        { to = "c", program = say("to c") },
      },
    },
    b = { precondition = function() log[#log + 1] = "b.pre?"; return allow_b end,
          entry = say("b.entry") },
    c = { entry = say("c.entry"), transitions = { { to = "b" } } },
    z = {},
  },
}
p:start()
p:update()
eq(take(), "b.pre?, b blocked, to c, c.entry", "precondition false: failure, next transition")
p:update()
eq(take(), "b.pre?", "c -> b blocked, no failure program, nothing else")
eq(p:get_state(), "c", "still in c")
local ok, why = p:request_state("b")
eq(ok, false, "request blocked by the precondition")
eq(why, 'the precondition of state "b" does not hold', "reason")
take()
allow_b = true
p:update()
eq(take(), "b.pre?, b.entry", "precondition true: entered")

-- failure_to is blocked by its target's precondition as well.
local q = statemachine {
  initial = "a", final = "z",
  states = {
    a = { handle = say("a.handle"),
          transitions = { { guard = function() return false end, to = "z",
                            failure = say("failure"), failure_to = "b" } } },
    b = { precondition = function() return false end, entry = say("b.entry") },
    z = {},
  },
}
q:start()
q:update()
eq(take(), "failure, a.handle", "failure_to blocked: no transition, so handle")
eq(q:get_state(), "a", "still in a")

-- A transition to the current state is always valid (L3545–3548): its precondition
-- is not consulted, and neither exit nor entry runs.
local s = statemachine {
  initial = "a", final = "z",
  states = {
    a = { entry = say("a.entry"), exit = say("a.exit"),
          precondition = function() log[#log + 1] = "a.pre?"; return false end,
          transitions = { { to = "a", program = say("self") } } },
    z = {},
  },
}
s:start()
take()
s:update()
eq(take(), "self", "self transition: program only")
