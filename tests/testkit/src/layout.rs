//! Checks of the source tree's shape, run as tests: no two modules of a crate import each
//! other (directly or round a longer cycle), and no function is longer than a limit.
//!
//! Both read the files as text, which is enough for this code base: module paths come from
//! `crate::…`, `super::…` and `self::…` paths outside comments, and a function runs from
//! its `fn` line to the brace that closes its body.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A crate's modules (by path, `crate` for the root) and which of them each one imports.
#[derive(Debug, Default)]
pub struct ModuleGraph {
    /// Module path -> the module paths it names.
    pub edges: BTreeMap<String, BTreeSet<String>>,
}

/// The module path of `file` under the crate's `src`: `crate`, `crate::a`, `crate::a::b`.
fn module_of(src: &Path, file: &Path) -> String {
    let rel = file.strip_prefix(src).unwrap_or(file).with_extension("");
    let mut parts: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if matches!(
        parts.last().map(String::as_str),
        Some("mod" | "lib" | "main")
    ) {
        parts.pop();
    }
    std::iter::once("crate".to_string())
        .chain(parts)
        .collect::<Vec<_>>()
        .join("::")
}

/// `text` without `//` comments, block comments and the contents of string literals.
pub fn strip_comments_and_strings(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let b: Vec<char> = text.chars().collect();
    let mut i = 0;
    while i < b.len() {
        match (b[i], b.get(i + 1).copied()) {
            ('/', Some('/')) => {
                while i < b.len() && b[i] != '\n' {
                    i += 1;
                }
            }
            ('/', Some('*')) => {
                i += 2;
                while i + 1 < b.len() && !(b[i] == '*' && b[i + 1] == '/') {
                    if b[i] == '\n' {
                        out.push('\n');
                    }
                    i += 1;
                }
                i += 2;
            }
            ('"', _) => {
                out.push('"');
                i += 1;
                while i < b.len() && b[i] != '"' {
                    if b[i] == '\\' {
                        i += 1;
                    }
                    if b.get(i) == Some(&'\n') {
                        out.push('\n');
                    }
                    i += 1;
                }
                out.push('"');
                i += 1;
            }
            // A char literal that could hide a quote or a brace.
            ('\'', Some(c)) if b.get(i + 2) == Some(&'\'') && c != '\\' => {
                out.push_str("' '");
                i += 3;
            }
            ('\'', Some('\\')) if b.get(i + 3) == Some(&'\'') => {
                out.push_str("' '");
                i += 4;
            }
            (c, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    out
}

/// Every path written `crate::…` (or through `use crate::{…}`), `super::…` or `self::…`
/// in `code`, as absolute module-path candidates seen from module `here`.
fn named_paths(
    code: &str,
    here: &str,
    is_dir_module: bool,
    is_module: &dyn Fn(&str) -> bool,
) -> Vec<Vec<String>> {
    let mut found = Vec::new();
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    let chars: Vec<char> = code.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let starts_word = i == 0 || !(ident(chars[i - 1]) || chars[i - 1] == ':');
        let rest: String = chars[i..chars.len().min(i + 7)].iter().collect();
        let base: Option<(Vec<String>, usize)> = if !starts_word {
            None
        } else if rest.starts_with("crate::") {
            Some((vec!["crate".into()], 7))
        } else if rest.starts_with("super::") {
            let mut m: Vec<String> = here.split("::").map(String::from).collect();
            if !is_dir_module {
                m.pop();
            }
            m.pop();
            Some((m, 7))
        } else if rest.starts_with("self::") {
            let mut m: Vec<String> = here.split("::").map(String::from).collect();
            if !is_dir_module {
                m.pop();
            }
            Some((m, 6))
        } else {
            // A relative path naming a child module: `child::Item`.
            let word: String = chars[i..].iter().take_while(|c| ident(**c)).collect();
            let after = i + word.chars().count();
            let child = format!("{here}::{word}");
            if !word.is_empty()
                && chars[after..].iter().take(2).collect::<String>() == "::"
                && is_dir_module
                && is_module(&child)
            {
                Some((here.split("::").map(String::from).collect(), 0))
            } else {
                None
            }
        };
        let Some((prefix, skip)) = base else {
            i += 1;
            continue;
        };
        i += skip;
        // Repeated `super::super::` climbs further.
        let mut prefix = prefix;
        while chars[i..].iter().collect::<String>().starts_with("super::") {
            prefix.pop();
            i += 7;
        }
        collect_tree(&chars, &mut i, prefix, &mut found);
    }
    found
}

/// Reads one path tail at `chars[*i..]` (`a::b::C`, or a `{…}` group of them) below
/// `prefix`, pushing each full path.
fn collect_tree(chars: &[char], i: &mut usize, prefix: Vec<String>, out: &mut Vec<Vec<String>>) {
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    let mut path = prefix;
    loop {
        while *i < chars.len() && chars[*i].is_whitespace() {
            *i += 1;
        }
        if *i < chars.len() && chars[*i] == '{' {
            *i += 1;
            loop {
                while *i < chars.len() && (chars[*i].is_whitespace() || chars[*i] == ',') {
                    *i += 1;
                }
                if *i >= chars.len() || chars[*i] == '}' {
                    *i += 1;
                    return;
                }
                let before = *i;
                collect_tree(chars, i, path.clone(), out);
                if *i == before {
                    *i += 1;
                }
            }
        }
        let start = *i;
        while *i < chars.len() && ident(chars[*i]) {
            *i += 1;
        }
        if *i == start {
            out.push(path);
            return;
        }
        path.push(chars[start..*i].iter().collect());
        if chars[*i..].iter().take(2).collect::<String>() == "::" {
            *i += 2;
            continue;
        }
        out.push(path);
        return;
    }
}

impl ModuleGraph {
    /// Reads every `.rs` file under `src` (a crate's source folder).
    pub fn read(src: &Path) -> std::io::Result<ModuleGraph> {
        let mut files = Vec::new();
        rust_files(src, &mut files)?;
        let modules: BTreeMap<String, PathBuf> = files
            .iter()
            .map(|f| (module_of(src, f), f.clone()))
            .collect();
        let mut graph = ModuleGraph::default();
        for (module, file) in &modules {
            let is_dir_module = matches!(
                file.file_stem().and_then(|s| s.to_str()),
                Some("mod" | "lib" | "main")
            );
            let code = strip_comments_and_strings(&std::fs::read_to_string(file)?);
            let edges = graph.edges.entry(module.clone()).or_default();
            let is_module = |m: &str| modules.contains_key(m);
            for path in named_paths(&code, module, is_dir_module, &is_module) {
                // The longest prefix of the path that is a module of this crate.
                let target = (1..=path.len())
                    .rev()
                    .map(|n| path[..n].join("::"))
                    .find(|p| modules.contains_key(p));
                if let Some(t) = target
                    && &t != module
                    // A module naming its own descendant is the normal direction.
                    && !t.starts_with(&format!("{module}::"))
                {
                    edges.insert(t);
                }
            }
        }
        Ok(graph)
    }

    /// Every cycle of imports, each as the modules round it (empty: none).
    pub fn cycles(&self) -> Vec<Vec<String>> {
        let mut cycles = Vec::new();
        let mut seen_in_cycle = BTreeSet::new();
        for start in self.edges.keys() {
            // Depth-first search for a way back to `start`.
            let mut stack = vec![(start.clone(), vec![start.clone()])];
            let mut visited = BTreeSet::new();
            while let Some((node, path)) = stack.pop() {
                for next in self.edges.get(&node).into_iter().flatten() {
                    if next == start {
                        let mut key = path.clone();
                        key.sort();
                        if seen_in_cycle.insert(key) {
                            cycles.push(path.clone());
                        }
                    } else if visited.insert(next.clone()) {
                        let mut p = path.clone();
                        p.push(next.clone());
                        stack.push((next.clone(), p));
                    }
                }
            }
        }
        cycles
    }
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)?.collect::<Result<_, _>>()?;
    entries.sort_by_key(|e| e.path());
    for e in entries {
        let p = e.path();
        if p.is_dir() {
            rust_files(&p, out)?;
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
    Ok(())
}

/// A function longer than allowed: file, first line, name, length in lines.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LongFunction {
    /// The file.
    pub file: PathBuf,
    /// Line of its `fn`, from 1.
    pub line: usize,
    /// Its name.
    pub name: String,
    /// Lines from `fn` to its closing brace.
    pub lines: usize,
}

/// Every function under `dir` (recursively) whose body spans more than `limit` lines.
pub fn long_functions(dir: &Path, limit: usize) -> std::io::Result<Vec<LongFunction>> {
    let mut files = Vec::new();
    rust_files(dir, &mut files)?;
    let mut long = Vec::new();
    for file in files {
        let code = strip_comments_and_strings(&std::fs::read_to_string(&file)?);
        let lines: Vec<&str> = code.lines().collect();
        for (n, line) in lines.iter().enumerate() {
            let Some(at) = line.find("fn ") else { continue };
            if at > 0 && !line[..at].ends_with(char::is_whitespace) {
                continue;
            }
            let name: String = line[at + 3..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if name.is_empty() {
                continue;
            }
            // Find the body's opening brace (before any `;`, which ends a declaration).
            let mut depth = 0i64;
            let mut opened = false;
            let mut end = None;
            'scan: for (k, l) in lines.iter().enumerate().skip(n) {
                let from = if k == n { at } else { 0 };
                for c in l[from..].chars() {
                    match c {
                        ';' if !opened && depth == 0 => break 'scan,
                        '{' => {
                            depth += 1;
                            opened = true;
                        }
                        '}' => {
                            depth -= 1;
                            if opened && depth == 0 {
                                end = Some(k);
                                break 'scan;
                            }
                        }
                        _ => {}
                    }
                }
            }
            if let Some(end) = end
                && end - n + 1 > limit
            {
                long.push(LongFunction {
                    file: file.clone(),
                    line: n + 1,
                    name,
                    lines: end - n + 1,
                });
            }
        }
    }
    Ok(long)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_are_found_in_use_groups_and_code_not_in_comments() {
        let code = strip_comments_and_strings(
            "use crate::{a::X, b::{c::Y, Z}};\n// crate::nope::N\nfn f() { crate::d::e(); let s = \"crate::s::t\"; super::p::q(); }",
        );
        let got = named_paths(&code, "crate::m::k", false, &|_| false);
        let got: Vec<String> = got.iter().map(|p| p.join("::")).collect();
        assert_eq!(
            got,
            vec![
                "crate::a::X",
                "crate::b::c::Y",
                "crate::b::Z",
                "crate::d::e",
                "crate::p::q"
            ]
        );
    }
}
