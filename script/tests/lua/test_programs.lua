-- test_programs.lua — programs (manual L2173–2210, L3017–3321): one piece between two
-- waits per step, waiting on operation handles and conditions, start/pause/step/stop,
-- the error state, and what programs._step() reports to the host.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local function eq(a, b, what)
  if a ~= b then
    error(what .. ":\n expected " .. tostring(b) .. "\n      got " .. tostring(a), 2)
  end
end
local function none(t, what) eq(#t, 0, what .. ": no failures") end

-- yield() waits exactly one step.
local count = 0
program("counter", function()
  while true do
    count = count + 1
    yield()
  end
end)
eq(programs.is_running("counter"), false, "registered, not started")
programs._step()
eq(count, 0, "not started: not run")
programs.start("counter")
eq(programs.is_running("counter"), true, "running")
eq(count, 0, "start does not run it: the next step does")
for i = 1, 5 do none(programs._step(), "step " .. i) end
eq(count, 5, "one loop per step")

-- pause, step, start again, stop, start afresh.
programs.pause("counter")
eq(programs.is_paused("counter"), true, "paused")
programs._step()
eq(count, 5, "paused: not run by _step")
eq(programs.step("counter"), "paused", "step returns the state")
eq(count, 6, "step: exactly once")
programs.step("counter")
eq(count, 7, "step again")
programs.start("counter")
programs._step()
eq(count, 8, "resumed")
programs.stop("counter")
eq(programs.state("counter"), "stopped", "stopped")
programs._step()
eq(count, 8, "stopped: not run")
local ok, err = pcall(function() programs.step("counter") end)
eq(ok, false, "step when not paused")
assert(err:find('program "counter" is stopped, not paused', 1, true), err)
assert(err:find("test_programs.lua:%d+:"), "points at the test: " .. err)
count = 100
programs.start("counter")
programs._step()
eq(count, 101, "start after stop: a fresh coroutine from the top")
programs.stop("counter")

-- wait(handle): polls now, then once per step; returns the results.
local function fake_handle(polls, ...)
  local result = table.pack(...)
  local h = { polls = 0 }
  function h:collect_if_done()
    self.polls = self.polls + 1
    if self.polls < polls then return nil end
    return table.unpack(result, 1, result.n)
  end
  return h
end
local got, got2, steps
local h = fake_handle(3, true, 42, "x")
program("waiter", function()
  steps = 0
  got, got2 = wait(h)
  yield()
end)
local pw = program("waiter_steps", function()
  while true do
    steps = (steps or 0) + 1
    yield()
  end
end)
programs.start("waiter")
pw:start()
programs._step()
eq(h.polls, 1, "polled at once")
eq(got, nil, "pending")
programs._step()
eq(h.polls, 2, "polled once per step")
programs._step()
eq(h.polls, 3, "third poll done")
eq(got, 42, "result")
eq(got2, "x", "second result")
eq(programs.is_running("waiter"), true, "still running (one yield left)")
programs._step()
eq(programs.state("waiter"), "stopped", "finished program is stopped")
eq(programs.in_error("waiter"), false, "not in error")
pw:stop()

-- A failed operation raises its message at the wait() line; the program goes to error.
local bad = fake_handle(2, false, "operation refused")
program("failing_wait", function()
  wait(bad)
end)
programs.start("failing_wait")
none(programs._step(), "pending")
local failed = programs._step()
eq(#failed, 1, "one failure reported")
eq(failed[1].name, "failing_wait", "its name")
assert(failed[1].error:find("test_programs.lua:%d+: operation refused"), failed[1].error)
eq(programs.in_error("failing_wait"), true, "in error")
none(programs._step(), "reported once only")

-- A raised error: state "error", message with file:line, reported once; start again.
local runs = 0
local where -- "file:line: " of the error below, taken on the same line
program("boom", function()
  runs = runs + 1
  yield()
  where = select(2, pcall(function() error("") end)); error("it broke")
end)
programs.start("boom")
none(programs._step(), "first piece fine")
failed = programs._step()
eq(#failed, 1, "failure this step")
eq(failed[1].name, "boom", "name")
assert(where:find("test_programs.lua:%d+: $"), where)
eq(failed[1].error, where .. "it broke", "message keeps file:line")
eq(programs.in_error("boom"), true, "in_error")
eq(programs.is_running("boom"), false, "not running")
eq(programs.error_of("boom"), failed[1].error, "error_of")
none(programs._step(), "nothing new")
programs.start("boom")
eq(programs.error_of("boom"), nil, "start clears the error")
eq(programs.state("boom"), "running", "running again")
programs._step()
eq(runs, 2, "fresh coroutine after error")
programs.stop("boom")
eq(programs.in_error("boom"), false, "stop leaves no error")

-- A paused program that fails while stepped is reported by step and by the next _step.
program("step_fail", function() yield(); error("late") end)
programs.start("step_fail")
programs.pause("step_fail")
eq(programs.step("step_fail"), "paused", "first piece")
local st, e = programs.step("step_fail")
eq(st, "error", "step into the error")
assert(e:find("late"), e)
eq(#programs._step(), 1, "reported at the next _step")

-- A program started during a step first runs at the next step.
local late = 0
program("late", function() late = late + 1; yield(); late = late + 1 end)
program("starter", function() programs.start("late") end)
programs.start("starter")
programs._step()
eq(programs.is_running("late"), true, "started by another program")
eq(late, 0, "not resumed in the step it was started in")
programs._step()
eq(late, 1, "resumed at the next step")
programs._step()
eq(late, 2, "and so on")
eq(programs.state("late"), "stopped", "finished")

-- A running program restarted by another one during a step is fresh: it waits for the
-- next step as well.
local b_runs = 0
program("restarter", function()
  yield()
  programs.stop("restarted")
  programs.start("restarted")
end)
program("restarted", function()
  while true do
    b_runs = b_runs + 1
    yield()
  end
end)
programs.start("restarter")
programs.start("restarted")
programs._step()
eq(b_runs, 1, "both ran once")
programs._step()
eq(b_runs, 1, "restarted during the step: not resumed in it")
programs._step()
eq(b_runs, 2, "the fresh coroutine runs from the next step")
programs.stop("restarted")

-- wait_until and sleep (with a fake clock).
local t = 0.0
function now() return t end
local flag, woke, ready = false, false, false
program("sleeper", function() sleep(0.5); woke = true end)
program("until", function() wait_until(function() return flag end); ready = true end)
programs.start("sleeper")
programs.start("until")
for _ = 1, 3 do
  t = t + 0.2
  programs._step()
end
eq(woke, false, "0.4 s after start: still asleep")
t = t + 0.2
programs._step()
eq(woke, true, "awake once 0.5 s have passed")
eq(ready, false, "condition false: waiting")
flag = true
programs._step()
eq(ready, true, "condition true: continues")

-- Waiting outside a program is a mistake.
ok, err = pcall(function() yield() end)
eq(ok, false, "yield outside a program")
assert(err:find("yield() can only be used inside a program", 1, true), err)
ok, err = pcall(function() wait(fake_handle(1, true)) end)
eq(ok, false, "wait outside a program")

-- Names: unknown ones list the known ones, duplicates refused, list() sorted.
ok, err = pcall(function() programs.start("nope") end)
eq(ok, false, "unknown program")
assert(err:find("test_programs.lua:%d+:"), err)
assert(err:find('no program "nope"; this script has: boom, counter, failing_wait, late, '
  .. 'restarted, restarter, sleeper, starter, step_fail, until, waiter, waiter_steps', 1, true),
  err)
ok, err = pcall(function() program("counter", function() end) end)
eq(ok, false, "duplicate")
assert(err:find('program "counter" is already defined', 1, true), err)
eq(table.concat(programs.list(), ","),
  "boom,counter,failing_wait,late,restarted,restarter,sleeper,starter,step_fail,until,waiter,"
  .. "waiter_steps", "list")

-- The program object's methods; their errors point at the caller as well.
local obj = program("obj", function()
  programs.pause("obj") -- a program may pause itself: it stops at its next yield
  yield()
  programs.stop("obj") -- or stop itself: it ends at its next yield
  yield()
  error("never reached")
end)
ok, err = pcall(function() obj:pause() end)
eq(ok, false, "pause a stopped program")
assert(err:find('test_programs.lua:%d+: program "obj" is stopped, not running'), err)
obj:start()
eq(obj:is_running(), true, "p:is_running()")
none(programs._step(), "obj first piece")
eq(obj:is_paused(), true, "paused itself")
eq(obj:get_state(), "paused", "p:get_state()")
none(programs._step(), "paused: skipped")
eq(obj:step(), "stopped", "stepped: it stopped itself")
eq(obj:in_error(), false, "not in error")
eq(obj:error_of(), nil, "no error")
