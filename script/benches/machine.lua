-- The benchmark's machine: 10 states, 20 transitions (each state: on to the next while
-- input a is in the state's window, across to the opposite state when input b dips), 4
-- port reads and writes a step (a and b read in update, x and y written in run). The
-- same logic is written in Rust in machine.rs, the reference.

local a = port.input("a", "f64")
local b = port.input("b", "f64")
local x = port.output("x", "f64")
local y = port.output("y", "i64")
local va, vb = 0.0, 0.0

local states = {}
for i = 0, 9 do
  local n = i
  local low, high = n - 5.0, n - 4.0
  states["s" .. i] = {
    run = function() x:write(va * 0.5 + n); y:write(n) end,
    transitions = {
      { guard = function() return va > low and va < high end, to = "s" .. ((i + 1) % 10) },
      { guard = function() return vb < -0.95 end, to = "s" .. ((i + 5) % 10) },
    },
  }
end

rootmachine { name = "bench", initial = "s0", final = "s9", states = states }

-- vars.alloc: each step also formats a line (a string of ~20 bytes: garbage for the
-- collector, as a script that logs or builds messages makes).
local alloc = vars.alloc
last_line = ""

function update()
  va = a:read() or va
  vb = b:read() or vb
  if alloc then last_line = string.format("%.3f %.3f", va, vb) end
end
