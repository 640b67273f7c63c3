//! The statements of a DBC file, read from its tokens by their keywords (see the module
//! [`dbc`](super)).

mod finish;

use super::lex::{Tok, Token, tokens};
use super::{DbcError, DbcSignal, Message, Mux};
use crate::signal::{ByteOrder, MAX_PAYLOAD, Signal, SignalError};
use finish::finish;
use std::collections::HashSet;

/// The extended-id flag DBC files put on 29-bit ids.
const EXTENDED: u64 = 0x8000_0000;

/// The pseudo-message CANdb++ writes for signals placed in no message.
const PSEUDO_MESSAGE: &str = "VECTOR__INDEPENDENT_SIG_MSG";

/// Keywords that begin a statement (a token that is one and first on its line ends the
/// statement before it).
const KEYWORDS: &[&str] = &[
    "VERSION",
    "NS_",
    "BS_",
    "BU_",
    "BO_",
    "SG_",
    "EV_",
    "CM_",
    "BA_DEF_",
    "BA_DEF_DEF_",
    "BA_",
    "VAL_",
    "VAL_TABLE_",
    "SIG_VALTYPE_",
    "SIGTYPE_VALTYPE_",
    "BO_TX_BU_",
    "SIG_GROUP_",
    "SGTYPE_",
    "SGTYPE_VAL_",
    "SIG_TYPE_REF_",
    "BA_DEF_SGTYPE_",
    "BA_SGTYPE_",
    "BA_DEF_REL_",
    "BA_REL_",
    "BA_DEF_DEF_REL_",
    "BU_SG_REL_",
    "BU_EV_REL_",
    "BU_BO_REL_",
    "SG_MUL_VAL_",
    "ENVVAR_DATA_",
    "EV_DATA_",
    "CAT_DEF_",
    "CAT_",
    "FILTER",
];

/// A signal's value type, comment and descriptions, by (message id as written, name).
type SignalKey = (u64, String);

/// What statements after the messages say about them, applied at the end.
#[derive(Default)]
struct Extras {
    kinds: Vec<(SignalKey, u64, usize)>,
    signal_comments: Vec<(SignalKey, String)>,
    message_comments: Vec<(u64, String)>,
    values: Vec<(SignalKey, Vec<(i64, String)>)>,
    cycles: Vec<(u64, f64)>,
    default_cycle: Option<f64>,
    extended_mux: Vec<u64>,
    /// `VFrameFormat`: its enum's names (`BA_DEF_`), its default (`BA_DEF_DEF_`) and each
    /// message's value (`BA_`, an index into the names).
    frame_format_names: Vec<String>,
    frame_format_default: Option<String>,
    frame_formats: Vec<(u64, u64)>,
}

/// A message being read, with its id as written (flag included).
struct Raw {
    id: u64,
    message: Message,
    /// A pseudo-message (read, then left out).
    pseudo: bool,
    /// Its signals' names (a repeated one is found without a scan of them all).
    names: HashSet<String>,
}

struct Parser<'a> {
    file: &'a str,
    toks: Vec<Token<'a>>,
    at: usize,
}

type Step<T> = Result<T, (usize, String)>;

