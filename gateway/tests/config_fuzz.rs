//! Hostile deployments: the shipped examples mutated at random — values replaced by the
//! extremes of every TOML type (huge, negative, NaN and infinite numbers, empty and
//! 100 000-character strings, empty and long arrays, tables where values go), lines
//! deleted, duplicated and swapped — and checked as `hwgw check` does. Each gets an
//! answer (ok, or its errors) within a bound, never a panic, and checking writes no file.
//! `CONFIG_FUZZ_CASES` sets the cases per example (default 200), `CONFIG_FUZZ_SEED` the
//! seed.

use hwgw::deploy::Gateway;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::mpsc;
use std::time::Duration;
use testkit::rng::Rng;

/// How long one check may take before the test calls it a hang.
const BOUND: Duration = Duration::from_secs(60);

/// What `hwgw check` would say: "ok" or the errors, or the panic's message.
fn check(text: &str, file: &str) -> Result<String, String> {
    catch_unwind(AssertUnwindSafe(|| {
        match Gateway::from_text(text, file, &hwgw::types::Types::builtin()) {
            Ok(_) => "ok".to_string(),
            Err(e) => e,
        }
    }))
    .map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "a panic".into())
    })
}

/// A hostile value of some TOML type.
fn hostile(rng: &mut Rng) -> String {
    let long = format!("\"{}\"", "x".repeat(100_000));
    let many = format!("[{}]", vec!["1"; 10_000].join(","));
    let values = [
        "0",
        "-1",
        "1",
        "9223372036854775807",
        "-9223372036854775808",
        "4294967296",
        "1e308",
        "-1e308",
        "5e-324",
        "nan",
        "inf",
        "-inf",
        "0.5",
        "true",
        "\"\"",
        "\"\\u0000\"",
        "\"ä€\\n\"",
        "\"../../../../../etc/passwd\"",
        "[]",
        "[[]]",
        "{}",
        "{ a = 1 }",
        "1979-05-27T07:32:00Z",
        long.as_str(),
        many.as_str(),
    ];
    rng.pick(&values)
        .map_or_else(String::new, |v| v.to_string())
}

/// Numbers no setting can take, or whose arithmetic overflows: each must get its error,
/// never a panic, a NaN reading or a 309-digit number.
const HOSTILE_NUMBERS: [&str; 13] = [
    "nan",
    "-nan",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1.7e308",
    "-1.7e308",
    "5e-324",
    "1e-308",
    "9007199254740993",
    "-0.0",
    "0",
];

/// Where the numbers of `line` are (outside strings and comments, after its `=`).
fn numbers(line: &str) -> Vec<std::ops::Range<usize>> {
    let b = line.as_bytes();
    let mut out = Vec::new();
    let (mut i, mut quoted, mut value) = (0, false, false);
    while i < b.len() {
        let c = b[i];
        if c == b'"' {
            quoted = !quoted;
        } else if quoted && c == b'\\' {
            i += 1;
        } else if !quoted && c == b'#' {
            break;
        } else if !quoted && c == b'=' {
            value = true;
        } else if !quoted
            && value
            && (c.is_ascii_digit()
                || ((c == b'-' || c == b'+') && b.get(i + 1).is_some_and(u8::is_ascii_digit)))
            && !b[i - 1].is_ascii_alphanumeric()
            && b[i - 1] != b'_'
            && b[i - 1] != b'.'
        {
            let start = i;
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b"_.+-:".contains(&b[i])) {
                i += 1;
            }
            out.push(start..i);
            continue;
        }
        i += 1;
    }
    out
}

/// `text` with 1 to 3 random mutations.
fn mutate(text: &str, rng: &mut Rng) -> String {
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for _ in 0..1 + rng.below(3) {
        if lines.is_empty() {
            break;
        }
        let at = rng.below(lines.len() as u64) as usize;
        match rng.below(5) {
            4 => {
                // A number replaced by a hostile one (a type the key takes: its range and
                // arithmetic are what is tried).
                let found = numbers(&lines[at]);
                if let Some(r) = rng.pick(&found).cloned()
                    && let Some(v) = rng.pick(&HOSTILE_NUMBERS)
                {
                    lines[at].replace_range(r, v);
                }
            }
            0 => {
                // A value replaced (the first `=` of the line: a key, or an inline table's).
                if let Some(eq) = lines[at].find('=') {
                    lines[at] = format!("{}= {}", &lines[at][..eq], hostile(rng));
                }
            }
            1 => {
                lines.remove(at);
            }
            2 => {
                let line = lines[at].clone();
                lines.insert(at, line);
            }
            _ => {
                let other = rng.below(lines.len() as u64) as usize;
                lines.swap(at, other);
            }
        }
    }
    lines.join("\n")
}

