//! Type names as the control protocol writes them, made from Rust's.
//!
//! Ports, operations and properties are listed with the types of the values they carry,
//! and those values travel as JSON: a client needs `read(channel: u32) -> f64`, not
//! `core::result::Result<f64, alloc::string::String>`. [`of`] and [`wire`] turn a Rust type
//! (as [`std::any::type_name`] spells it) into the protocol's name:
//!
//! | Rust | protocol |
//! |---|---|
//! | `u8`…`u64`, `i8`…`i64`, `f32`, `f64`, `bool`, `char` | the same |
//! | `usize`, `isize` | `u64`, `i64` |
//! | `String`, `str`, `Cow<str>` | `string` |
//! | `Result<T, E>` | `T` (an error is the call's error) |
//! | `()` | nothing (the empty string) |
//! | `Vec<T>`, `[T]`, `[T; N]`, `VecDeque<T>`, sets | `[T]` |
//! | `Option<T>` | `T?` |
//! | `HashMap<K, V>`, `BTreeMap<K, V>` | `{K: V}` |
//! | `(A, B)` | `(A, B)` |
//! | `Box<T>`, `Arc<T>`, `Rc<T>`, `&T` | `T` |
//! | `serde_json::Value` | `json` |
//! | any other type | its own name without its module path (`Edge`, `Counters`) |
//!
//! ```
//! assert_eq!(rtt::typename::of::<Result<f64, String>>(), "f64");
//! assert_eq!(rtt::typename::of::<Result<(), String>>(), "");
//! assert_eq!(
//!     rtt::typename::of::<(String, Option<f64>, Vec<u32>)>(),
//!     "(string, f64?, [u32])"
//! );
//! ```

/// The protocol's name of `T`.
pub fn of<T: ?Sized>() -> String {
    wire(std::any::type_name::<T>())
}

/// The protocol's name of the Rust type spelt `rust` (as [`std::any::type_name`] gives
/// it). `()`, and a `Result` of `()`, are the empty string: nothing.
pub fn wire(rust: &str) -> String {
    let mut p = Parser {
        s: rust.as_bytes(),
        at: 0,
    };
    let ty = p.ty();
    if p.at < p.s.len() {
        // Not a shape this parser knows: the text itself, paths and all, beats a wrong name.
        return rust.to_string();
    }
    match ty.unwrap_result() {
        Ty::Tuple(items) if items.is_empty() => String::new(),
        t => t.render(),
    }
}

/// A parsed type.
enum Ty {
    /// `(A, B, …)`; `()` when empty.
    Tuple(Vec<Ty>),
    /// `[T]` or `[T; N]`.
    Slice(Box<Ty>),
    /// `path::Name<args>`: the last segment of the path, and the arguments.
    Named(String, Vec<Ty>),
}

impl Ty {
    /// `Result<T, E>` as `T`, through any number of wrappers that show as their content.
    fn unwrap_result(self) -> Ty {
        match self {
            Ty::Named(name, mut args) if name == "Result" && !args.is_empty() => {
                args.swap_remove(0).unwrap_result()
            }
            other => other,
        }
    }

    fn render(&self) -> String {
        match self {
            Ty::Tuple(items) => {
                let items: Vec<String> = items.iter().map(Ty::render).collect();
                format!("({})", items.join(", "))
            }
            Ty::Slice(item) => format!("[{}]", item.render()),
            Ty::Named(name, args) => named(name, args),
        }
    }
}

/// A named type's protocol name.
fn named(name: &str, args: &[Ty]) -> String {
    let arg = |i: usize| args.get(i).map_or_else(|| "?".to_string(), Ty::render);
    match (name, args.len()) {
        ("usize", 0) => "u64".into(),
        ("isize", 0) => "i64".into(),
        ("String" | "str", 0) => "string".into(),
        ("Value", 0) => "json".into(),
        ("Result", 1..) => arg(0),
        ("Option", 1) => format!("{}?", arg(0)),
        ("Vec" | "VecDeque" | "HashSet" | "BTreeSet" | "SmallVec", 1..) => {
            format!("[{}]", arg(0))
        }
        ("HashMap" | "BTreeMap" | "IndexMap", 2..) => format!("{{{}: {}}}", arg(0), arg(1)),
        ("Box" | "Arc" | "Rc" | "Cow", 1..) => arg(0),
        (_, 0) => name.to_string(),
        _ => {
            let args: Vec<String> = args.iter().map(Ty::render).collect();
            format!("{name}<{}>", args.join(", "))
        }
    }
}

