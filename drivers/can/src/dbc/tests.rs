//! The DBC reader against the files tools write: every section keyword, the syntax
//! variants cantools accepts, multiplexing, floats, 64-bit values, encodings; problems kept
//! with their message; and hostile text (a seeded fuzz run: never a panic).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use super::*;
use crate::signal::ValueKind;
use testkit::rng::Rng;

const DBC: &str = r#"VERSION ""

NS_ :
    NS_DESC_
    CM_
    BA_DEF_
    BA_
    VAL_
    CAT_DEF_
    CAT_
    FILTER
    BA_DEF_DEF_
    EV_DATA_
    ENVVAR_DATA_
    SGTYPE_
    SGTYPE_VAL_
    BA_DEF_SGTYPE_
    BA_SGTYPE_
    SIG_TYPE_REF_
    VAL_TABLE_
    SIG_GROUP_
    SIG_VALTYPE_
    SIGTYPE_VALTYPE_
    BO_TX_BU_
    BA_DEF_REL_
    BA_REL_
    BA_DEF_DEF_REL_
    BU_SG_REL_
    BU_EV_REL_
    BU_BO_REL_
    SG_MUL_VAL_

BS_:

BU_: ECU Gateway

VAL_TABLE_ OnOff 1 "on" 0 "off" ;

BO_ 291 EngineData: 8 ECU
 SG_ EngineTemp : 16|8@1+ (1,-40) [-40|215] "degC" Gateway
 SG_ RPM : 24|16@1+ (0.25,0) [0|16383.75] "rpm" Gateway,ECU
 SG_ Torque : 7|16@0- (0.1,0) [-3276.8|3276.7] "Nm" Gateway

BO_ 2147487744 Extended: 4 ECU
 SG_ Flag : 0|1@1+ (1,0) [0|1] "" Gateway

BO_ 3221225472 VECTOR__INDEPENDENT_SIG_MSG: 0 Vector__XXX
 SG_ Orphan : 0|8@1+ (1,0) [0|0] "" Vector__XXX

BO_TX_BU_ 291 : ECU,Gateway;

EV_ Env1: 0 [0|100] "" 0 1 DUMMY_NODE_VECTOR0 Vector__XXX;

CM_ "the whole file";
CM_ BU_ ECU "the engine controller";
CM_ BO_ 291 "engine state";
CM_ SG_ 291 RPM "engine speed";
CM_ SG_ 291 Torque "a comment
over two lines, with a \"quote\"";
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_ SG_ "GenSigStartValue" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 291 100;
BA_ "GenSigStartValue" SG_ 291 RPM 0;
VAL_ 291 EngineTemp 0 "cold" 200 "hot" ;
VAL_ Env1 0 "zero" ;
SIG_GROUP_ 291 Group 1 : RPM Torque;
"#;

#[test]
fn messages_signals_and_what_the_file_says_of_them() {
    let dbc = Dbc::parse("car.dbc", DBC).unwrap();
    let names: Vec<&str> = dbc.messages.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(
        names,
        ["EngineData", "Extended"],
        "the pseudo-message left out"
    );
    let m = dbc.message("EngineData").unwrap();
    assert_eq!(
        (m.id, m.extended, m.length, m.signals.len()),
        (0x123, false, 8, 3)
    );
    assert!(m.problems.is_empty(), "{:?}", m.problems);
    let payload = [0x12, 0x34, 130, 0x40, 0x1F, 0, 0, 0];
    let decode = |n: &str| m.signal(n).unwrap().signal.decode(&payload).unwrap();
    assert_eq!(decode("EngineTemp"), 90.0);
    assert_eq!(decode("RPM"), 2000.0);
    assert_eq!(decode("Torque"), 466.0, "0x1234 = 4660 * 0.1");
    let t = m.signal("Torque").unwrap();
    assert_eq!((t.min, t.max, t.line), (-3276.8, 3276.7, 42));
    assert_eq!(
        t.comment.as_deref(),
        Some("a comment\nover two lines, with a \"quote\"")
    );
    assert_eq!(
        m.signal("RPM").unwrap().comment.as_deref(),
        Some("engine speed")
    );
    assert_eq!(m.comment.as_deref(), Some("engine state"));
    assert_eq!(
        m.signal("EngineTemp").unwrap().values,
        [(0, "cold".to_string()), (200, "hot".to_string())]
    );
    assert_eq!(m.cycle, Some(Duration::from_millis(100)));
    let e = dbc.message("Extended").unwrap();
    assert_eq!((e.id, e.extended, e.cycle), (0x1000, true, None));
}

