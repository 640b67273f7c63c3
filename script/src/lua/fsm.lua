-- fsm.lua — hwgw's script component: hierarchical state machines after Orocos RTT 1.x.
--
-- Loaded by the script component after programs.lua and before the user's script, into a
-- sandboxed Lua 5.4 state (base, table, string, math, coroutine, utf8 only). Running this
-- chunk defines one global, statemachine(def), which checks a definition and returns a
-- machine object; the host calls m:update() on each root machine once per step.
--
-- Semantics follow the RTT 1.x manual (/work/shared/seeds/000_237df74429c13ddb.txt),
-- L3323–4052, and its summary at L2226–2263:
--   * one transition per step at most (L3333–3336); a state has entry, run, handle and exit
--     programs; handle runs right after run when no transition succeeds (L3338–3343);
--   * an initial state entered on activation and a final state entered on stop(), the
--     transition to which is always allowed (L3348–3352, L3964–3966);
--   * reactive mode: events and requests only, the run program runs once after entry
--     (L3359–3379, L3510–3515); step() makes one transition to the best next state or
--     runs handle (L3381–3385); automatic mode: run, then the transitions in order, else
--     handle, every step, events still served (L3388–3406, L4038–4052);
--   * transitions checked in order, with a failure ("else") program and select
--     (L3517–3548); a transition to the current state calls neither exit nor entry and is
--     always valid (L3545–3548); preconditions block a transition as if its guard were
--     false (L3550–3568); event transitions with arguments (L3570–3609);
--   * sub-machines activated, started and stopped by the parent's programs (L3723–3848),
--     public variables (L3644–3700); control commands (L3851–4052).
-- Order within a transition, here always: transition program, exit, entry. The manual
-- gives this order for events (L3368–3370) and automatic mode (L3401–3404), but exit
-- before the transition program for requests (L3376–3378); we use one order everywhere.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local QUEUE_LIMIT = 64 -- events queued per machine; emit() beyond it drops and counts

local HOOKS = { "entry", "run", "handle", "exit", "precondition" }
local DEF_KEYS = { name = true, initial = true, final = true, vars = true,
  submachines = true, states = true }
local STATE_KEYS = { entry = true, run = true, handle = true, exit = true,
  precondition = true, transitions = true }
local TRANSITION_KEYS = { event = true, guard = true, to = true, program = true,
  failure = true, failure_to = true }

local Machine = {}
Machine.__index = Machine

local BadDef = {} -- metatable marking a definition error raised while compiling