/// A recursive-descent reader of `std::any::type_name`'s grammar.
struct Parser<'a> {
    s: &'a [u8],
    at: usize,
}

impl Parser<'_> {
    fn peek(&self) -> Option<u8> {
        self.s.get(self.at).copied()
    }

    fn skip_spaces(&mut self) {
        while self.peek() == Some(b' ') {
            self.at += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        self.skip_spaces();
        if self.peek() == Some(c) {
            self.at += 1;
            true
        } else {
            false
        }
    }

    fn eat_word(&mut self, w: &str) -> bool {
        self.skip_spaces();
        let rest = &self.s[self.at..];
        let ends = rest.get(w.len()).is_none_or(|c| !c.is_ascii_alphanumeric());
        if rest.starts_with(w.as_bytes()) && ends {
            self.at += w.len();
            true
        } else {
            false
        }
    }

    fn ty(&mut self) -> Ty {
        self.skip_spaces();
        // References and pointers show as what they point to.
        if self.eat(b'&') {
            self.skip_lifetime();
            self.eat_word("mut");
            return self.ty();
        }
        if self.eat(b'*') {
            let _ = self.eat_word("const") || self.eat_word("mut");
            return self.ty();
        }
        if self.eat(b'(') {
            let items = self.list(b')');
            return Ty::Tuple(items);
        }
        if self.eat(b'[') {
            let item = self.ty();
            if self.eat(b';') {
                // The length: `[T; 4]`.
                while self.peek().is_some_and(|c| c != b']') {
                    self.at += 1;
                }
            }
            self.eat(b']');
            return Ty::Slice(Box::new(item));
        }
        self.eat_word("dyn");
        let name = self.path();
        let args = if self.eat(b'<') {
            self.list(b'>')
        } else {
            Vec::new()
        };
        // `dyn A + Send`: the first trait names it.
        while self.eat(b'+') {
            let _ = self.ty();
        }
        Ty::Named(name, args)
    }

    fn skip_lifetime(&mut self) {
        self.skip_spaces();
        if self.peek() == Some(b'\'') {
            self.at += 1;
            while self
                .peek()
                .is_some_and(|c| c.is_ascii_alphanumeric() || c == b'_')
            {
                self.at += 1;
            }
        }
    }

    /// Types separated by commas up to `close` (a trailing comma allowed).
    fn list(&mut self, close: u8) -> Vec<Ty> {
        let mut items = Vec::new();
        loop {
            if self.eat(close) || self.peek().is_none() {
                return items;
            }
            let before = self.at;
            items.push(self.ty());
            self.eat(b',');
            if self.at == before {
                // Nothing this parser reads: give up on the rest (`wire` sees it unread).
                return items;
            }
        }
    }

    /// `a::b::Name`: the last segment.
    fn path(&mut self) -> String {
        loop {
            self.skip_spaces();
            let start = self.at;
            while self
                .peek()
                .is_some_and(|c| c.is_ascii_alphanumeric() || c == b'_' || c >= 0x80)
            {
                self.at += 1;
            }
            if self.s[self.at..].starts_with(b"::") {
                self.at += 2;
            } else {
                return String::from_utf8_lossy(&self.s[start..self.at]).into_owned();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;
    use std::sync::Arc;

    #[test]
    fn rust_types_get_protocol_names() {
        assert_eq!(of::<u32>(), "u32");
        assert_eq!(of::<usize>(), "u64");
        assert_eq!(of::<String>(), "string");
        assert_eq!(of::<&str>(), "string");
        assert_eq!(of::<()>(), "");
        assert_eq!(of::<Result<(), String>>(), "");
        assert_eq!(of::<Result<f64, String>>(), "f64");
        assert_eq!(of::<Option<Vec<bool>>>(), "[bool]?");
        assert_eq!(of::<[u8; 4]>(), "[u8]");
        assert_eq!(of::<BTreeMap<String, i64>>(), "{string: i64}");
        assert_eq!(of::<Arc<f64>>(), "f64");
        assert_eq!(of::<serde_json::Value>(), "json");
        assert_eq!(
            of::<Result<(String, Option<f64>, Option<String>), String>>(),
            "(string, f64?, string?)"
        );
        assert_eq!(of::<(u32,)>(), "(u32)");
        assert_eq!(of::<crate::TaskState>(), "TaskState");
        assert_eq!(of::<std::time::Duration>(), "Duration");
    }

    #[test]
    fn what_it_cannot_read_is_left_as_it_is() {
        assert_eq!(wire("fn(u32) -> u32"), "fn(u32) -> u32");
        assert_eq!(wire(""), "");
    }
}
