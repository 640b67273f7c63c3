-- test_events.lua — event transitions (manual L3364–3371, L3570–3609): an emitted event is
-- served at the next update, its arguments go to the guard and the transition program;
-- a port whose read() says "new" is an event with the value as its argument; events no
-- transition of the current state wants are discarded; one transition per update; the
-- queue is bounded.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local function eq(a, b, what)
  if a ~= b then
    error(what .. ":\n expected " .. tostring(b) .. "\n      got " .. tostring(a), 2)
  end
end


-- Checks that `err` points at a line of this file and contains `needle`.
local function raised_here(err, needle)
  if not (tostring(err):find("test_events.lua:%d+:") and tostring(err):find(needle, 1, true)) then
    error("expected an error at a line of this file with «" .. needle .. "», got: "
      .. tostring(err), 2)
  end
end

local log = {}
local function say(s) return function() log[#log + 1] = s end end
local function take()
  local s = table.concat(log, ", ")
  log = {}
  return s
end

-- A fake input port: read() returns the value with "new" once, then "old".
local function fake_port()
  local port = { value = nil, fresh = false, reads = 0 }
  function port:write(v) self.value, self.fresh = v, true end
  function port:read()
    self.reads = self.reads + 1
    if self.value == nil then return nil, "none" end
    local status = self.fresh and "new" or "old"
    self.fresh = false
    return self.value, status
  end
  return port
end

local alarm = fake_port()
local m = statemachine {
  name = "ev", initial = "idle", final = "stopped",
  vars = {},
  states = {
    idle = {
      run = say("idle.run"),
      exit = say("idle.exit"),
      transitions = {
        { event = "go", guard = function(m, speed, dir)
            log[#log + 1] = "guard(" .. tostring(speed) .. "," .. tostring(dir) .. ")"
            return speed > 10
          end,
          to = "moving",
          program = function(m, speed, dir) m.vars.speed, m.vars.dir = speed, dir end,
          failure = function(m, speed) log[#log + 1] = "too slow " .. speed end },
        { event = alarm, to = "fault", program = function(m, v) m.vars.alarm = v end },
      },
    },
    moving = {
      entry = say("moving.entry"), run = say("moving.run"),
      transitions = {
        { event = "halt", to = "idle" },
        { event = alarm, to = "fault", program = function(m, v) m.vars.alarm = v end },
      },
    },
    fault = { entry = say("fault.entry"), transitions = { { event = "reset", to = "idle" } } },
    stopped = {},
  },
}

eq(m:emit("go", 20), false, "emit to an inactive machine is not queued")
m:activate()
eq(take(), "idle.run", "activate")

-- An event is served at the next update, not when emitted.
eq(m:emit("go", 5, "fwd"), true, "queued")
eq(take(), "", "nothing before update")
m:update()
eq(take(), "guard(5,fwd), too slow 5", "guard false: failure program, no transition")
eq(m:get_state(), "idle", "still idle")

eq(m:emit("go", 20, "back"), true, "queued")
m:update()
eq(take(), "guard(20,back), idle.exit, moving.entry, moving.run",
  "guard true: program, exit, entry, run once (reactive)")
eq(m.vars.speed, 20, "argument 1 reached the program")
eq(m.vars.dir, "back", "argument 2 reached the program")

-- An event the current state does not listen for is discarded, not kept for later.
m:emit("reset")
m:update()
eq(m:get_state(), "moving", "reset ignored in moving")
m:emit("halt")
m:update()
eq(m:get_state(), "idle", "halt")
take()
m:emit("go", 50)
m:update()
eq(m:get_state(), "moving", "go")

-- One transition per update: the second event waits for the next update (and the new
-- state); FIFO order.
m:emit("halt")
m:emit("go", 30)
m:update()
eq(m:get_state(), "idle", "first event: halt")
m:update()
eq(m:get_state(), "moving", "second event, next update: go")
take()

-- The port: fires exactly at the update after the write, once.
local reads = alarm.reads
m:update()
eq(m:get_state(), "moving", "no new data: no transition")
eq(alarm.reads, reads + 1, "the port is read once per update")
alarm:write(7.5)
eq(m:get_state(), "moving", "a write alone changes nothing")
m:update()
eq(m:get_state(), "fault", "port event fired at this update")
eq(m.vars.alarm, 7.5, "the port's value is the event's argument")
take()
m:emit("reset")
m:update()
eq(m:get_state(), "idle", "reset")
m:update()
eq(m:get_state(), "idle", "old data on the port does not fire again")
eq(take(), "idle.run", "entering idle in reactive mode ran run once")

-- Events are also served in automatic mode, before run: an event taken means no run.
m:start()
m:update()
eq(take(), "idle.run", "automatic: run")
m:emit("go", 99)
m:update()
eq(take(), "guard(99,nil), idle.exit, moving.entry", "event first; no run after entry (automatic)")
m:update()
eq(take(), "moving.run", "run next update")

-- The queue is bounded; overflow is counted.
m:pause()
for i = 1, 64 do eq(m:emit("halt"), true, "emit " .. i) end
eq(m:emit("halt"), false, "emit 65 dropped")
eq(m:emit("halt"), false, "emit 66 dropped")
eq(m.dropped_events, 2, "dropped_events")
m:start()
m:update()
eq(m:get_state(), "idle", "one halt taken")
m:update()
eq(m:get_state(), "idle", "the 63 other halts were discarded in idle")
m:emit("go", 11)
m:update()
eq(m:get_state(), "moving", "queue works after draining")

-- Mistakes.
local ok, err = pcall(function() m:emit("hlat") end)
eq(ok, false, "unknown event name")
raised_here(err, 'no transition listens for event "hlat"; its events are: go, halt, reset')
ok, err = pcall(function() m:emit(alarm) end)
eq(ok, false, "a port is not emitted")
assert(err:find("emit() needs an event name", 1, true), err)