impl<'a> Parser<'a> {
    fn peek(&self) -> Option<&Token<'a>> {
        self.toks.get(self.at)
    }

    fn line(&self) -> usize {
        self.peek()
            .or_else(|| self.toks.last())
            .map_or(0, |t| t.line)
    }

    fn next(&mut self) -> Option<&Token<'a>> {
        let t = self.toks.get(self.at);
        self.at += usize::from(t.is_some());
        t
    }

    fn fail<T>(&self, what: &str) -> Step<T> {
        let found = match self.peek().map(|t| &t.tok) {
            None => "the end of the file".to_string(),
            Some(Tok::Ident(s)) => format!("{s:?}"),
            Some(Tok::Num(n)) => n.to_string(),
            Some(Tok::Str(_)) => "a string".to_string(),
            Some(Tok::Punct(c)) => format!("{c:?}"),
        };
        Err((self.line(), format!("expected {what}, found {found}")))
    }

    fn ident(&mut self, what: &str) -> Step<&'a str> {
        match self.peek().map(|t| &t.tok) {
            Some(Tok::Ident(s)) => {
                let s = *s;
                self.at += 1;
                Ok(s)
            }
            _ => self.fail(what),
        }
    }

    fn num(&mut self, what: &str) -> Step<&'a str> {
        match self.peek().map(|t| &t.tok) {
            Some(Tok::Num(s)) => {
                let s = *s;
                self.at += 1;
                Ok(s)
            }
            _ => self.fail(what),
        }
    }

    fn float(&mut self, what: &str) -> Step<f64> {
        let line = self.line();
        let n = self.num(what)?;
        n.parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| (line, format!("{what} {n:?} is not a number")))
    }

    fn uint(&mut self, what: &str) -> Step<u64> {
        let line = self.line();
        let n = self.num(what)?;
        n.parse::<u64>()
            .map_err(|_| (line, format!("{what} {n:?} is not a whole number")))
    }

    fn punct(&mut self, c: char) -> Step<()> {
        match self.peek().map(|t| &t.tok) {
            Some(Tok::Punct(p)) if *p == c => {
                self.at += 1;
                Ok(())
            }
            _ => self.fail(&format!("{c:?}")),
        }
    }

    fn maybe(&mut self, c: char) -> bool {
        let yes = matches!(self.peek().map(|t| &t.tok), Some(Tok::Punct(p)) if *p == c);
        self.at += usize::from(yes);
        yes
    }

    fn string(&mut self, what: &str) -> Step<String> {
        match self.peek().map(|t| &t.tok) {
            Some(Tok::Str(s)) => {
                let s = s.clone();
                self.at += 1;
                Ok(s)
            }
            _ => self.fail(what),
        }
    }

    /// True at a token that begins a statement.
    fn at_statement(&self) -> bool {
        self.peek()
            .is_some_and(|t| t.first && matches!(t.tok, Tok::Ident(k) if KEYWORDS.contains(&k)))
    }

    /// Skips to the next statement (past a `;` ending this one, or to a keyword that is
    /// first on its line); nothing when already there.
    fn skip_statement(&mut self) {
        if self.at_statement() {
            return;
        }
        while let Some(t) = self.peek() {
            if matches!(t.tok, Tok::Punct(';')) {
                self.at += 1;
                return;
            }
            self.at += 1;
            if self.at_statement() {
                return;
            }
        }
    }

    /// The rest of the line (receivers, node lists): skipped.
    fn skip_line(&mut self) {
        while self.peek().is_some_and(|t| !t.first) {
            self.at += 1;
        }
    }

    fn error(&self, line: usize, signal: Option<&str>, problem: String) -> DbcError {
        DbcError {
            file: self.file.to_string(),
            line,
            signal: signal.map(String::from),
            problem,
        }
    }
}