/// What an answer's text must never hold, whatever the file said: Rust's `Debug` text, a
/// float printed in full (309 digits for 1e308), a value echoed beyond a bound, NaN taken
/// for "no value".
fn text_problems(answer: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in answer.lines() {
        if line.chars().count() > 4500 {
            out.push(format!("a line of {} characters", line.chars().count()));
        }
        let digits = line
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .map(|run| run.bytes().filter(u8::is_ascii_digit).count())
            .max()
            .unwrap_or(0);
        if digits >= 22 {
            out.push(format!("a number of {digits} digits: {}", cut(line)));
        }
        for debug in [
            "Unit(\"",
            "Some(",
            "AnalogRange {",
            "RawRange {",
            "Scale {",
            "invalid type: null",
        ] {
            if line.contains(debug) {
                out.push(format!("{debug:?} in: {}", cut(line)));
            }
        }
    }
    out
}

fn cut(s: &str) -> String {
    s.chars().take(300).collect()
}

/// Every number of every shipped example replaced, one at a time, by each of
/// [`HOSTILE_NUMBERS`]: an answer for each, no panic, and its text clean.
#[test]
fn every_number_of_the_examples_made_hostile() {
    let mut examples = vec![("demo.toml".to_string(), hwgw::DEMO.to_string())];
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../config");
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            examples.push((
                path.display().to_string(),
                std::fs::read_to_string(&path).unwrap(),
            ));
        }
    }
    let (mut tried, mut refused, mut bad) = (0u64, 0u64, Vec::new());
    for (file, text) in &examples {
        let lines: Vec<&str> = text.lines().collect();
        for (n, line) in lines.iter().enumerate() {
            for r in numbers(line) {
                for v in HOSTILE_NUMBERS {
                    let mut changed = line.to_string();
                    changed.replace_range(r.clone(), v);
                    let mut all = lines.clone();
                    all[n] = &changed;
                    tried += 1;
                    match check(&all.join("\n"), file) {
                        Ok(answer) => {
                            refused += u64::from(answer != "ok");
                            for p in text_problems(&answer) {
                                bad.push(format!("{file}:{}: {changed}: {p}", n + 1));
                            }
                            let non_finite = ["nan", "-nan", "inf", "-inf"].contains(&v);
                            if non_finite
                                && !(answer.contains("is NaN") || answer.contains("is infinite"))
                            {
                                bad.push(format!(
                                    "{file}:{}: {changed}: not named: {}",
                                    n + 1,
                                    cut(&answer)
                                ));
                            }
                        }
                        Err(panic) => {
                            bad.push(format!("{file}:{}: {changed}: panic: {panic}", n + 1))
                        }
                    }
                }
            }
        }
    }
    eprintln!(
        "hostile numbers: {tried} tried, {refused} refused, {} bad",
        bad.len()
    );
    assert!(tried > 1000, "the examples' numbers were found: {tried}");
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

#[test]
fn mutated_examples_get_an_answer_never_a_panic() {
    let cases: u64 = std::env::var("CONFIG_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(200);
    let seed: u64 = std::env::var("CONFIG_FUZZ_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0xC0F1_6F22);
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../config");
    let mut examples = vec![("demo.toml".to_string(), hwgw::DEMO.to_string())];
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let text = std::fs::read_to_string(&path).unwrap();
            examples.push((path.display().to_string(), text));
        }
    }
    // Checked from an empty directory of its own: it must stay empty.
    let cwd = std::env::temp_dir().join(format!("hwgw-config-fuzz-{}", std::process::id()));
    std::fs::create_dir_all(&cwd).unwrap();
    std::env::set_current_dir(&cwd).unwrap();
    let (jobs, work) = mpsc::channel::<(String, String)>();
    let (answers, answered) = mpsc::channel();
    std::thread::spawn(move || {
        for (text, file) in work {
            if answers.send(check(&text, &file)).is_err() {
                break;
            }
        }
    });
    let mut rng = Rng::new(seed);
    let (mut ok, mut refused, mut panics) = (0u64, 0u64, Vec::new());
    for (file, text) in &examples {
        for case in 0..cases {
            let mutated = mutate(text, &mut rng);
            jobs.send((mutated.clone(), file.clone())).unwrap();
            match answered.recv_timeout(BOUND) {
                Ok(Ok(answer)) if answer == "ok" => ok += 1,
                Ok(Ok(answer)) => {
                    refused += 1;
                    for p in text_problems(&answer) {
                        panics.push(format!("{file} case {case}: {p}"));
                    }
                }
                Ok(Err(panic)) => panics.push(format!("{file} case {case}: {panic}")),
                Err(_) => panic!(
                    "{file} case {case}: no answer within {BOUND:?} for:\n{}",
                    mutated.chars().take(4000).collect::<String>()
                ),
            }
        }
    }
    let left: Vec<_> = std::fs::read_dir(&cwd).unwrap().collect();
    let _ = std::fs::remove_dir_all(&cwd);
    eprintln!(
        "config fuzz: {} examples x {cases} cases: {ok} ok, {refused} refused, {} panics",
        examples.len(),
        panics.len()
    );
    assert!(
        panics.is_empty(),
        "panics and unclean answers:\n{}",
        panics.join("\n")
    );
    assert!(left.is_empty(), "checking wrote files: {left:?}");
    assert!(refused > 0 && ok > 0, "the mutations reach both answers");
}