/// One message written the ways tools and people write it: every variant reads the same.
#[test]
fn syntax_variants_read_alike() {
    let variants = [
        "BO_ 256 M: 8 X\n SG_ A : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ B : 15|16@0- (0.5,-2) [-10|10] \"V\" Y\n",
        "BO_ 256 M : 8 X\n SG_ A : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ B : 15|16@0- (0.5,-2) [-10|10] \"V\" Y\n",
        "BO_ 256 M:8 X\n SG_ A:0|8@1+(1,0)[0|0]\"\" Y\n SG_ B:15|16@0-(0.5,-2)[-10|10]\"V\" Y\n",
        "BO_ 256 M : 8 X\r\n\tSG_ A : 0 | 8 @ 1 + ( 1 , 0 ) [ 0 | 0 ] \"\" Y\r\n\tSG_ B : 15|16@0- (5E-1,-2.0) [-1e1|1.0e+1] \"V\" Y , Z\r\n",
        "CM_ \"a comment\nSG_ that is not a signal\";\nBO_ 256 M: 8 X\n SG_ A : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ B : 15|16@0- (0.5,-2) [-10|10] \"V\" Y\nCM_ SG_ 256 B \"two\nSG_ lines\";\n",
        "VERSION \"1.0\"\nBS_: 500 : 1,2\nBU_: X Y\nBO_ 256 M: 8 X\n SG_ A : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ B : 15|16@0- (0.5,-2) [-10|10] \"V\" Y\nBA_DEF_ \"BusType\" STRING ;\nBA_ \"BusType\" \"CAN\";\n",
    ];
    for text in variants {
        let dbc = Dbc::parse("v.dbc", text).unwrap_or_else(|e| panic!("{e}: {text:?}"));
        let m = dbc.message("M").unwrap_or_else(|| panic!("no M: {text:?}"));
        assert!(m.problems.is_empty(), "{:?}: {text:?}", m.problems);
        let payload = [7, 0x00, 0x10, 0, 0, 0, 0, 0];
        let b = m.signal("B").unwrap();
        assert_eq!(
            m.signal("A").unwrap().signal.decode(&payload).unwrap(),
            7.0,
            "{text:?}"
        );
        assert_eq!(b.signal.decode(&payload).unwrap(), 6.0, "{text:?}");
        assert_eq!((b.min, b.max), (-10.0, 10.0), "{text:?}");
    }
}

