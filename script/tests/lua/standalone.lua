-- standalone.lua — runs one of the script component's Lua tests on the system interpreter.
--
-- Usage, from the repository root:
--   lua5.4 script/tests/lua/standalone.lua [--sandbox] script/tests/lua/test_x.lua
--
-- Loads script/src/lua/programs.lua, then script/src/lua/fsm.lua (the order the script
-- component uses), then runs the test file, which raises on failure; prints "ok <file>".
-- With --sandbox, io, os, package, debug, require, dofile and loadfile are set to nil after
-- the libraries are loaded, before the test runs: the libraries and tests must not need
-- them (the component's Lua state has only base, table, string, math, coroutine, utf8).
-- The tests themselves do not depend on this runner: the Rust side runs them the same way.
--
-- SPDX-License-Identifier: MIT OR Apache-2.0

local sandbox, file = false, nil
for _, a in ipairs(arg) do
  if a == "--sandbox" then sandbox = true else file = a end
end
if file == nil then
  io.stderr:write("usage: lua5.4 script/tests/lua/standalone.lua [--sandbox] <test.lua>\n")
  os.exit(2)
end

local exit, write, traceback = os.exit, io.stderr.write, debug.traceback
dofile("script/src/lua/programs.lua")
dofile("script/src/lua/fsm.lua")
local chunk, err = loadfile(file, "t")
if chunk == nil then
  write(io.stderr, err .. "\n")
  exit(1)
end
local stderr = io.stderr
if sandbox then
  io, os, package, debug, require, dofile, loadfile = nil, nil, nil, nil, nil, nil, nil
end
local ok, msg = xpcall(chunk, traceback)
if not ok then
  write(stderr, "FAIL " .. file .. ": " .. tostring(msg) .. "\n")
  exit(1)
end
print("ok " .. file .. (sandbox and " (sandbox)" or ""))
