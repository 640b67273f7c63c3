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

impl Problem {
    /// A problem at `location`, under key `path`: its path and message [tidied](tidy), so
    /// no value of the file comes back in full however long it is.
    pub fn new(location: Option<Location>, path: &str, message: &str) -> Problem {
        Problem {
            location,
            path: tidy(path),
            message: tidy(message),
        }
    }
}

/// Characters of a quoted string kept in a message; the rest is cut and counted.
const QUOTED_CHARS: usize = device_interface::text::SHOWN_CHARS;
/// Characters of an unquoted word (a path, a key) kept in a message.
const WORD_CHARS: usize = 300;
/// Characters of a whole message kept.
const MESSAGE_CHARS: usize = 4000;
/// Digits from which a number in a message is a float printed in full (no integer type
/// has this many): it is shown short instead (`1e308`).
const LONG_NUMBER: usize = 22;

/// `text` as a message shows it: a quoted string (`"…"`, `` `…` ``) longer than 80
/// characters cut with an ellipsis and its full length; a float printed in full (serde's
/// `floating point \`1000…0.0\``) shown short (`1e308`); any other word longer than 300
/// characters cut; the whole at most 4000 characters.
pub fn tidy(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len().min(MESSAGE_CHARS + 64));
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c == '"' || c == '`' {
            // The quoted part: to the closing quote (escapes skipped), or the end.
            let mut j = i + 1;
            while j < chars.len() && chars[j] != c {
                j += if chars[j] == '\\' { 2 } else { 1 };
            }
            let end = j.min(chars.len());
            let closed = j < chars.len();
            let inner: String = chars[i + 1..end].iter().collect();
            out.push(c);
            if let Some(n) = long_number(&inner).filter(|_| c == '`') {
                out.push_str(&n);
                if closed {
                    out.push(c);
                }
            } else {
                let n = inner.chars().count();
                // Cut already (`"xxxx…" (N characters)` from `text::Quoted`): as it is.
                let cut_before = inner.ends_with('…') && n <= QUOTED_CHARS + 1;
                out.push_str(&cut(&inner, QUOTED_CHARS, true));
                if closed {
                    out.push(c);
                }
                if n > QUOTED_CHARS && !cut_before {
                    // `"xxxx…" (N characters)`.
                    out.push_str(&format!(" ({n} characters)"));
                }
            }
            i = end + 1;
        } else if c.is_whitespace() {
            out.push(c);
            i += 1;
        } else {
            // A word: to the next space or quote.
            let mut j = i;
            while j < chars.len() && !chars[j].is_whitespace() && chars[j] != '"' && chars[j] != '`'
            {
                j += 1;
            }
            let word: String = chars[i..j].iter().collect();
            out.push_str(&shorten_word(&word));
            i = j;
        }
    }
    cut(&out, MESSAGE_CHARS, false)
}

/// A word of a message, its long numbers shown short and the whole cut when long.
fn shorten_word(word: &str) -> String {
    // Numbers inside a word (`1000…0.0:`, `[1000…0,`): each run of digits and dots.
    let mut out = String::new();
    let mut rest = word;
    while let Some(start) = rest.find(|c: char| c.is_ascii_digit()) {
        out.push_str(&rest[..start]);
        let tail = &rest[start..];
        let len = tail
            .find(|c: char| !(c.is_ascii_digit() || c == '.'))
            .unwrap_or(tail.len());
        let run = &tail[..len];
        match long_number(run.trim_end_matches('.')) {
            Some(n) => {
                out.push_str(&n);
                out.push_str(&run[run.trim_end_matches('.').len()..]);
            }
            None => out.push_str(run),
        }
        rest = &tail[len..];
    }
    out.push_str(rest);
    if out.chars().count() > WORD_CHARS {
        let n = word.chars().count();
        let head: String = out.chars().take(QUOTED_CHARS).collect();
        format!("{head}… ({n} characters)")
    } else {
        out
    }
}

/// A float printed in full (`1000…0.0`, `0.000…05`), shown short; `None` for anything
/// else.
fn long_number(s: &str) -> Option<String> {
    let digits = s.bytes().filter(u8::is_ascii_digit).count();
    let (sign, body) = s.strip_prefix('-').map_or(("", s), |b| ("-", b));
    if digits < LONG_NUMBER || !body.bytes().all(|b| b.is_ascii_digit() || b == b'.') {
        return None;
    }
    let v: f64 = body.parse().ok()?;
    Some(format!("{sign}{}", device_interface::text::Number(v)))
}