/// The messages of DBC `text`.
pub(super) fn messages(file: &str, text: &str) -> Result<Vec<Message>, DbcError> {
    let toks = tokens(text).map_err(|e| DbcError {
        file: file.to_string(),
        line: e.line,
        signal: None,
        problem: e.problem,
    })?;
    let mut p = Parser { file, toks, at: 0 };
    let mut raws: Vec<Raw> = Vec::new();
    let mut extras = Extras::default();
    while let Some(t) = p.next() {
        let (line, tok) = (t.line, t.tok.clone());
        let keyword = match tok {
            Tok::Ident(k) => k,
            // Stray text between statements: skipped.
            _ => continue,
        };
        let result = match keyword {
            "BO_" => message(&mut p, line).map(|r| raws.push(r)),
            "SG_" => match raws.last_mut() {
                Some(r) => {
                    // The signal's name, if it has one, for the error.
                    let name = match p.peek().map(|t| &t.tok) {
                        Some(Tok::Ident(n)) => Some(n.to_string()),
                        _ => None,
                    };
                    if let Err((l, why)) = signal(&mut p, r, line) {
                        let e = p.error(l, name.as_deref(), why);
                        r.message.problems.push(e);
                        p.skip_statement();
                    }
                    Ok(())
                }
                None => Err((
                    line,
                    "a signal outside any message (no BO_ before it)".into(),
                )),
            },
            "NS_" => {
                ns(&mut p);
                Ok(())
            }
            "CM_" => comment(&mut p, &mut extras),
            "BA_DEF_" => attribute_definition(&mut p, &mut extras),
            "BA_DEF_DEF_" => attribute_default(&mut p, &mut extras),
            "BA_" => attribute(&mut p, &mut extras),
            "VAL_" => values(&mut p, &mut extras),
            "SIG_VALTYPE_" => value_type(&mut p, &mut extras, line),
            "SG_MUL_VAL_" => {
                let id = p.uint("a message id");
                if let Ok(id) = id {
                    extras.extended_mux.push(id);
                }
                p.skip_statement();
                Ok(())
            }
            _ => {
                p.skip_statement();
                Ok(())
            }
        };
        // A statement that does not parse outside a message is skipped: nothing maps it.
        if result.is_err() {
            p.skip_statement();
        }
    }
    Ok(finish(raws, extras, &p))
}

/// `NS_ :` and its list of symbols (each alone on its line).
fn ns(p: &mut Parser<'_>) {
    p.maybe(':');
    while let Some(t) = p.peek() {
        let alone = p.toks.get(p.at + 1).is_none_or(|n| n.first);
        match t.tok {
            Tok::Ident(k) if alone && !matches!(k, "BS_" | "BU_" | "BO_") => p.at += 1,
            _ => return,
        }
    }
}

/// `BO_ 291 EngineData: 8 ECU`
fn message(p: &mut Parser<'_>, line: usize) -> Step<Raw> {
    let id = p.uint("a message id")?;
    let name = p.ident("a message name")?.to_string();
    p.punct(':')?;
    let length = p.uint("a payload length")?;
    p.skip_line();
    let extended = id & EXTENDED != 0;
    let can_id = id & !EXTENDED;
    let mut problems = Vec::new();
    let pseudo = name == PSEUDO_MESSAGE;
    if !pseudo {
        // Whether the length fits the frame is the map's to say: a classic frame has 8
        // bytes, an FD frame 64, a J1939 message up to what a signal can sit in.
        if length > MAX_PAYLOAD as u64 {
            problems.push(p.error(
                line,
                None,
                format!(
                    "message {name}: {length} bytes is more than hwgw maps ({MAX_PAYLOAD}, a J1939 message; a CAN FD frame carries 64)"
                ),
            ));
        }
        if (!extended && can_id > 0x7FF) || can_id > 0x1FFF_FFFF {
            problems.push(p.error(
                line,
                None,
                format!(
                    "message {name}: id {can_id:#x} does not fit a {} id",
                    if extended { "29-bit" } else { "11-bit" }
                ),
            ));
        }
    }
    Ok(Raw {
        id,
        pseudo,
        names: HashSet::new(),
        message: Message {
            id: (can_id & 0x1FFF_FFFF) as u32,
            extended,
            fd: false,
            name,
            length: length.min(MAX_PAYLOAD as u64) as usize,
            signals: Vec::new(),
            line,
            cycle: None,
            comment: None,
            extended_mux: false,
            problems,
        },
    })
}

