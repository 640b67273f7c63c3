//! Problems in a deployment file, each named by its key path and located at it.
//!
//! The file is parsed once into a tree that keeps every key's and value's position;
//! a [`Problems`] collector turns a [`KeyPath`] into both the printed path and the
//! line:column it points at, so the two cannot disagree. Locating is a walk down the tree
//! (indexed arrays, hashed tables) and a binary search for the line: linear in the number
//! of problems, whatever their number.

use std::fmt;
use std::ops::Range;
use toml::Spanned;
use toml::de::{DeTable, DeValue};

/// One step of a key path: a table key or an array index.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Seg {
    /// `.key`
    Key(String),
    /// `[i]`
    Index(usize),
}

/// Where a value is in a deployment: `card[0].sim.analog_in[1]`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct KeyPath(Vec<Seg>);

impl KeyPath {
    /// The file's top level.
    pub fn root() -> KeyPath {
        KeyPath(Vec::new())
    }

    /// The top-level `key`.
    pub fn top(key: &str) -> KeyPath {
        KeyPath::root().key(key)
    }

    /// `self.key`.
    pub fn key(&self, key: &str) -> KeyPath {
        let mut p = self.clone();
        p.0.push(Seg::Key(key.to_string()));
        p
    }

    /// `self[i]`.
    pub fn index(&self, i: usize) -> KeyPath {
        let mut p = self.clone();
        p.0.push(Seg::Index(i));
        p
    }

    /// `self` followed by `rest`, a path written as text (`rx[0].message`).
    pub fn join(&self, rest: &str) -> KeyPath {
        let mut p = self.clone();
        for part in rest.split('.').filter(|s| !s.is_empty()) {
            let (key, mut tail) = match part.find('[') {
                Some(i) => (&part[..i], &part[i..]),
                None => (part, ""),
            };
            if !key.is_empty() {
                p.0.push(Seg::Key(key.to_string()));
            }
            while let Some(rest) = tail.strip_prefix('[') {
                let Some(end) = rest.find(']') else { break };
                match rest[..end].parse() {
                    Ok(i) => p.0.push(Seg::Index(i)),
                    Err(_) => p.0.push(Seg::Key(rest[..end].to_string())),
                }
                tail = &rest[end + 1..];
            }
        }
        p
    }
}

impl fmt::Display for KeyPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, s) in self.0.iter().enumerate() {
            match s {
                Seg::Key(k) if i == 0 => write!(f, "{k}")?,
                Seg::Key(k) => write!(f, ".{k}")?,
                Seg::Index(n) => write!(f, "[{n}]")?,
            }
        }
        Ok(())
    }
}

/// Where in a file something is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// The file.
    pub file: String,
    /// Line, from 1.
    pub line: usize,
    /// Column, from 1.
    pub column: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}", self.file, self.line, self.column)
    }
}

/// One problem in a deployment file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Problem {
    /// Where, when known.
    pub location: Option<Location>,
    /// Key path, e.g. `card[0].sim.analog_in[1].range`.
    pub path: String,
    /// What is wrong and what was expected.
    pub message: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(l) = &self.location {
            write!(f, "{l}: ")?;
        }
        if self.path.is_empty() {
            write!(f, "{}", self.message)
        } else {
            write!(f, "{}: {}", self.path, self.message)
        }
    }
}

/// What a walk down a key path found: the deepest value, its key's span, and whether
/// that is the whole path.
struct Found<'s, 'a> {
    value: &'s Spanned<DeValue<'a>>,
    key: Option<Range<usize>>,
    whole: bool,
}

/// A deployment file's text, parsed once for locating keys in it.
pub struct Source<'a> {
    file: &'a str,
    text: &'a str,
    tree: Option<Spanned<DeTable<'a>>>,
    /// Byte offset of the start of each line.
    lines: Vec<usize>,
}