local function sorted_keys(t)
  local keys = {}
  for k in pairs(t) do keys[#keys + 1] = k end
  table.sort(keys, function(a, b) return tostring(a) < tostring(b) end)
  return keys
end

local function keylist(t)
  local keys = sorted_keys(t)
  if #keys == 0 then return "none" end
  for i, k in ipairs(keys) do keys[i] = tostring(k) end
  return table.concat(keys, ", ")
end

local function bad(fmt, ...)
  error(setmetatable({ msg = string.format(fmt, ...) }, BadDef))
end

-- Refuses keys of `t` not in `allowed` (catches typos such as `entyr`).
local function only_keys(t, allowed, where)
  for k in pairs(t) do
    if not allowed[k] then
      bad("%s: unknown key %q (allowed: %s)", where, tostring(k), keylist(allowed))
    end
  end
end

-- Refuses a value that is neither nil nor a table.
local function table_or_nil(v, what, where)
  if v ~= nil and type(v) ~= "table" then
    bad("%s: %s must be a table, got %s", where, what, type(v))
  end
end

-- Refuses fields of `t` named in `keys` that are neither nil nor functions.
local function only_functions(t, keys, where)
  for _, k in ipairs(keys) do
    if t[k] ~= nil and type(t[k]) ~= "function" then
      bad("%s: %s must be a function, got %s", where, k, type(t[k]))
    end
  end
end

-- A port event source: a table or userdata with a read method (value, "new"|"old"|"none").
local function is_port(v)
  local t = type(v)
  if t ~= "table" and t ~= "userdata" then return false end
  local ok, read = pcall(function() return v.read end)
  return ok and read ~= nil
end

-- Checks one transition and returns its compiled form.
local function compile_transition(t, where, known)
  if type(t) ~= "table" then bad("%s must be a table, got %s", where, type(t)) end
  only_keys(t, TRANSITION_KEYS, where)
  local ev = t.event
  if ev ~= nil and type(ev) ~= "string" and not is_port(ev) then
    bad("%s: event must be a name (string) or a port (a value with a read method), got %s",
      where, type(ev))
  end
  only_functions(t, { "guard", "program", "failure" }, where)
  if t.to ~= nil then known(t.to, where .. ": to") end
  if t.failure_to ~= nil then known(t.failure_to, where .. ": failure_to") end
  if t.to == nil and t.program == nil then
    bad("%s: needs a target state (to = ...) or a transition program (program = ...)", where)
  end
  return { event = ev, guard = t.guard, to = t.to, program = t.program,
    failure = t.failure, failure_to = t.failure_to }
end

-- Checks a whole definition; returns what the machine object is built from.
local function compile(def)
  if type(def) ~= "table" then
    bad("statemachine() needs a definition table, got %s", type(def))
  end
  if def.name ~= nil and type(def.name) ~= "string" then
    bad("statemachine: name must be a string, got %s", type(def.name))
  end
  local name = def.name or "machine"
  local where = string.format("statemachine %q", name)
  only_keys(def, DEF_KEYS, where)
  if type(def.states) ~= "table" or next(def.states) == nil then
    bad("%s: needs states = { <name> = { ... }, ... }", where)
  end
  local function known(target, what)
    if type(target) ~= "string" or def.states[target] == nil then
      bad("%s: %s: unknown state %s; states are: %s", where, what,
        type(target) == "string" and string.format("%q", target) or tostring(target),
        keylist(def.states))
    end
  end
  for _, k in ipairs({ "initial", "final" }) do
    if def[k] == nil then bad("%s: needs %s = \"<state name>\"", where, k) end
    known(def[k], k)
  end
  table_or_nil(def.vars, "vars", where)
  table_or_nil(def.submachines, "submachines", where)
  local subs = {}
  for k, child in pairs(def.submachines or {}) do
    if type(k) ~= "string" then bad("%s: submachine names must be strings", where) end
    if getmetatable(child) ~= Machine then
      bad("%s: submachine %q must be made by statemachine{...}, got %s", where, k, type(child))
    end
    if child._parent ~= nil then
      bad("%s: submachine %q already belongs to statemachine %q", where, k, child._parent.name)
    end
    subs[k] = child
  end

  local states, event_names = {}, {}
  for sname, s in pairs(def.states) do
    if type(sname) ~= "string" then bad("%s: state names must be strings", where) end
    local swhere = string.format("%s: state %q", where, sname)
    if type(s) ~= "table" then bad("%s must be a table, got %s", swhere, type(s)) end
    only_keys(s, STATE_KEYS, swhere)
    only_functions(s, HOOKS, swhere)
    table_or_nil(s.transitions, "transitions", swhere)
    local st, ts = { events = {}, conds = {} }, s.transitions or {}
    for _, h in ipairs(HOOKS) do st[h] = s[h] end
    for k in pairs(ts) do
      if math.type(k) ~= "integer" or k < 1 or k > #ts then
        bad("%s: transitions must be a list { {...}, {...} }; found key %q", swhere, tostring(k))
      end
    end
    for i, t in ipairs(ts) do
      local c = compile_transition(t, string.format("%s, transition %d", swhere, i), known)
      if c.event == nil then
        st.conds[#st.conds + 1] = c
      else
        st.events[#st.events + 1] = c
        if type(c.event) == "string" then event_names[c.event] = true end
      end
    end
    states[sname] = st
  end
  return { name = name, named = def.name ~= nil, states = states, subs = subs,
    event_names = event_names }
end

-- Creates a machine from its definition, raising at the caller's line if it is wrong.
function statemachine(def)
  local ok, c = pcall(compile, def)
  if not ok then
    if getmetatable(c) == BadDef then error(c.msg, 2) end
    error(c, 0)
  end
  local m = setmetatable({
    name = c.name, vars = def.vars or {}, dropped_events = 0,
    _states = c.states, _initial = def.initial, _final = def.final,
    _state = nil, _mode = "inactive", _queue = {}, _changes = 0,
    _event_names = c.event_names, _subnames = sorted_keys(c.subs), _named = c.named,
  }, Machine)
  for k, child in pairs(c.subs) do
    child._parent = m
    if not child._named then child.name = k end
  end
  -- m.sub.<name>; a misspelt name is an error at the user's line, not a nil.
  m.sub = setmetatable(c.subs, { __index = function(_, k)
    error(string.format("statemachine %q has no submachine %q; it has: %s", m.name,
      tostring(k), keylist(c.subs)), 2)
  end })
  return m
end

---------------------------------------------------------------------------------------
-- Internals. They raise nothing of their own; errors from hooks propagate unchanged.

-- Checks the method was called as m:method() and, if `active`, that the machine is
-- active. Level 3 is the user's line.
local function me(m, what, active)
  if getmetatable(m) ~= Machine then
    error(string.format("%s must be called as m:%s(...)", what, what), 3)
  end
  if active and m._mode == "inactive" then
    error(string.format("statemachine %q: %s() needs an active machine (activate() or "
      .. "start() it first)", m.name, what), 3)
  end
end

local function must_know(m, name, what)
  if type(name) ~= "string" or m._states[name] == nil then
    error(string.format("statemachine %q: %s: no state %s; states are: %s", m.name, what,
      type(name) == "string" and string.format("%q", name) or tostring(name),
      keylist(m._states)), 3)
  end
end

-- Whether `to` may be entered now: a transition to the current state (or one without a
-- target) is always valid (L3545–3548); otherwise the target's precondition must hold.
local function enterable(m, to)
  if to == nil or to == m._state then return true end
  local pre = m._states[to].precondition
  return pre == nil or not not pre(m)
end

-- Makes one transition: the transition program, then, when `to` is another state, the
-- current state's exit, the switch (recorded before entry, so an error in entry leaves the
-- machine in the new state) and the target's entry. In reactive mode the run program of
-- the state now current follows once (L3376–3379, L3510–3513). `...` are event arguments.
local function transit(m, to, program, ...)
  m._changes = m._changes + 1
  if program then program(m, ...) end
  if to ~= nil and to ~= m._state then
    local from = m._states[m._state]
    if from.exit then from.exit(m) end
    m._state = to
    local entry = m._states[to].entry
    if entry then entry(m) end
    -- A state reacts to events once its entry is done (L3364–3367): what its event ports
    -- hold from before is no event of its.
    local evs = m._states[to].events
    for i = 1, #evs do
      local port = evs[i].event
      if type(port) ~= "string" then port:read() end
    end
  end
  if m._mode == "reactive" then
    local run = m._states[m._state].run
    if run then run(m) end
  end
end

-- Tries one transition: guard (with the event's arguments) and target precondition hold ->
-- taken; otherwise the failure program runs and failure_to, if given and enterable, is
-- taken. Returns whether the machine changed state (a hook may also have done so).
local function try(m, t, ...)
  local before = m._changes
  if (t.guard == nil or t.guard(m, ...)) and enterable(m, t.to) then
    transit(m, t.to, t.program, ...)
  else
    if t.failure then t.failure(m, ...) end
    if t.failure_to ~= nil and m._changes == before and enterable(m, t.failure_to) then
      transit(m, t.failure_to, nil, ...)
    end
  end
  return m._changes ~= before
end

-- Serves the events of this step; returns whether one led to a transition. First the
-- emitted events queued before the step, oldest first: each is offered to the current
-- state's transitions on its name, in order, and is consumed whether one takes it or not.
-- Events after the one that wins stay queued for the next step (and the new state). Then
-- the port events, in transition order, each port read at most once per step; a read
-- with status "new" is an event whose argument is the value. Nothing is read after a win.
local function take_event(m)
  local st = m._states[m._state]
  local q = m._queue
  local events = st.events
  -- The common step: nothing queued, no event transition here. Nothing to do.
  if events[1] == nil then
    if q[1] ~= nil then
      for i = #q, 1, -1 do q[i] = nil end -- no transition here wants them
    end
    return false
  end
  for _ = 1, #q do
    local ev = table.remove(q, 1)
    for _, t in ipairs(st.events) do
      if t.event == ev.name and try(m, t, table.unpack(ev.args, 1, ev.args.n)) then
        return true
      end
    end
  end
  local read = nil -- made only when a port is read: a step with no port event allocates nothing
  for _, t in ipairs(st.events) do
    local port = t.event
    if type(port) ~= "string" then
      read = read or {}
      local r = read[port]
      if r == nil then
        local value, status = port:read()
        r = { new = status == "new", value = value }
        read[port] = r
      end
      if r.new and try(m, t, r.value) then return true end
    end
  end
  return false
end

-- Evaluates the non-event transitions in order; the first that is taken ends it. (A
-- numeric loop and a direct guard call: this runs every step of an automatic machine.)
local function take_transition(m)
  local conds = m._states[m._state].conds
  for i = 1, #conds do
    local t = conds[i]
    local guard = t.guard
    if guard == nil or t.failure ~= nil or t.failure_to ~= nil then
      if try(m, t) then return true end
    elseif guard(m) then
      -- try() without its failure path, the guard called once.
      local before = m._changes
      if enterable(m, t.to) then transit(m, t.to, t.program) end
      if m._changes ~= before then return true end
    end
  end
  return false
end

-- One step: events; in automatic mode (or a paused step) and when no event was taken:
-- run, then the transitions, else handle; then every active sub-machine, by name.
local function cycle(m, automatic)
  local before = m._changes
  if not take_event(m) and automatic then
    local st = m._states[m._state]
    if st.run then st.run(m) end
    if m._changes == before and not take_transition(m) and st.handle then st.handle(m) end
  end
  local subnames = m._subnames
  for i = 1, #subnames do
    local child = m.sub[subnames[i]]
    if child._mode ~= "inactive" then child:update() end
  end
end

-- Enters the initial state from inactive, in `mode`.
local function enter_initial(m, mode)
  m._mode = mode
  m._state = m._initial
  m._changes = m._changes + 1
  local st = m._states[m._initial]
  if st.entry then st.entry(m) end
  if mode == "reactive" and st.run then st.run(m) end
end

---------------------------------------------------------------------------------------
-- Methods.

-- inactive -> the initial state (entry, then run once), reactive mode. Active: nothing.
function Machine:activate()
  me(self, "activate")
  if self._mode == "inactive" then enter_initial(self, "reactive") end
end

-- Automatic mode; activates first when inactive (then entry only: run comes with the
-- next update, as in every automatic step).
function Machine:start()
  me(self, "start")
  if self._mode == "inactive" then
    enter_initial(self, "automatic")
  else
    self._mode = "automatic"
  end
end
Machine.automatic = Machine.start -- the manual's alias (L2253)

-- Freezes the machine: update() does nothing (nor for its sub-machines) until start() or
-- reactive(); step() then makes one automatic step.
function Machine:pause()
  me(self, "pause", true)
  self._mode = "paused"
end

-- Back to reactive mode (from automatic or paused).
function Machine:reactive()
  me(self, "reactive", true)
  self._mode = "reactive"
end

-- Reactive mode: one transition to the best next state (the first valid transition), or
-- handle when there is none (L3381–3385). Paused: one whole automatic step (events, run,
-- transitions or handle, sub-machines). Returns whether the state changed.
function Machine:step()
  me(self, "step", true)
  local before = self._changes
  if self._mode == "paused" then
    cycle(self, true)
  elseif self._mode == "automatic" then
    error(string.format("statemachine %q: step() is for reactive or paused mode, and it "
      .. "is running (automatic); pause() or reactive() it first", self.name), 2)
  elseif not take_transition(self) and self._changes == before then
    local handle = self._states[self._state].handle
    if handle then handle(self) end
  end
  return self._changes ~= before
end

-- To the final state now (exit, entry; the transition is always allowed), reactive mode.
-- Already in the final state: only the mode changes.
function Machine:stop()
  me(self, "stop", true)
  self._mode = "reactive"
  if self._state ~= self._final then transit(self, self._final) end
end

-- From the final state back to the initial one (final's exit, initial's entry).
function Machine:reset()
  me(self, "reset", true)
  if self._state ~= self._final then
    error(string.format("statemachine %q: reset() needs the final state %q; it is in %q "
      .. "(stop() it first)", self.name, self._final, self._state), 2)
  end
  transit(self, self._initial)
end

-- Leaves the current state (its exit) and becomes inactive; queued events are dropped.
-- Sub-machines are the parent's programs' business (L3723–3848) and are left as they are.
function Machine:deactivate()
  me(self, "deactivate")
  if self._mode == "inactive" then return end
  local exit = self._states[self._state].exit
  if exit then exit(self) end
  self._state = nil
  self._mode = "inactive"
  self._queue = {}
end

-- A requested transition (L3373–3379, L3957–3961). Allowed: the current state (only its run
-- program runs), the final state (always), or a state a non-event transition of the current
-- state leads to whose guard holds now and whose precondition holds. Performs it at once
-- and returns true; else false and the reason.
function Machine:request_state(name)
  me(self, "request_state")
  must_know(self, name, "request_state()")
  if self._mode == "inactive" then
    return false, string.format("statemachine %q is not active", self.name)
  end
  local cur = self._states[self._state]
  if name == self._state then
    if cur.run then cur.run(self) end
    return true
  end
  if name == self._final then
    transit(self, name)
    return true
  end
  local reason = string.format("state %q has no transition to %q", self._state, name)
  for _, t in ipairs(cur.conds) do
    if t.to == name then
      if t.guard ~= nil and not t.guard(self) then
        reason = string.format("the guard of state %q's transition to %q is false",
          self._state, name)
      elseif not enterable(self, name) then
        reason = string.format("the precondition of state %q does not hold", name)
      else
        transit(self, name, t.program)
        return true
      end
    end
  end
  return false, reason
end

function Machine:in_state(name)
  me(self, "in_state")
  must_know(self, name, "in_state()")
  return self._state == name
end

function Machine:get_state() me(self, "get_state"); return self._state end
function Machine:is_active() me(self, "is_active"); return self._mode ~= "inactive" end
function Machine:is_running() me(self, "is_running"); return self._mode == "automatic" end
function Machine:is_reactive() me(self, "is_reactive"); return self._mode == "reactive" end
function Machine:is_paused() me(self, "is_paused"); return self._mode == "paused" end

-- Queues an event for the next update. Returns true if queued; false when the machine is
-- inactive (nothing listens) or the queue already holds QUEUE_LIMIT events (then counted
-- in m.dropped_events). An event name no transition of this machine uses is an error.
function Machine:emit(event, ...)
  me(self, "emit")
  if type(event) ~= "string" then
    error(string.format("statemachine %q: emit() needs an event name, got %s", self.name,
      type(event)), 2)
  end
  if not self._event_names[event] then
    error(string.format("statemachine %q: no transition listens for event %q; its events "
      .. "are: %s", self.name, event, keylist(self._event_names)), 2)
  end
  if self._mode == "inactive" then return false end
  if #self._queue >= QUEUE_LIMIT then
    self.dropped_events = self.dropped_events + 1
    return false
  end
  self._queue[#self._queue + 1] = { name = event, args = table.pack(...) }
  return true
end

-- One step, called by the host on each root machine once per step (L3333–3336).
-- Inactive or paused: nothing. Otherwise events, then (automatic mode) run, transitions
-- or handle, then each active sub-machine's update(), in name order.
function Machine:update()
  me(self, "update")
  if self._mode == "inactive" or self._mode == "paused" then return end
  cycle(self, self._mode == "automatic")
end

-- For diagnostics: { name=, state=, mode=, sub = { <name> = <describe()>, ... } }.
function Machine:describe()
  me(self, "describe")
  local sub = {}
  for _, n in ipairs(self._subnames) do sub[n] = self.sub[n]:describe() end
  return { name = self.name, state = self._state, mode = self._mode, sub = sub }
end