/// `s` cut after `keep` characters with an ellipsis (not inside an escape when `escaped`).
fn cut(s: &str, keep: usize, escaped: bool) -> String {
    let Some((end, _)) = s.char_indices().nth(keep) else {
        return s.to_string();
    };
    let mut head = &s[..end];
    if escaped {
        // Not half an escape: an odd run of backslashes at the end loses one.
        let slashes = head.len() - head.trim_end_matches('\\').len();
        if slashes % 2 == 1 {
            head = &head[..head.len() - 1];
        }
    }
    if escaped {
        format!("{head}…")
    } else {
        format!("{head}… ({} characters)", s.chars().count())
    }
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

    /// A problem for every number of the file that is NaN or infinite (`nan`, `inf`,
    /// `-inf`), in the order written: no setting takes one, and each is named as what it
    /// is rather than as whatever a setting makes of it later.
    pub fn non_finite(&self) -> Vec<Problem> {
        fn walk(
            src: &Source<'_>,
            path: &KeyPath,
            value: &Spanned<DeValue<'_>>,
            out: &mut Vec<Problem>,
        ) {
            match value.get_ref() {
                DeValue::Float(f) => {
                    let v: f64 = f.as_str().parse().unwrap_or(0.0);
                    if let Some(why) = device_interface::text::non_finite(v) {
                        let message = format!("{why} ({}): give a finite number", f.as_str());
                        let at = src.locate_offset(value.span().start);
                        out.push(Problem::new(Some(at), &path.to_string(), &message));
                    }
                }
                DeValue::Array(a) => {
                    for (i, v) in a.iter().enumerate() {
                        walk(src, &path.index(i), v, out);
                    }
                }
                DeValue::Table(t) => {
                    for (k, v) in t.iter() {
                        walk(src, &path.key(k.get_ref()), v, out);
                    }
                }
                _ => {}
            }
        }
        let mut out = Vec::new();
        if let Some(root) = &self.tree {
            for (k, v) in root.get_ref().iter() {
                walk(self, &KeyPath::top(k.get_ref()), v, &mut out);
            }
        }
        // A table's keys come hashed: the file's order is the spans' order.
        out.sort_by_key(|p| p.location.as_ref().map(|l| (l.line, l.column)));
        out
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
        self.list
            .push(Problem::new(location, &path, &message.to_string()));
    }

    /// A problem found in another file (a component's property file), located there.
    pub fn add(&mut self, problem: Problem) {
        self.list.push(problem);
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

    #[test]
    fn messages_show_values_short() {
        let long = "x".repeat(1000);
        assert_eq!(
            tidy(&format!(
                "invalid type: string \"{long}\", expected a boolean"
            )),
            format!(
                "invalid type: string \"{}…\" (1000 characters), expected a boolean",
                "x".repeat(80)
            )
        );
        // Cut already by `text::Quoted`: left as it is.
        let quoted = device_interface::text::Quoted(&long).to_string();
        assert_eq!(
            tidy(&format!("unit {quoted} is long")),
            format!("unit {quoted} is long")
        );
        // Floats printed in full, by serde and by `{}`.
        let full = format!("{}", 1e308);
        assert_eq!(
            tidy(&format!(
                "invalid type: floating point `{full}.0`, expected u32"
            )),
            "invalid type: floating point `1e308`, expected u32"
        );
        assert_eq!(
            tidy(&format!("{full}: at most 10, not -{full}.")),
            "1e308: at most 10, not -1e308."
        );
        assert_eq!(tidy(&format!("{}", 5e-324)), "5e-324");
        // Integers, addresses, short numbers and numbers in a user's string stay.
        for same in [
            "18446744073709551615 and 0x7fff and 127.0.0.1 and 1.2.3.4.5.6.7.8.9.10.11.12",
            "\"1111111111111111111111111\" is not a port name",
        ] {
            assert_eq!(tidy(same), same);
        }
        // A word too long (a key, a path) is cut; the whole message is bounded.
        let word = "k".repeat(1000);
        assert_eq!(
            tidy(&word),
            format!("{}… (1000 characters)", "k".repeat(80))
        );
        assert!(tidy(&"a ".repeat(100_000)).chars().count() < 4100);
        // Escapes are not cut in two.
        let escaped = format!("\"{}\"", "\\n".repeat(100));
        assert_eq!(
            tidy(&escaped),
            format!("\"{}…\" (200 characters)", "\\n".repeat(40))
        );
    }

    #[test]
    fn numbers_that_are_not_numbers_are_found_where_they_are() {
        let text = "a = nan\n[[card]]\nx = { y = [1.0, -inf] }\nz = 1e308\nw = +inf\n";
        let src = Source::new("f.toml", text);
        let found: Vec<String> = src.non_finite().iter().map(|p| p.to_string()).collect();
        assert_eq!(
            found,
            [
                "f.toml:1:5: a: is NaN (nan): give a finite number",
                "f.toml:3:17: card[0].x.y[1]: is infinite (-inf): give a finite number",
                "f.toml:5:5: card[0].w: is infinite (+inf): give a finite number",
            ]
        );
    }
}