#[test]
fn floats_doubles_and_64_bit_values() {
    let text = "BO_ 301 F: 8 X\n SG_ F32 : 0|32@1- (1,0) [0|0] \"\" Y\n SG_ Rest : 32|32@1+ (2,1) [0|0] \"\" Y\n\
                BO_ 302 D: 8 X\n SG_ F64 : 0|64@1- (1,0) [0|0] \"\" Y\n\
                BO_ 303 U: 8 X\n SG_ U64 : 0|64@1+ (1,0) [0|0] \"\" Y\n\
                SIG_VALTYPE_ 301 F32 : 1;\nSIG_VALTYPE_ 302 F64 : 2;\nSIG_VALTYPE_ 303 U64 : 2;\n";
    let dbc = Dbc::parse("f.dbc", text).unwrap();
    let f = dbc.message("F").unwrap().signal("F32").unwrap();
    assert_eq!(f.signal.kind(), ValueKind::Float32);
    let mut p = [0u8; 8];
    p[..4].copy_from_slice(&1.5f32.to_le_bytes());
    assert_eq!(f.signal.decode(&p).unwrap(), 1.5);
    let d = dbc.message("D").unwrap().signal("F64").unwrap();
    assert_eq!(d.signal.decode(&(-2.25f64).to_le_bytes()).unwrap(), -2.25);
    // SIG_VALTYPE_ 2 on U64 makes it a double too: the last word wins.
    let u = dbc.message("U").unwrap();
    assert_eq!(u.signals[0].signal.kind(), ValueKind::Float64);
    let plain = Dbc::parse(
        "u.dbc",
        "BO_ 303 U: 8 X\n SG_ U64 : 0|64@1+ (1,0) [0|0] \"\" Y\n",
    )
    .unwrap();
    let u = &plain.messages[0].signals[0].signal;
    assert_eq!(u.decode(&[0xFF; 8]).unwrap(), 18446744073709551615.0);
    assert_eq!(u.decode(&[0xFF; 8]).unwrap(), 1.8446744073709552e19);
    // Values above 2^63 are in range when the declared range (or, none declared, the
    // type's) reaches them, and counted out of it when it does not.
    let all = u.extract(&[0xFF; 8]).unwrap();
    assert!(u.in_range(all));
    let ranged = |max: &str| {
        let text = format!("BO_ 303 U: 8 X\n SG_ U64 : 0|64@1+ (1,0) [0|{max}] \"\" Y\n");
        let dbc = Dbc::parse("u.dbc", &text).unwrap();
        let d = &dbc.messages[0].signals[0];
        d.signal.clone().with_limits(d.min, d.max).unwrap()
    };
    assert!(ranged("18446744073709551615").in_range(all));
    assert!(!ranged("1000").in_range(all));
    assert!(ranged("1000").in_range(1000));
    assert!(!ranged("9223372036854775807").in_range(all));
    // A float type on a signal of the wrong length: that message's problem only.
    let bad = Dbc::parse(
        "b.dbc",
        "BO_ 1 B: 8 X\n SG_ S : 0|16@1+ (1,0) [0|0] \"\" Y\nSIG_VALTYPE_ 1 S : 1;\n",
    )
    .unwrap();
    assert_eq!(
        bad.messages[0].problems[0].to_string(),
        "b.dbc:3: signal S: a float signal is 32 bits long, not 16"
    );
}

#[test]
fn multiplexing_simple_and_extended() {
    let text = "BO_ 400 Mux: 8 X\n SG_ Sel M : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ A m1 : 8|16@1+ (1,0) [0|0] \"\" Y\n SG_ B m2 : 8|16@1+ (0.5,0) [0|0] \"\" Y\n SG_ Always : 24|8@1+ (1,0) [0|0] \"\" Y\n\
                BO_ 401 Ext: 8 X\n SG_ S0 M : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ S1 m1M : 8|8@1+ (1,0) [0|0] \"\" Y\n SG_ C m3 : 16|8@1+ (1,0) [0|0] \"\" Y\n\
                SG_MUL_VAL_ 401 C S1 3-3;\n";
    let dbc = Dbc::parse("m.dbc", text).unwrap();
    let m = dbc.message("Mux").unwrap();
    let mux: Vec<Mux> = m.signals.iter().map(|s| s.mux).collect();
    assert_eq!(
        mux,
        [Mux::Multiplexer, Mux::When(1), Mux::When(2), Mux::Plain]
    );
    assert_eq!(m.multiplexer().unwrap().name, "Sel");
    assert!(!m.extended_mux);
    assert!(dbc.message("Ext").unwrap().extended_mux);
}

#[test]
fn can_fd_messages_by_their_frame_format_or_length() {
    // As CANdb++ writes it: the enum's names, a default, and one message's own value.
    let text = "BO_ 100 Classic: 8 X\nBO_ 101 Fd: 8 X\nBO_ 2147483750 Long: 64 X\n\
                BA_DEF_ BO_  \"VFrameFormat\" ENUM  \"StandardCAN\",\"ExtendedCAN\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"StandardCAN_FD\",\"ExtendedCAN_FD\";\n\
                BA_DEF_DEF_  \"VFrameFormat\" \"StandardCAN\";\n\
                BA_ \"VFrameFormat\" BO_ 101 14;\n";
    let dbc = Dbc::parse("fd.dbc", text).unwrap();
    let fd = |name: &str| dbc.message(name).unwrap().fd;
    assert_eq!((fd("Classic"), fd("Fd"), fd("Long")), (false, true, true));
    // Without the enum's definition, Vector's indices; a default of CAN FD for all.
    let bare = Dbc::parse(
        "fd.dbc",
        "BO_ 101 Fd: 8 X\nBA_ \"VFrameFormat\" BO_ 101 15;\n",
    )
    .unwrap();
    assert!(bare.message("Fd").unwrap().fd);
    let all = Dbc::parse(
        "fd.dbc",
        "BO_ 1 A: 8 X\nBA_DEF_DEF_ \"VFrameFormat\" \"StandardCAN_FD\";\n",
    )
    .unwrap();
    assert!(all.message("A").unwrap().fd);
}