/// `SG_ EngineTemp [M|m3] : 16|8@1+ (1,-40) [-40|215] "degC" Gateway`
fn signal(p: &mut Parser<'_>, r: &mut Raw, line: usize) -> Step<()> {
    let name = p.ident("a signal name")?.to_string();
    let mut mux = Mux::Plain;
    if let Some(Tok::Ident(m)) = p.peek().map(|t| &t.tok) {
        let m = *m;
        p.at += 1;
        mux = match m {
            "M" => Mux::Multiplexer,
            _ => {
                let digits = m.strip_prefix('m').unwrap_or("");
                let (k, rest) = digits.split_at(
                    digits
                        .find(|c: char| !c.is_ascii_digit())
                        .unwrap_or(digits.len()),
                );
                let k: u64 = k.parse().map_err(|_| {
                    (
                        line,
                        format!("multiplexer indicator {m:?}: expected M or m<value>"),
                    )
                })?;
                match rest {
                    "" => Mux::When(k),
                    "M" => {
                        // Both multiplexed and a multiplexer: extended multiplexing.
                        r.message.extended_mux = true;
                        Mux::When(k)
                    }
                    _ => {
                        return Err((
                            line,
                            format!("multiplexer indicator {m:?}: expected M or m<value>"),
                        ));
                    }
                }
            }
        };
    }
    p.punct(':')?;
    let start = p.uint("a start bit")?;
    p.punct('|')?;
    let length = p.uint("a length")?;
    p.punct('@')?;
    let order = match p.num("a byte order (@1 or @0)")? {
        "1" => ByteOrder::Intel,
        "0" => ByteOrder::Motorola,
        o => {
            return Err((
                line,
                format!("byte order @{o}: expected @1 (Intel) or @0 (Motorola)"),
            ));
        }
    };
    let signed = if p.maybe('-') {
        true
    } else if p.maybe('+') {
        false
    } else {
        return p.fail("+ or - (the sign)");
    };
    p.punct('(')?;
    let factor = p.float("a factor")?;
    p.punct(',')?;
    let offset = p.float("an offset")?;
    p.punct(')')?;
    p.punct('[')?;
    let min = p.float("a minimum")?;
    p.punct('|')?;
    let max = p.float("a maximum")?;
    p.punct(']')?;
    let unit = p.string("the unit (a string)")?;
    p.skip_line();
    let as_u32 = |v: u64, what: &str| {
        u32::try_from(v).map_err(|_| (line, format!("{what} {v} is too large")))
    };
    let signal = Signal::new(
        as_u32(start, "start bit")?,
        as_u32(length, "length")?,
        order,
        signed,
        factor,
        offset,
        &unit,
    )
    .map_err(|e: SignalError| (line, e.to_string()))?;
    if r.pseudo {
        return Ok(());
    }
    let m = &mut r.message;
    if signal.bytes_needed() > m.length {
        return Err((
            line,
            format!(
                "it reaches byte {} but message {} has {} bytes",
                signal.bytes_needed(),
                m.name,
                m.length
            ),
        ));
    }
    if !r.names.insert(name.clone()) {
        return Err((
            line,
            format!("message {} already has a signal of that name", m.name),
        ));
    }
    m.signals.push(DbcSignal {
        name,
        signal,
        min,
        max,
        line,
        mux,
        comment: None,
        values: Vec::new(),
    });
    Ok(())
}

/// `CM_ [BU_ n | BO_ id | SG_ id name | EV_ n] "text" ;`
fn comment(p: &mut Parser<'_>, x: &mut Extras) -> Step<()> {
    match p.peek().map(|t| t.tok.clone()) {
        Some(Tok::Ident("BO_")) => {
            p.at += 1;
            let id = p.uint("a message id")?;
            let text = p.string("a comment")?;
            x.message_comments.push((id, text));
        }
        Some(Tok::Ident("SG_")) => {
            p.at += 1;
            let id = p.uint("a message id")?;
            let name = p.ident("a signal name")?.to_string();
            let text = p.string("a comment")?;
            x.signal_comments.push(((id, name), text));
        }
        _ => {}
    }
    p.skip_statement();
    Ok(())
}

