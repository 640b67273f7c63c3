//! The fixed-size log record and its arguments: what a real-time thread builds on its stack
//! and pushes, and the logger thread formats.

use std::fmt::{self, Write as _};

/// Arguments a record carries (more are left out, and the text says so).
pub const MAX_ARGS: usize = 4;

/// Bytes of text an argument carries ([`Arg::text`], [`Arg::display`]); longer text is cut
/// at a character boundary and ends in `…`.
pub const TEXT_BYTES: usize = 94;

/// A short text kept in the record itself.
#[derive(Clone, Copy)]
pub struct Inline {
    bytes: [u8; TEXT_BYTES],
    len: u8,
    cut: bool,
}

impl Inline {
    fn empty() -> Self {
        Inline {
            bytes: [0; TEXT_BYTES],
            len: 0,
            cut: false,
        }
    }

    /// How many bytes of `s` fit in what is left, cut at a character boundary.
    fn fitting(&self, s: &str) -> usize {
        let mut take = s.len().min(TEXT_BYTES - usize::from(self.len));
        while !s.is_char_boundary(take) {
            take -= 1;
        }
        take
    }

    fn as_str(&self) -> &str {
        // Only whole characters are ever copied in.
        std::str::from_utf8(&self.bytes[..usize::from(self.len)]).unwrap_or("")
    }
}

impl fmt::Write for Inline {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        let take = self.fitting(s);
        let at = usize::from(self.len);
        self.bytes[at..at + take].copy_from_slice(&s.as_bytes()[..take]);
        // TEXT_BYTES fits in a u8.
        self.len += u8::try_from(take).unwrap_or(0);
        if take < s.len() {
            self.cut = true;
            // Stop the formatting: the rest would be cut anyway.
            return Err(fmt::Error);
        }
        Ok(())
    }
}

/// Fills inline texts one after the other.
struct Chunks<const N: usize> {
    parts: [Inline; N],
    at: usize,
}

impl<const N: usize> fmt::Write for Chunks<N> {
    fn write_str(&mut self, mut s: &str) -> fmt::Result {
        while !s.is_empty() {
            let Some(part) = self.parts.get_mut(self.at) else {
                return Err(fmt::Error);
            };
            if self.at + 1 == N {
                // The last part: what does not fit is cut there.
                return part.write_str(s);
            }
            let take = part.fitting(s);
            part.write_str(&s[..take])?;
            s = &s[take..];
            if !s.is_empty() {
                self.at += 1;
            }
        }
        Ok(())
    }
}

/// One argument of a record: a number, a flag, a static text, or a short copy of one.
#[derive(Clone, Copy)]
pub enum Arg {
    /// A signed integer.
    Int(i64),
    /// An unsigned integer.
    Uint(u64),
    /// A float, written as Rust writes it (shortest form that reads back the same).
    Float(f64),
    /// A flag.
    Bool(bool),
    /// A text that lives for the whole program.
    Static(&'static str),
    /// A short text copied in.
    Text(Inline),
    /// An operating-system error, by its number (its text is looked up when written:
    /// std allocates to look it up).
    Errno(i32),
}

impl Arg {
    /// `s`, copied into the record (at most [`TEXT_BYTES`] bytes).
    pub fn text(s: &str) -> Arg {
        let mut t = Inline::empty();
        let _ = t.write_str(s);
        Arg::Text(t)
    }

    /// `v` as its `Display` writes it, into `N` arguments one after the other (at most `N`
    /// × [`TEXT_BYTES`] bytes; beyond, it is cut and the last ends in `…`): a long text in
    /// a message with `N` `{}`s in a row. Formats on the calling thread, as
    /// [`display`](Self::display) does.
    pub fn chunks<const N: usize>(v: &dyn fmt::Display) -> [Arg; N] {
        let mut w = Chunks {
            parts: [Inline::empty(); N],
            at: 0,
        };
        let _ = write!(w, "{v}");
        w.parts.map(Arg::Text)
    }

    /// An I/O error: by its number when it is the operating system's (whose text std
    /// allocates to look up: the logger thread does that), else as [`display`](Self::display).
    pub fn io(e: &std::io::Error) -> Arg {
        match e.raw_os_error() {
            Some(code) => Arg::Errno(code),
            None => Arg::display(e),
        }
    }

    /// `v` as its `Display` writes it, into the record (at most [`TEXT_BYTES`] bytes).
    /// Formats on the calling thread into the record itself: no allocation, as long as
    /// `v`'s `Display` makes none (an operating-system `io::Error`'s does: use
    /// [`io`](Self::io)).
    pub fn display(v: &dyn fmt::Display) -> Arg {
        let mut t = Inline::empty();
        let _ = write!(t, "{v}");
        Arg::Text(t)
    }
}

macro_rules! arg_from {
    ($variant:ident, $as:ty: $($t:ty),+) => {
        $(impl From<$t> for Arg {
            fn from(v: $t) -> Arg {
                Arg::$variant(<$as>::from(v))
            }
        })+
    };
}
arg_from!(Int, i64: i8, i16, i32, i64);
arg_from!(Uint, u64: u8, u16, u32, u64);
arg_from!(Float, f64: f32, f64);
arg_from!(Bool, bool: bool);

impl From<usize> for Arg {
    fn from(v: usize) -> Arg {
        Arg::Uint(u64::try_from(v).unwrap_or(u64::MAX))
    }
}

impl From<&'static str> for Arg {
    fn from(v: &'static str) -> Arg {
        Arg::Static(v)
    }
}

