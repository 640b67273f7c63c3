-- test_reactive.lua — reactive mode (manual L3359–3385, L3892–3983): update() makes no
-- transition by itself; request_state() is checked against the current state's
-- transitions and performed at once; step() takes the best transition; stop(), reset(),
-- deactivate(); pause() and a paused step().
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local function eq(a, b, what)
  if a ~= b then
    error(what .. ":\n expected " .. tostring(b) .. "\n      got " .. tostring(a), 2)
  end
end


-- Checks that `err` points at a line of this file and contains `needle`.
local function raised_here(err, needle)
  if not (tostring(err):find("test_reactive.lua:%d+:") and tostring(err):find(needle, 1, true)) then
    error("expected an error at a line of this file with «" .. needle .. "», got: "
      .. tostring(err), 2)
  end
end

local log = {}
local function hooks(name, extra)
  local s = extra or {}
  for _, h in ipairs({ "entry", "run", "handle", "exit" }) do
    s[h] = function() log[#log + 1] = name .. "." .. h end
  end
  return s
end
local function take()
  local s = table.concat(log, ", ")
  log = {}
  return s
end

local m = statemachine {
  name = "x", initial = "y", final = "exit",
  vars = { some = false, other = false },
  states = {
    -- the manual's example, L3894–3922
    y = hooks("y", { transitions = {
      { guard = function(m) return m.vars.some end, to = "z",
        program = function() log[#log + 1] = "y->z" end },
      { guard = function(m) return m.vars.other end, to = "exit" },
    } }),
    z = hooks("z", { transitions = { { to = "ok_1" } } }),
    ok_1 = hooks("ok_1"),
    exit = hooks("exit"),
  },
}

local ok, why = m:request_state("z")
eq(ok, false, "request on an inactive machine")
eq(why, 'statemachine "x" is not active', "reason inactive")

m:activate()
eq(take(), "y.entry, y.run", "activate: initial entry, then run once")
eq(m:is_reactive(), true, "reactive")
for _ = 1, 3 do m:update() end
eq(take(), "", "reactive: update does nothing without events or requests")
eq(m:get_state(), "y", "still y")

ok, why = m:request_state("ok_1")
eq(ok, false, "no transition y -> ok_1")
eq(why, 'state "y" has no transition to "ok_1"', "reason no transition")
ok, why = m:request_state("z")
eq(ok, false, "guard false")
eq(why, 'the guard of state "y"\'s transition to "z" is false', "reason guard")
eq(take(), "", "refused requests run nothing")

m.vars.some = true
eq(m:request_state("z"), true, "request granted")
eq(take(), "y->z, y.exit, z.entry, z.run", "performed at once: program, exit, entry, run")
eq(m:get_state(), "z", "in z")

eq(m:request_state("z"), true, "request to the current state")
eq(take(), "z.run", "only run")

eq(m:step(), true, "step takes the best transition")
eq(take(), "z.exit, ok_1.entry, ok_1.run", "step: exit, entry, run once")
eq(m:step(), false, "ok_1 has no transitions")
eq(take(), "ok_1.handle", "step without transition runs handle")

m:stop()
eq(take(), "ok_1.exit, exit.entry, exit.run", "stop: to the final state")
eq(m:in_state("exit"), true, "in_state final")
m:stop()
eq(take(), "", "stop in the final state: nothing")

m:reset()
eq(take(), "exit.exit, y.entry, y.run", "reset: final exit, initial entry")
local okr, err = pcall(function() m:reset() end)
eq(okr, false, "reset outside the final state")
raised_here(err, 'reset() needs the final state "exit"')

eq(m:request_state("exit"), true, "the final state can always be requested")
eq(take(), "y.exit, exit.entry, exit.run", "request final")
m:reset()
take()

-- step() in automatic mode is a mistake; pause() makes step() one automatic step.
m:start()
eq(m:is_running(), true, "automatic")
okr, err = pcall(function() m:step() end)
eq(okr, false, "step while automatic")
raised_here(err, "step() is for reactive or paused mode")
m:pause()
eq(m:is_paused(), true, "paused")
m:update()
eq(take(), "", "paused: update does nothing")
eq(m:step(), true, "paused step: one automatic step, y -> z (vars.some still true)")
eq(take(), "y.run, y->z, y.exit, z.entry", "automatic step: run, transition; no run after entry")
eq(m:is_paused(), true, "still paused")
eq(m:step(), true, "paused step 2")
eq(take(), "z.run, z.exit, ok_1.entry", "second paused step")
m:reactive()
eq(m:is_reactive(), true, "reactive again")
m:update()
eq(take(), "", "reactive")

-- deactivate: the current state's exit, then inactive.
m:deactivate()
eq(take(), "ok_1.exit", "deactivate runs exit")
eq(m:is_active(), false, "inactive")
eq(m:get_state(), nil, "no state when inactive")
m:deactivate()
eq(take(), "", "deactivate twice: nothing")
for _, op in ipairs({ "pause", "reactive", "step", "stop", "reset" }) do
  okr, err = pcall(function() m[op](m) end)
  eq(okr, false, op .. " on an inactive machine")
  assert(err:find(op .. "() needs an active machine", 1, true), err)
end

-- Mistakes: unknown states, dot instead of colon.
okr, err = pcall(function() m:activate(); m:request_state("zz") end)
eq(okr, false, "unknown state requested")
raised_here(err, 'no state "zz"; states are: exit, ok_1, y, z')
okr, err = pcall(function() return m:in_state("Y") end)
eq(okr, false, "in_state with an unknown state")
okr, err = pcall(function() m.update() end)
eq(okr, false, "m.update()")
raised_here(err, "update must be called as m:update(...)")
