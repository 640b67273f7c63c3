-- hwgw's glue between the script component and the Lua libraries (programs.lua,
-- fsm.lua): the root machine (`rootmachine{...}`: the one machine the component's
-- operations and its `state` port show), the per-step entry point, and the operations'
-- entry points. Loaded after the libraries and before the script.

local root, root_mode

-- The component's machine: `mode` is "automatic" (the default: started with the
-- component), "reactive" (activated with the component, moved by request_state, step
-- and events) or "manual" (left inactive until the machine.activate/start operation).
function rootmachine(def, mode)
  if root then error("rootmachine: this script has one already", 2) end
  mode = mode or "automatic"
  if mode ~= "automatic" and mode ~= "reactive" and mode ~= "manual" then
    error("rootmachine: mode " .. tostring(mode) .. " is not automatic, reactive or manual", 2)
  end
  root = statemachine(def)
  root_mode = mode
  return root
end

-- Called by the component at start: the machine from its initial state, in its mode.
function __hwgw_start()
  if not root then return end
  if root:is_active() and root:get_state() ~= nil and not root:is_running() then
    -- A machine stopped with its component waits in its final state: back to initial.
    pcall(root.reset, root)
  end
  if root_mode == "automatic" then root:start()
  elseif root_mode == "reactive" then root:activate() end
end

-- Called by the component at stop: the machine to its final state (manual L3350).
function __hwgw_stop()
  if root and root:is_active() then root:stop() end
end

-- One step: the script's update (passed in: the one it defined when it loaded), the
-- programs, then the machine (not when `requested`: an operation moved it this step);
-- one call from the component a step. Returns the machine's state and, when programs
-- failed this step, their list.
function __hwgw_step(update, requested)
  if update then update() end
  local failed = programs._step()
  if failed[1] == nil then failed = nil end
  if root then
    -- A transition an operation requested before this step was the step's one (L3333).
    if not requested then root:update() end
    return root:get_state(), failed
  end
  return nil, failed
end

local machine_ops = {
  activate = true, start = true, stop = true, pause = true, step = true, reactive = true,
  reset = true, deactivate = true, request_state = true, in_state = true, get_state = true,
  emit = true, is_active = true, is_running = true, is_reactive = true, is_paused = true,
}

function __hwgw_machine(op, arg)
  if not machine_ops[op] then error("no machine operation " .. tostring(op), 0) end
  if not root then error("this script has no machine (rootmachine{...})", 0) end
  return root[op](root, arg)
end

function __hwgw_program(op, name)
  return programs[op](name)
end