#[test]
fn problems_stay_with_their_message() {
    let text = "BO_ 1 Good: 8 X\n SG_ A : 0|8@1+ (1,0) [0|0] \"\" Y\n\
                BO_ 2 Bad: 2 X\n SG_ A : 16|8@1+ (1,0) [0|0] \"\" Y\n SG_ B : 0|8@2+ (1,0) [0|0] \"\" Y\n SG_ C : 0|8@1+ (1;0) [0|0] \"\" Y\n SG_ D : 0|65@1+ (1,0) [0|0] \"\" Y\n SG_ E : 0|8@1+ (0,0) [0|0] \"\" Y\n SG_ F : 0|8@1+ (1,0) [0|0] \"\" Y\n SG_ F : 8|8@1+ (1,0) [0|0] \"\" Y\n\
                BO_ 4096 Wide: 8 X\n\
                BO_ 3 Long: 65537 X\n\
                BO_ 2147483654 J1939: 100 X\n SG_ Last : 792|8@1+ (1,0) [0|0] \"\" Y\n\
                BO_ 5 After: 8 X\n SG_ Z : 0|8@1+ (1,0) [0|0] \"\" Y\n";
    let dbc = Dbc::parse("bad.dbc", text).unwrap();
    assert!(dbc.message("Good").unwrap().problems.is_empty());
    assert!(
        dbc.message("After").unwrap().problems.is_empty(),
        "reading goes on"
    );
    let problems: Vec<String> = dbc
        .message("Bad")
        .unwrap()
        .problems
        .iter()
        .map(ToString::to_string)
        .collect();
    assert_eq!(
        problems,
        [
            "bad.dbc:4: signal A: it reaches byte 3 but message Bad has 2 bytes",
            "bad.dbc:5: signal B: byte order @2: expected @1 (Intel) or @0 (Motorola)",
            "bad.dbc:6: signal C: expected ',', found ';'",
            "bad.dbc:7: signal D: a signal is 1 to 64 bits long, not 65",
            "bad.dbc:8: signal E: factor 0 and offset 0 are invalid: needs a finite non-zero factor and a finite offset",
            "bad.dbc:10: signal F: message Bad already has a signal of that name",
        ]
    );
    assert_eq!(
        dbc.message("Wide").unwrap().problems[0].to_string(),
        "bad.dbc:11: message Wide: id 0x1000 does not fit a 11-bit id"
    );
    assert_eq!(
        dbc.message("Long").unwrap().problems[0].to_string(),
        "bad.dbc:12: message Long: 65537 bytes is more than hwgw maps (65536, a J1939 message; a CAN FD frame carries 64)"
    );
    // Longer than a frame is the map's to judge: a J1939 message may be.
    let j = dbc.message("J1939").unwrap();
    assert!(j.problems.is_empty(), "{:?}", j.problems);
    assert_eq!((j.length, j.signals[0].signal.bytes_needed()), (100, 100));
    // Text that cannot be cut into tokens refuses the file, naming the line.
    let e = Dbc::parse("open.dbc", "BO_ 1 A: 8 X\nCM_ SG_ 1 A \"never\nclosed").unwrap_err();
    assert_eq!(
        e.to_string(),
        "open.dbc:2: a string that is not closed (no \" before the end of the file)"
    );
}

