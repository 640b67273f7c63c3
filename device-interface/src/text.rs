//! Values as error messages show them: numbers short (`1e308`, not 309 digits; `NaN` and
//! `inf` by name) and long strings cut, so no message a user's value lands in grows with
//! it. Every crate's configuration and device errors print values through these.
//!
//! ```
//! use device_interface::text::{Number, Quoted, non_finite};
//!
//! assert_eq!(Number(1e308).to_string(), "1e308");
//! assert_eq!(Number(-2.5).to_string(), "-2.5");
//! assert_eq!(Number(f64::NAN).to_string(), "NaN");
//! assert_eq!(Number(f64::NEG_INFINITY).to_string(), "-inf");
//! assert_eq!(Quoted("pump").to_string(), "\"pump\"");
//! let long = "x".repeat(1000);
//! assert_eq!(Quoted(&long).to_string(), format!("\"{}…\" (1000 characters)", "x".repeat(80)));
//! assert_eq!(non_finite(f64::NAN), Some("is NaN"));
//! assert_eq!(non_finite(f64::INFINITY), Some("is infinite"));
//! assert_eq!(non_finite(1.0), None);
//! ```

use std::fmt;

/// The most characters of a string an error shows; the rest is cut and counted.
pub const SHOWN_CHARS: usize = 80;

/// A number as people read it: plain where that is short, else in exponent form (`1e308`,
/// `5e-324`); `NaN`, `inf` and `-inf` by name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Number(pub f64);

impl fmt::Display for Number {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let v = self.0;
        if v.is_nan() {
            f.write_str("NaN")
        } else if v.is_infinite() {
            f.write_str(if v > 0.0 { "inf" } else { "-inf" })
        } else if v != 0.0 && !(1e-5..1e15).contains(&v.abs()) {
            write!(f, "{v:e}")
        } else {
            write!(f, "{v}")
        }
    }
}

/// Why a number is not one a setting can take, as the message's words: `"is NaN"` or
/// `"is infinite"`; `None` for a finite number.
pub fn non_finite(v: f64) -> Option<&'static str> {
    if v.is_nan() {
        Some("is NaN")
    } else if v.is_infinite() {
        Some("is infinite")
    } else {
        None
    }
}

/// A string in quotes, escaped as Rust's `{:?}` does, and cut after [`SHOWN_CHARS`]
/// characters with an ellipsis and its full length (`"xxxx…" (10000000 characters)`).
#[derive(Debug, Clone, Copy)]
pub struct Quoted<'a>(pub &'a str);

impl fmt::Display for Quoted<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match cut(self.0) {
            None => write!(f, "{:?}", self.0),
            Some((head, n)) => {
                let shown = format!("{head:?}");
                let inner = shown.strip_suffix('"').unwrap_or(&shown);
                write!(f, "{inner}…\" ({n} characters)")
            }
        }
    }
}

/// A string as it is, cut after [`SHOWN_CHARS`] characters with an ellipsis and its full
/// length (`xxxx… (10000000 characters)`).
#[derive(Debug, Clone, Copy)]
pub struct Cut<'a>(pub &'a str);

impl fmt::Display for Cut<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match cut(self.0) {
            None => f.write_str(self.0),
            Some((head, n)) => write!(f, "{head}… ({n} characters)"),
        }
    }
}

/// `s`'s first [`SHOWN_CHARS`] characters and its length in characters, when it is longer.
fn cut(s: &str) -> Option<(&str, usize)> {
    let (end, _) = s.char_indices().nth(SHOWN_CHARS)?;
    Some((&s[..end], s.chars().count()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_short() {
        for (v, text) in [
            (0.0, "0"),
            (-0.0, "-0"),
            (1.0, "1"),
            (0.1, "0.1"),
            (123456.75, "123456.75"),
            (1e15, "1e15"),
            (-1.7e308, "-1.7e308"),
            (f64::MAX, "1.7976931348623157e308"),
            (5e-324, "5e-324"),
            (0.00001, "0.00001"),
            (0.000001, "1e-6"),
        ] {
            assert_eq!(Number(v).to_string(), text, "{v:?}");
        }
    }

    #[test]
    fn long_strings_are_cut_and_counted() {
        assert_eq!(Cut("short").to_string(), "short");
        let s = "é".repeat(81);
        assert_eq!(
            Cut(&s).to_string(),
            format!("{}… (81 characters)", "é".repeat(80))
        );
        assert_eq!(Quoted("a\"b").to_string(), "\"a\\\"b\"");
        let q = Quoted(&"\n".repeat(100)).to_string();
        assert_eq!(q, format!("\"{}…\" (100 characters)", "\\n".repeat(80)));
    }
}
