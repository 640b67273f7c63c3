-- The pump interlock of interlock.toml: a state machine (idle → starting → running, a
-- fault on the limit switch, reset through the `emit reset` operation) and a timed
-- start-up program (the lamp warns for vars.warn_s seconds, then the supply pressure
-- must be there).
--
-- Ports are declared here and connected in the TOML; the card is read by name.

local start_button = port.input("start_button", "bool", { event = true, doc = "the start button" })
local limit = port.input("limit", "bool", { event = true, doc = "the limit switch" })
local pump = port.output("pump", "bool", { doc = "the pump's contactor" })
local alarm = port.output("alarm", "bool", { doc = "the alarm horn" })
local lamp = port.output("lamp", "bool", { doc = "the warning lamp" })
local field = device.digital_in("sim0")

local PRESSURE_OK = 2
local LIMIT = 1

-- The start-up sequence: warn, then check the supply pressure.
program("startup", function()
  lamp:write(true)
  sleep(vars.warn_s)
  lamp:write(false)
  if not field:get(PRESSURE_OK) then
    error("no supply pressure (input " .. PRESSURE_OK .. " off)")
  end
end)

local function pressed(_, on) return on end

rootmachine {
  name = "interlock",
  initial = "idle",
  final = "off",
  states = {
    idle = {
      entry = function() pump:write(false); alarm:write(false) end,
      transitions = {
        -- Start only with the limit switch clear.
        { event = start_button, guard = function(_, on) return on and not field:get(LIMIT) end,
          to = "starting" },
      },
    },
    starting = {
      entry = function() programs.start("startup") end,
      transitions = {
        { event = limit, guard = pressed, to = "fault" },
        { guard = function() return programs.in_error("startup") end, to = "fault" },
        { guard = function() return not programs.is_running("startup") end, to = "running" },
      },
      -- Left early (the limit switch): the sequence stops, the lamp goes off. A failed
      -- sequence keeps its error for `hwgw call sup program.error_of startup`.
      exit = function()
        if programs.is_running("startup") then programs.stop("startup") end
        lamp:write(false)
      end,
    },
    running = {
      entry = function() pump:write(true); log.info("pump running") end,
      transitions = {
        { event = limit, guard = pressed, to = "fault" },
        { event = "stop", to = "idle" },
      },
    },
    fault = {
      entry = function()
        pump:write(false)
        alarm:write(true)
        log.warn("interlock fault")
      end,
      transitions = {
        -- Reset through an operation, once the limit switch is clear.
        { event = "reset", guard = function() return not field:get(LIMIT) end, to = "idle" },
      },
    },
    off = {
      entry = function() pump:write(false); alarm:write(false); lamp:write(false) end,
    },
  },
}
