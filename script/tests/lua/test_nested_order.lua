-- test_nested_order.lua — the exact order of entry/exit/run/handle/transition programs
-- across a parent and a sub-machine that the parent starts in a state's entry and stops in
-- its exit (manual L3723–3848): the child's hooks nest inside the parent's, and the child
-- is updated after the parent in the same update.
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

local child = statemachine {
  initial = "c_init", final = "c_final",
  states = {
    c_init = { entry = say("C.init.entry"), run = say("C.init.run"),
               handle = say("C.init.handle"), exit = say("C.init.exit"),
               transitions = { { to = "c_work" } } },
    c_work = { entry = say("C.work.entry"), run = say("C.work.run"),
               handle = say("C.work.handle"), exit = say("C.work.exit") },
    c_final = { entry = say("C.final.entry"), run = say("C.final.run"),
                exit = say("C.final.exit") },
  },
}

local parent = statemachine {
  name = "parent", initial = "idle", final = "done",
  vars = { go = false, leave = false },
  submachines = { child = child },
  states = {
    idle = {
      entry = say("P.idle.entry"), handle = say("P.idle.handle"), exit = say("P.idle.exit"),
      transitions = { { guard = function(m) return m.vars.go end, to = "active",
                        program = say("P.idle->active") } },
    },
    active = {
      entry = function(m)
        log[#log + 1] = "P.active.entry{"
        m.sub.child:start()
        log[#log + 1] = "}"
      end,
      run = say("P.active.run"), handle = say("P.active.handle"),
      exit = function(m)
        log[#log + 1] = "P.active.exit{"
        m.sub.child:stop()
        log[#log + 1] = "}"
      end,
      transitions = { { guard = function(m) return m.vars.leave end, to = "done" } },
    },
    done = { entry = say("P.done.entry") },
  },
}

eq(child.name, "child", "an unnamed sub-machine is named after its key")
eq(parent.sub.child, child, "m.sub.child")

parent:start()
eq(take(), "P.idle.entry", "start")
parent:update()
eq(take(), "P.idle.handle", "update 1: guard false, handle; inactive child not updated")

parent.vars.go = true
parent:update()
eq(take(), "P.idle->active, P.idle.exit, P.active.entry{, C.init.entry, }, "
  .. "C.init.run, C.init.exit, C.work.entry",
  "update 2: transition program, exit, entry with the child's start nested; then the child")
eq(child:is_running(), true, "child automatic")

parent:update()
eq(take(), "P.active.run, P.active.handle, C.work.run, C.work.handle", "update 3")

parent.vars.leave = true
parent:update()
eq(take(), "P.active.run, P.active.exit{, C.work.exit, C.final.entry, C.final.run, }, "
  .. "P.done.entry",
  "update 4: the child's stop (exit, final entry, run once: reactive) inside the parent's exit")
eq(child:get_state(), "c_final", "child in its final state")
eq(child:is_reactive(), true, "stop() leaves the child reactive")

parent:update()
eq(take(), "", "update 5: nothing (parent's final state empty, child reactive)")

local d = parent:describe()
eq(d.name, "parent", "describe name")
eq(d.state, "done", "describe state")
eq(d.mode, "automatic", "describe mode")
eq(d.sub.child.state, "c_final", "describe child state")
eq(d.sub.child.mode, "reactive", "describe child mode")

-- A paused parent freezes its children too.
child:reset()
eq(take(), "C.final.exit, C.init.entry, C.init.run", "child reset (reactive: run once)")
child:start()
parent:pause()
parent:update()
eq(take(), "", "paused parent: nothing, not even the child")
eq(parent:describe().mode, "paused", "describe paused")
parent:start()
parent:update()
eq(take(), "C.init.run, C.init.exit, C.work.entry", "resumed: the child moves again")

-- A misspelt sub-machine name is an error, not a nil.
local ok, err = pcall(function() return parent.sub.chlid end)
eq(ok, false, "unknown sub-machine")
assert(err:find('no submachine "chlid"; it has: child', 1, true), err)
assert(err:find("test_nested_order.lua:%d+:"), "error points at the test line: " .. err)

-- A machine can be the sub-machine of one parent only.
ok, err = pcall(statemachine, { initial = "a", final = "a", states = { a = {} },
  submachines = { c = child } })
eq(ok, false, "sub-machine reused")
assert(err:find('already belongs to statemachine "parent"', 1, true), err)
