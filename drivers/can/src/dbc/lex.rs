//! The tokens of a DBC file: identifiers (keywords, names, multiplexer indicators such as
//! `M` and `m3`), numbers (with sign, fraction and exponent), strings (which may span lines
//! and escape `"` and `\` with a backslash) and single punctuation characters, each with
//! the line it is on and whether it is the first token of that line. White space between
//! tokens is free: `0|8@1+(1,0)` and `0 | 8 @ 1 + ( 1 , 0 )` are the same tokens.

/// What a token is.
#[derive(Debug, Clone, PartialEq)]
pub enum Tok<'a> {
    /// A name or keyword.
    Ident(&'a str),
    /// A number as written.
    Num(&'a str),
    /// A string's text, escapes resolved.
    Str(String),
    /// Any other character (`:`, `;`, `|`, `@`, `+`, `-`, `(`, `)`, `[`, `]`, `,`, …).
    Punct(char),
}

/// A token and where it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Token<'a> {
    /// The token.
    pub tok: Tok<'a>,
    /// Its line, from 1.
    pub line: usize,
    /// True when nothing but white space precedes it on its line.
    pub first: bool,
}

/// The longest string taken (a comment may be long; a runaway one stops here).
pub const MAX_STRING: usize = 1 << 20;

/// The most tokens taken from one file: a 16 MiB DBC file of real statements has about
/// three million; more is a file of stray characters, and the tokens' memory (at most
/// this many times `size_of::<Token>()`, 40 bytes: 160 MB) stops here.
pub const MAX_TOKENS: usize = 4_000_000;

/// Why the text could not be cut into tokens.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LexError {
    /// The line where the trouble starts.
    pub line: usize,
    /// What is wrong.
    pub problem: String,
}

/// The tokens of `text`.
pub fn tokens(text: &str) -> Result<Vec<Token<'_>>, LexError> {
    let bytes = text.as_bytes();
    let mut out = Vec::new();
    let (mut i, mut line, mut first) = (0usize, 1usize, true);
    while i < bytes.len() {
        let c = bytes[i];
        if c == b'\n' {
            line += 1;
            first = true;
            i += 1;
            continue;
        }
        if c.is_ascii_whitespace() {
            i += 1;
            continue;
        }
        if out.len() >= MAX_TOKENS {
            return Err(LexError {
                line,
                problem: format!("more than {MAX_TOKENS} tokens (not a DBC file of statements)"),
            });
        }
        let start = i;
        let tok = if c.is_ascii_alphabetic() || c == b'_' {
            while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                i += 1;
            }
            Tok::Ident(&text[start..i])
        } else if c.is_ascii_digit() || starts_signed_number(bytes, i) {
            i = number_end(bytes, i);
            Tok::Num(&text[start..i])
        } else if c == b'"' {
            let (s, end, lines) = string(text, i).map_err(|problem| LexError { line, problem })?;
            i = end;
            let tok = Tok::Str(s);
            out.push(Token { tok, line, first });
            line += lines;
            first = false;
            continue;
        } else {
            // One character, whatever it is (a multi-byte one whole).
            let ch = text[i..].chars().next().unwrap_or('?');
            i += ch.len_utf8();
            Tok::Punct(ch)
        };
        out.push(Token { tok, line, first });
        first = false;
    }
    Ok(out)
}

/// A `+` or `-` that begins a number (followed by a digit, or a point and a digit).
fn starts_signed_number(b: &[u8], i: usize) -> bool {
    let digit = |k: usize| b.get(k).is_some_and(u8::is_ascii_digit);
    matches!(b[i], b'+' | b'-') && (digit(i + 1) || (b.get(i + 1) == Some(&b'.') && digit(i + 2)))
        || (b[i] == b'.' && digit(i + 1))
}

/// The end of the number at `i`: sign, digits, fraction, exponent.
fn number_end(b: &[u8], mut i: usize) -> usize {
    if matches!(b[i], b'+' | b'-') {
        i += 1;
    }
    while i < b.len() && (b[i].is_ascii_digit() || b[i] == b'.') {
        i += 1;
    }
    if i < b.len() && matches!(b[i], b'e' | b'E') {
        let mut k = i + 1;
        if k < b.len() && matches!(b[k], b'+' | b'-') {
            k += 1;
        }
        if k < b.len() && b[k].is_ascii_digit() {
            while k < b.len() && b[k].is_ascii_digit() {
                k += 1;
            }
            i = k;
        }
    }
    i
}

/// The string opening at `i`: its text, the index past its closing quote, and the line
/// breaks inside it.
fn string(text: &str, i: usize) -> Result<(String, usize, usize), String> {
    let mut s = String::new();
    let mut lines = 0;
    let mut chars = text[i + 1..].char_indices();
    while let Some((k, ch)) = chars.next() {
        match ch {
            '"' => return Ok((s, i + 1 + k + 1, lines)),
            '\\' => match chars.next() {
                Some((_, e @ ('"' | '\\'))) => s.push(e),
                Some((_, e)) => {
                    if e == '\n' {
                        lines += 1;
                    }
                    s.push('\\');
                    s.push(e);
                }
                None => break,
            },
            _ => {
                if ch == '\n' {
                    lines += 1;
                }
                if s.len() >= MAX_STRING {
                    return Err(format!("a string longer than {MAX_STRING} bytes"));
                }
                s.push(ch);
            }
        }
    }
    Err("a string that is not closed (no \" before the end of the file)".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn toks(text: &str) -> Vec<Tok<'_>> {
        match tokens(text) {
            Ok(t) => t.into_iter().map(|t| t.tok).collect(),
            Err(e) => panic!("{e:?}"),
        }
    }

    #[test]
    fn spacing_does_not_matter() {
        let a = toks(r#"SG_ A : 0|8@1+ (1,0) [0|255] "V" X"#);
        let b = toks(r#"SG_ A:0|8@1+(1,0)[0|255]"V" X"#);
        assert_eq!(a, b);
        assert_eq!(
            toks("(0.5,-40) [-1.5e3|+2E-2] @0-"),
            [
                Tok::Punct('('),
                Tok::Num("0.5"),
                Tok::Punct(','),
                Tok::Num("-40"),
                Tok::Punct(')'),
                Tok::Punct('['),
                Tok::Num("-1.5e3"),
                Tok::Punct('|'),
                Tok::Num("+2E-2"),
                Tok::Punct(']'),
                Tok::Punct('@'),
                Tok::Num("0"),
                Tok::Punct('-'),
            ]
        );
    }

    #[test]
    fn strings_span_lines_and_escape() {
        let t = match tokens("CM_ SG_ 1 A \"two\nlines \\\"quoted\\\"\";\nBO_") {
            Ok(t) => t,
            Err(e) => panic!("{e:?}"),
        };
        assert_eq!(t[4].tok, Tok::Str("two\nlines \"quoted\"".into()));
        assert_eq!(
            (t[6].tok.clone(), t[6].line, t[6].first),
            (Tok::Ident("BO_"), 3, true)
        );
        assert!(tokens("CM_ \"never closed").is_err());
    }
}