/// `BA_DEF_ BO_ "VFrameFormat" ENUM "StandardCAN","ExtendedCAN",…,"StandardCAN_FD";`
/// (other definitions are skipped)
fn attribute_definition(p: &mut Parser<'_>, x: &mut Extras) -> Step<()> {
    if matches!(p.peek().map(|t| &t.tok), Some(Tok::Ident("BO_"))) {
        p.at += 1;
        if p.string("an attribute name")? == "VFrameFormat"
            && matches!(p.peek().map(|t| &t.tok), Some(Tok::Ident("ENUM")))
        {
            p.at += 1;
            let mut names = Vec::new();
            while let Some(Tok::Str(_)) = p.peek().map(|t| &t.tok) {
                names.push(p.string("a frame format")?);
                p.maybe(',');
            }
            x.frame_format_names = names;
        }
    }
    p.skip_statement();
    Ok(())
}

/// `BA_DEF_DEF_ "GenMsgCycleTime" 100;`, `BA_DEF_DEF_ "VFrameFormat" "StandardCAN";`
fn attribute_default(p: &mut Parser<'_>, x: &mut Extras) -> Step<()> {
    match p.string("an attribute name")?.as_str() {
        "GenMsgCycleTime" => x.default_cycle = p.float("a cycle time").ok(),
        "VFrameFormat" => x.frame_format_default = p.string("a frame format").ok(),
        _ => {}
    }
    p.skip_statement();
    Ok(())
}

/// `BA_ "GenMsgCycleTime" BO_ 291 100;`, `BA_ "VFrameFormat" BO_ 291 14;`
fn attribute(p: &mut Parser<'_>, x: &mut Extras) -> Step<()> {
    let name = p.string("an attribute name")?;
    let of_message = matches!(p.peek().map(|t| &t.tok), Some(Tok::Ident("BO_")));
    if of_message && (name == "GenMsgCycleTime" || name == "VFrameFormat") {
        p.at += 1;
        let id = p.uint("a message id")?;
        if name == "GenMsgCycleTime" {
            x.cycles.push((id, p.float("a cycle time")?));
        } else {
            x.frame_formats.push((id, p.uint("a frame format")?));
        }
    }
    p.skip_statement();
    Ok(())
}

/// `VAL_ 291 Gear 0 "P" 1 "R" 2 "N" 3 "D" ;` (an environment variable's, without an id,
/// is skipped)
fn values(p: &mut Parser<'_>, x: &mut Extras) -> Step<()> {
    if !matches!(p.peek().map(|t| &t.tok), Some(Tok::Num(_))) {
        p.skip_statement();
        return Ok(());
    }
    let id = p.uint("a message id")?;
    let name = p.ident("a signal name")?.to_string();
    let mut list = Vec::new();
    while let Some(Tok::Num(n)) = p.peek().map(|t| &t.tok) {
        let line = p.line();
        // An unsigned 64-bit signal's values above 2^63 - 1 are kept as their bits, as
        // the signal's raw values are.
        let v = n
            .parse::<i64>()
            .ok()
            .or_else(|| n.parse::<u64>().ok().map(|u| u as i64))
            .or_else(|| {
                n.parse::<f64>()
                    .ok()
                    .filter(|f| f.fract() == 0.0 && f.abs() < 9e18)
                    .map(|f| f as i64)
            })
            .ok_or_else(|| (line, format!("value {n:?} is not a whole number")))?;
        p.at += 1;
        list.push((v, p.string("a value's description")?));
    }
    p.skip_statement();
    x.values.push(((id, name), list));
    Ok(())
}

/// `SIG_VALTYPE_ 291 Speed : 1;`
fn value_type(p: &mut Parser<'_>, x: &mut Extras, line: usize) -> Step<()> {
    let id = p.uint("a message id")?;
    let name = p.ident("a signal name")?.to_string();
    p.maybe(':');
    let kind = p.uint("a value type (1 float, 2 double)")?;
    x.kinds.push(((id, name), kind, line));
    p.skip_statement();
    Ok(())
}