impl fmt::Display for Arg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Arg::Int(v) => write!(f, "{v}"),
            Arg::Uint(v) => write!(f, "{v}"),
            Arg::Float(v) => write!(f, "{v}"),
            Arg::Bool(v) => write!(f, "{v}"),
            Arg::Static(s) => f.write_str(s),
            Arg::Errno(code) => write!(f, "{}", std::io::Error::from_raw_os_error(*code)),
            Arg::Text(t) => {
                f.write_str(t.as_str())?;
                if t.cut { f.write_str("…") } else { Ok(()) }
            }
        }
    }
}

/// A record as pushed: when, how grave, from where, the message with `{}` for each
/// argument, and the arguments.
#[derive(Clone, Copy)]
pub(crate) struct Record {
    /// Wall-clock time of the push, ns since the Unix epoch.
    pub(crate) at_ns: u64,
    pub(crate) level: super::Level,
    /// The area's index in the registry.
    pub(crate) area: u32,
    pub(crate) message: &'static str,
    pub(crate) args: [Option<Arg>; MAX_ARGS],
    /// Arguments given beyond [`MAX_ARGS`].
    pub(crate) left_out: u8,
}

impl Record {
    /// The message with its arguments in place of the `{}`s: a `{}` without an argument
    /// stays, arguments without a `{}` follow in brackets.
    pub(crate) fn text(&self) -> String {
        let mut out = String::with_capacity(self.message.len() + 32);
        let mut args = self.args.iter().flatten();
        let mut rest = self.message;
        while let Some(at) = rest.find("{}") {
            out.push_str(&rest[..at]);
            match args.next() {
                Some(a) => {
                    let _ = write!(out, "{a}");
                }
                None => out.push_str("{}"),
            }
            rest = &rest[at + 2..];
        }
        out.push_str(rest);
        let extra: Vec<String> = args.map(ToString::to_string).collect();
        if !extra.is_empty() {
            let _ = write!(out, " [{}]", extra.join(", "));
        }
        if self.left_out > 0 {
            let _ = write!(out, " (+{} arguments left out)", self.left_out);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(message: &'static str, args: &[Arg]) -> Record {
        let mut r = Record {
            at_ns: 0,
            level: crate::log::Level::Info,
            area: 0,
            message,
            args: [None; MAX_ARGS],
            left_out: 0,
        };
        for (slot, a) in r.args.iter_mut().zip(args) {
            *slot = Some(*a);
        }
        r
    }

    #[test]
    fn arguments_take_the_places_of_the_braces() {
        let r = record(
            "unit {} failed {} times ({}), last {}",
            &[
                Arg::from(3u8),
                Arg::from(-2i32),
                Arg::from("timeout"),
                Arg::from(0.1f64),
            ],
        );
        assert_eq!(r.text(), "unit 3 failed -2 times (timeout), last 0.1");
        assert_eq!(
            record("{} and {}", &[Arg::from(true)]).text(),
            "true and {}"
        );
        assert_eq!(
            record("plain", &[Arg::from(1u32), Arg::text("x")]).text(),
            "plain [1, x]"
        );
    }

    #[test]
    fn long_text_is_cut_at_a_character() {
        let long = "é".repeat(100);
        let a = Arg::text(&long);
        let shown = a.to_string();
        assert!(shown.ends_with('…'), "{shown}");
        assert_eq!(shown.chars().count(), TEXT_BYTES / 2 + 1);
        let e = std::io::Error::other("x".repeat(200));
        assert_eq!(
            Arg::display(&e).to_string().len(),
            TEXT_BYTES + '…'.len_utf8()
        );
        assert_eq!(Arg::display(&42).to_string(), "42");
        let refused = std::io::Error::from_raw_os_error(111);
        assert_eq!(Arg::io(&refused).to_string(), refused.to_string());
    }

    #[test]
    fn a_long_text_goes_whole_into_chunks() {
        let long: String = (0..250u8).map(|i| char::from(b'a' + i % 26)).collect();
        let [a, b, c] = Arg::chunks(&long);
        assert_eq!(record("{}{}{}", &[a, b, c]).text(), long);
        let [x, y] = Arg::chunks(&long);
        let shown = record("{}{}", &[x, y]).text();
        assert!(shown.ends_with('…'), "{shown}");
        assert!(long.starts_with(shown.trim_end_matches('…')));
        let [p, q] = Arg::chunks(&"short");
        assert_eq!(record("{}{}", &[p, q]).text(), "short");
        let accents = "é".repeat(100);
        let [u, v, w] = Arg::chunks(&accents);
        assert_eq!(record("{}{}{}", &[u, v, w]).text(), accents);
        let e = std::io::Error::other("y".repeat(150));
        let [m, n] = Arg::chunks(&e);
        assert_eq!(record("{}{}", &[m, n]).text(), e.to_string());
    }

    #[test]
    fn floats_read_back_the_same() {
        let x = 0.1 + 0.2;
        assert_eq!(Arg::from(x).to_string().parse::<f64>().unwrap(), x);
    }
}