#[test]
fn windows_1252_files_are_read() {
    let dir = std::env::temp_dir().join(format!("hwgw-dbc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("cp1252.dbc");
    let mut bytes = b"BO_ 1 T: 8 X\n SG_ Temp : 0|8@1+ (1,0) [0|0] \"".to_vec();
    bytes.push(0xB0); // degree sign in Windows-1252 (and Latin-1)
    bytes.extend_from_slice(b"C\" Y\nCM_ SG_ 1 Temp \"");
    bytes.push(0x80); // the euro sign, only in Windows-1252
    bytes.extend_from_slice(b"\";\n");
    std::fs::write(&path, &bytes).unwrap();
    let dbc = Dbc::load(&path, Encoding::Auto).unwrap();
    assert_eq!(dbc.encoding, "windows-1252");
    let s = &dbc.messages[0].signals[0];
    assert_eq!(s.signal.scale().unit().as_str(), "°C");
    assert_eq!(s.comment.as_deref(), Some("€"));
    let e = Dbc::load(&path, Encoding::Utf8).unwrap_err().to_string();
    assert!(e.contains("cp1252.dbc:2: not UTF-8 (byte 0xb0)"), "{e}");
    let missing =
        Dbc::load(std::path::Path::new("/nonexistent/car.dbc"), Encoding::Auto).unwrap_err();
    assert!(
        missing
            .to_string()
            .starts_with("/nonexistent/car.dbc: cannot read"),
        "{missing}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The reader's fuzz run: the test file mutated (characters inserted, deleted, replaced by
/// the grammar's own punctuation, keywords and digits) and random text: every result is a
/// value, never a panic. Prints how many texts it read.
#[test]
fn hostile_text_never_panics() {
    // DBC_FUZZ_SCALE multiplies the texts (a longer run by hand: 40 is a million).
    let scale: usize = std::env::var("DBC_FUZZ_SCALE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let mut rng = Rng::new(0xDBC0_F022);
    let pieces = [
        "\"",
        "(",
        ")",
        "[",
        "]",
        "|",
        "@",
        ":",
        ";",
        " ",
        "-",
        "+",
        "9",
        "x",
        "\n",
        "SG_ ",
        "BO_ ",
        "m1",
        " M ",
        "CM_ ",
        "VAL_ ",
        "SIG_VALTYPE_ ",
        "1e309",
        "\\",
    ];
    let base: Vec<char> = DBC.chars().collect();
    let mut read = 0u64;
    for _ in 0..20_000 * scale {
        let mut t = base.clone();
        for _ in 0..=rng.next_u64() % 8 {
            let at = (rng.next_u64() % (t.len() as u64 + 1)) as usize;
            match rng.next_u64() % 3 {
                0 if at < t.len() => {
                    t.remove(at);
                }
                _ => {
                    let p = pieces[(rng.next_u64() % pieces.len() as u64) as usize];
                    for (k, c) in p.chars().enumerate() {
                        t.insert(at + k, c);
                    }
                }
            }
        }
        let text: String = t.into_iter().collect();
        let _ = Dbc::parse("fuzz.dbc", &text);
        read += 1;
    }
    for _ in 0..5_000 * scale {
        let len = (rng.next_u64() % 400) as usize;
        let text: String = (0..len)
            .map(|_| char::from_u32((rng.next_u64() % 128) as u32).unwrap_or(' '))
            .collect();
        let _ = Dbc::parse("random.dbc", &text);
        read += 1;
    }
    println!("DBC reader fuzz: {read} texts, 0 panics");
}

#[test]
fn large_hostile_files_are_read_in_bounded_time_and_memory() {
    use super::lex::{MAX_TOKENS, Token};
    // The token bound's memory, as its doc says.
    assert!(std::mem::size_of::<Token<'_>>() <= 40);
    // Too many tokens: refused with the line, not read into gigabytes.
    let text = "(".repeat(MAX_TOKENS + 1);
    let e = Dbc::parse("paren.dbc", &text).unwrap_err();
    assert!(e.to_string().contains("more than 4000000 tokens"), "{e}");
    // One message of 100 000 signals, each with a comment and a value table: linear.
    let mut text = String::from("BO_ 1 M: 64 X\n");
    for k in 0..100_000 {
        text.push_str(&format!(" SG_ S{k} : 0|1@1+ (1,0) [0|1] \"\" Y\n"));
    }
    for k in 0..100_000 {
        text.push_str(&format!(
            "CM_ SG_ 1 S{k} \"c\";\nVAL_ 1 S{k} 0 \"off\" 1 \"on\";\n"
        ));
    }
    let start = std::time::Instant::now();
    let dbc = Dbc::parse("many.dbc", &text).unwrap();
    let took = start.elapsed();
    let m = dbc.message("M").unwrap();
    assert_eq!(m.signals.len(), 100_000);
    assert_eq!(m.signals[99_999].values.len(), 2);
    // Not a timing assertion: a quadratic reading of this file takes minutes.
    println!("100 000 signals with comments and values read in {took:?}");
}
