-- test_one_transition.lua — at most one transition per update: a chain a→b→c→d whose
-- guards are all true moves one state per update (manual L3333–3336), in automatic mode,
-- and one state per step() in reactive mode.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local function eq(a, b, what)
  if a ~= b then
    error(what .. ":\n expected " .. tostring(b) .. "\n      got " .. tostring(a), 2)
  end
end

local entries = {}
local function entered(m) entries[#entries + 1] = m:get_state() end
local yes = function() return true end

local function chain()
  return statemachine {
    name = "chain", initial = "a", final = "d",
    states = {
      a = { entry = entered, transitions = { { guard = yes, to = "b" } } },
      b = { entry = entered, transitions = { { guard = yes, to = "c" } } },
      c = { entry = entered, transitions = { { to = "d" } } },
      d = { entry = entered },
    },
  }
end

-- Automatic mode.
local m = chain()
eq(m:get_state(), nil, "inactive machine's state")
eq(m:is_active(), false, "is_active before start")
m:start()
eq(m:get_state(), "a", "after start")
eq(m:is_running(), true, "is_running after start")
eq(#entries, 1, "entries after start")
m:update()
eq(m:get_state(), "b", "after update 1")
m:update()
eq(m:get_state(), "c", "after update 2")
m:update()
eq(m:get_state(), "d", "after update 3")
m:update()
eq(m:get_state(), "d", "after update 4 (d has no transitions)")
eq(table.concat(entries, ","), "a,b,c,d", "entries")

-- Reactive mode: update() takes no transition, step() takes exactly one.
entries = {}
local r = chain()
r:activate()
eq(r:is_reactive(), true, "is_reactive after activate")
r:update()
r:update()
eq(r:get_state(), "a", "reactive: update makes no transition")
eq(r:step(), true, "step 1 transition")
eq(r:get_state(), "b", "after step 1")
eq(r:step(), true, "step 2 transition")
eq(r:get_state(), "c", "after step 2")
eq(table.concat(entries, ","), "a,b,c", "reactive entries")

-- A hook that requests a transition itself counts as this update's one transition.
local log = {}
local h = statemachine {
  initial = "a", final = "z",
  states = {
    a = { run = function(m) log[#log + 1] = "run a"; m:request_state("z") end,
          transitions = { { to = "b" } } },
    b = {},
    z = { entry = function() log[#log + 1] = "entry z" end,
          transitions = { { to = "b" } } },
  },
}
h:start()
h:update()
eq(h:get_state(), "z", "state after run requested z")
eq(table.concat(log, ","), "run a,entry z", "no second transition in that update")
h:update()
eq(h:get_state(), "b", "next update moves on")