impl<'a> Source<'a> {
    /// `text`, read from `file`.
    pub fn new(file: &'a str, text: &'a str) -> Source<'a> {
        let lines = std::iter::once(0)
            .chain(text.match_indices('\n').map(|(i, _)| i + 1))
            .collect();
        Source {
            file,
            text,
            tree: DeTable::parse(text).ok(),
            lines,
        }
    }

    /// The file's name as given.
    pub fn file(&self) -> &str {
        self.file
    }

    /// Line and column (from 1) of byte `offset`.
    pub fn locate_offset(&self, offset: usize) -> Location {
        let offset = offset.min(self.text.len());
        let line = self.lines.partition_point(|&start| start <= offset).max(1);
        let start = self.lines[line - 1];
        let column = self
            .text
            .get(start..offset)
            .map_or(0, |s| s.chars().count())
            + 1;
        Location {
            file: self.file.to_string(),
            line,
            column,
        }
    }

    /// The value at `path` and the span of its key (the last step's), following the path
    /// as far as it exists.
    fn walk(&self, path: &KeyPath) -> Option<Found<'_, 'a>> {
        let root = self.tree.as_ref()?;
        let mut table: Option<&DeTable<'a>> = Some(root.get_ref());
        let mut array: Option<&[Spanned<DeValue<'a>>]> = None;
        let mut found: Option<(&Spanned<DeValue<'a>>, Option<Range<usize>>)> = None;
        for seg in &path.0 {
            let next = match (seg, table, array) {
                (Seg::Key(k), Some(t), _) => t
                    .get_key_value(k.as_str())
                    .map(|(key, v)| (v, Some(key.span()))),
                (Seg::Index(i), _, Some(a)) => a.get(*i).map(|v| (v, None)),
                _ => None,
            };
            let Some((value, key)) = next else {
                return found.map(|(value, key)| Found {
                    value,
                    key,
                    whole: false,
                });
            };
            table = match value.get_ref() {
                DeValue::Table(t) => Some(t),
                _ => None,
            };
            array = match value.get_ref() {
                DeValue::Array(a) => Some(a.as_ref()),
                _ => None,
            };
            found = Some((value, key));
        }
        found.map(|(value, key)| Found {
            value,
            key,
            whole: true,
        })
    }

    /// The value at `path`, exactly.
    pub fn value(&self, path: &KeyPath) -> Option<&Spanned<DeValue<'a>>> {
        match self.walk(path) {
            Some(f) if f.whole => Some(f.value),
            _ => None,
        }
    }

    /// Where the value at `path` starts, or the deepest part of the path that exists.
    pub fn locate(&self, path: &KeyPath) -> Option<Location> {
        match self.walk(path) {
            Some(f) => Some(self.locate_offset(f.value.span().start)),
            None if path.0.is_empty() => Some(self.locate_offset(0)),
            None => None,
        }
    }

    /// Where the key at the end of `path` is written (for a key that should not be there).
    pub fn locate_key(&self, path: &KeyPath) -> Option<Location> {
        match self.walk(path) {
            Some(Found {
                key: Some(key),
                whole: true,
                ..
            }) => Some(self.locate_offset(key.start)),
            _ => self.locate(path),
        }
    }
}

/// Collects the problems of one deployment, each rendered and located from its path.
pub struct Problems<'s, 'a> {
    source: &'s Source<'a>,
    list: Vec<Problem>,
}

impl<'s, 'a> Problems<'s, 'a> {
    /// No problems yet, in `source`.
    pub fn new(source: &'s Source<'a>) -> Self {
        Problems {
            source,
            list: Vec::new(),
        }
    }

    /// The file being checked.
    pub fn source(&self) -> &'s Source<'a> {
        self.source
    }

    /// A problem with the value at `path`.
    pub fn at(&mut self, path: &KeyPath, message: impl fmt::Display) {
        let location = self.source.locate(path);
        self.push(location, path.to_string(), message);
    }

    /// A problem with the key at the end of `path` (one that should not be there).
    pub fn at_key(&mut self, path: &KeyPath, message: impl fmt::Display) {
        let location = self.source.locate_key(path);
        self.push(location, path.to_string(), message);
    }

    /// A problem the parser found at byte `span` of the file, under `path`.
    pub fn at_span(
        &mut self,
        path: &KeyPath,
        span: Option<Range<usize>>,
        message: impl fmt::Display,
    ) {
        let location = match span {
            Some(s) => Some(self.source.locate_offset(s.start)),
            None => self.source.locate(path),
        };
        self.push(location, path.to_string(), message);
    }

    fn push(&mut self, location: Option<Location>, path: String, message: impl fmt::Display) {
        self.list.push(Problem {
            location,
            path,
            message: message.to_string(),
        });
    }

    /// True while nothing was found.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// Every problem, in the order found.
    pub fn into_vec(self) -> Vec<Problem> {
        self.list
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_render_and_locate_alike() {
        let text = "a = 1\n[[card]]\nname = \"x\"\n[card.sim]\nn = [1, 2]\n";
        let src = Source::new("f.toml", text);
        let p = KeyPath::top("card").index(0).key("sim").key("n").index(1);
        assert_eq!(p.to_string(), "card[0].sim.n[1]");
        assert_eq!(src.locate(&p).unwrap().to_string(), "f.toml:5:9");
        assert_eq!(
            src.locate_key(&KeyPath::top("card").index(0).key("name"))
                .unwrap()
                .to_string(),
            "f.toml:3:1"
        );
        // A path that goes on past what exists points at what does.
        let missing = KeyPath::top("card").index(0).key("sim").key("nope");
        assert_eq!(src.locate(&missing).unwrap().to_string(), "f.toml:4:1");
        assert_eq!(
            KeyPath::top("card").join("rx[0].signal[2]").to_string(),
            "card.rx[0].signal[2]"
        );
    }
}
