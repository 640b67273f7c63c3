//! `io.open` for a script, within its `data_dir` and nowhere else: a relative path with
//! no `..`, no link followed (the file or a folder on the way), regular files only, at
//! most [`MAX_READ`] read at once. Without `data_dir`, `io.open` refuses every path. The
//! file object has the usual `read` ("a", "l", "n"), `lines`, `write` and `close`; a
//! file opened for writing is written at `flush` and `close` (not when collected: a
//! script has no finalizers).

use crate::host::Host;
use mlua::Lua;
use std::fs::OpenOptions;
use std::io::{Read, Write};
use std::path::{Component, Path, PathBuf};

/// The most a script reads from one file.
pub const MAX_READ: u64 = 1 << 20;

/// Opens `path` with `options` and `flags` besides `O_NONBLOCK` (a FIFO's open does not
/// wait for its writer), and refuses anything but a regular file. The one way a script's
/// file, its `io.open` and the deployment's digest of script files open what they read.
pub fn open_regular(
    options: &mut std::fs::OpenOptions,
    path: &Path,
    flags: i32,
) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    let f = options.custom_flags(libc::O_NONBLOCK | flags).open(path)?;
    if !f.metadata()?.is_file() {
        return Err(std::io::Error::other("not a regular file"));
    }
    Ok(f)
}

/// `path` under `dir`, or why not.
fn resolve(dir: Option<&Path>, path: &str) -> Result<PathBuf, String> {
    let Some(dir) = dir else {
        return Err(format!(
            "io.open({path:?}): this script has no data_dir, so it opens no file"
        ));
    };
    let p = Path::new(path);
    if path.is_empty()
        || !p
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(format!(
            "io.open({path:?}): only a relative path inside data_dir {} (no '..', not absolute)",
            dir.display()
        ));
    }
    let root = dir
        .canonicalize()
        .map_err(|e| format!("data_dir {}: {e}", dir.display()))?;
    let full = root.join(p);
    let parent = full.parent().unwrap_or(&root);
    let real_parent = parent
        .canonicalize()
        .map_err(|e| format!("io.open({path:?}): {}: {e}", parent.display()))?;
    if !real_parent.starts_with(&root) {
        return Err(format!(
            "io.open({path:?}): a link leads outside data_dir {}",
            dir.display()
        ));
    }
    Ok(full)
}

fn read(dir: Option<&Path>, path: &str) -> Result<String, String> {
    let full = resolve(dir, path)?;
    let failed = |e: std::io::Error| format!("io.open({path:?}): {e}");
    let f = open_regular(OpenOptions::new().read(true), &full, libc::O_NOFOLLOW).map_err(failed)?;
    let mut text = String::new();
    f.take(MAX_READ + 1)
        .read_to_string(&mut text)
        .map_err(failed)?;
    if text.len() as u64 > MAX_READ {
        return Err(format!("io.open({path:?}): larger than {MAX_READ} bytes"));
    }
    Ok(text)
}

fn write(dir: Option<&Path>, path: &str, text: &[u8], append: bool) -> Result<(), String> {
    let full = resolve(dir, path)?;
    let failed = |e: std::io::Error| format!("io.open({path:?}): {e}");
    let mut options = OpenOptions::new();
    options.write(true).create(true).append(append);
    let mut f = open_regular(&mut options, &full, libc::O_NOFOLLOW).map_err(failed)?;
    if !append {
        f.set_len(0).map_err(failed)?;
    }
    f.write_all(text).map_err(failed)
}

fn data_dir(lua: &Lua) -> Option<PathBuf> {
    lua.app_data_ref::<Host>().and_then(|h| h.data_dir.clone())
}

const OPEN: &str = r##"
local read, write = __hwgw_read, __hwgw_write
__hwgw_read, __hwgw_write = nil, nil
local function reader(text)
  local pos = 1
  local f = {}
  function f:read(fmt)
    fmt = fmt or "l"
    if type(fmt) == "string" then fmt = fmt:gsub("^%*", "") end
    if pos > #text and fmt ~= "a" then return nil end
    if fmt == "a" then local s = text:sub(pos); pos = #text + 1; return s end
    if fmt == "n" then
      local s, e = text:find("^%s*[-+]?[%d%.eExX]+", pos)
      if not s then return nil end
      local n = tonumber(text:sub(s, e):match("%S+")); pos = e + 1; return n
    end
    local e = text:find("\n", pos, true)
    local line = text:sub(pos, (e or #text + 1) - 1)
    pos = (e or #text) + 1
    if fmt == "L" and e then return line .. "\n" end
    return line
  end
  function f:lines(fmt) return function() return f:read(fmt) end end
  function f:close() return true end
  return f
end
local function writer(path, append)
  local parts, closed = {}, false
  local f = {}
  function f:write(...)
    if closed then error("write on a closed file", 2) end
    for i = 1, select("#", ...) do parts[#parts + 1] = tostring((select(i, ...))) end
    return f
  end
  function f:flush()
    local ok, err = write(path, table.concat(parts), append)
    if not ok then error(err, 2) end
    append = true; parts = {}
    return true
  end
  function f:close() if not closed then f:flush(); closed = true end return true end
  return f
end
io = setmetatable({
  open = function(path, mode)
    mode = (mode or "r"):gsub("b", "")
    if mode == "r" then
      local text, err = read(path)
      if not text then return nil, err end
      return reader(text)
    elseif mode == "w" or mode == "a" then
      local ok, err = write(path, "", mode == "a")
      if not ok then return nil, err end
      return writer(path, true)
    end
    error("io.open: mode " .. tostring(mode) .. " is not one of r, w, a", 2)
  end,
}, getmetatable(io))
"##;

/// Installs `io.open` (replacing the sandbox's empty `io`).
pub fn install(lua: &Lua) -> mlua::Result<()> {
    let g = lua.globals();
    g.set(
        "__hwgw_read",
        lua.create_function(|lua, path: String| {
            Ok(match read(data_dir(lua).as_deref(), &path) {
                Ok(text) => (Some(text), None),
                Err(e) => (None, Some(e)),
            })
        })?,
    )?;
    g.set(
        "__hwgw_write",
        lua.create_function(|lua, (path, text, append): (String, mlua::String, bool)| {
            Ok(
                match write(data_dir(lua).as_deref(), &path, &text.as_bytes(), append) {
                    Ok(()) => (true, None),
                    Err(e) => (false, Some(e)),
                },
            )
        })?,
    )?;
    lua.load(OPEN).set_name("=hwgw/io").exec()
}
